"""What the rig tests share: the paper's controller file, the scenario they run, the control
period, the staleness rule's expected fault time, and the example C driver compiled."""

from __future__ import annotations

import math
import shutil
import subprocess
from pathlib import Path

import pytest

from pneutune.control.sim.scenarios import SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
C_DRIVER = ROOT / "docs" / "examples" / "rig_driver.c"
#: rig.Ts of data/controller-paper.yaml [s].
TS = 0.004
SINE = SCENARIOS["sine-0.5hz"]
#: limits.sensor_timeout_s of data/controller-paper.yaml [s].
TIMEOUT = 0.02


def first_stale_time(t_fault: float) -> float:
    """A channel that stops at t_fault was last new at t_fault - Ts; the fault comes at the
    first sample more than the timeout later."""
    k_last = round(t_fault / TS) - 1
    return (k_last + math.floor(TIMEOUT / TS + 1e-9) + 1) * TS


def compile_c_driver(folder: Path) -> Path:
    """docs/examples/rig_driver.c compiled with gcc into ``folder``, warning-free under
    -std=c99 -Wall -Wextra -Wpedantic -Werror (as docs/deploy.md builds it); skip without gcc."""
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc is not installed")
    exe = folder / "rig_driver"
    proc = subprocess.run([gcc, "-std=c99", "-O2", "-Wall", "-Wextra", "-Wpedantic", "-Werror",
                           "-o", str(exe), str(C_DRIVER), "-lm"],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    return exe
