"""A seeded identification run repeats bit for bit in another process (seeds go
into constructors, no global random state), and another seed gives another log."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.logs.reader import read_run_log

SIMULATE = Path(sys.executable).with_name("simulate")


def _simulate(out: Path, seed: int) -> dict:
    """Run the ``simulate`` console script in a fresh process; return its --json summary."""
    proc = subprocess.run(
        [str(SIMULATE), "--experiment", "identification", "--seed", str(seed), "--out", str(out),
         "--json"],
        capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow  # two fresh processes, each loading every compiled kernel: about 22 s
def test_seeded_identification_run_is_identical_in_two_processes(tmp_path: Path) -> None:
    first = _simulate(tmp_path / "a.mcap", 3)
    second = _simulate(tmp_path / "b.mcap", 3)
    other = _simulate(tmp_path / "c.mcap", 4)

    a, b, c = (_sha256(tmp_path / name) for name in ("a.mcap", "b.mcap", "c.mcap"))
    # same seed: the same bytes (the output path is not part of the log)
    assert a == b
    assert first["sha256"] == second["sha256"] == a
    assert first["seed"] == second["seed"] == 3
    assert first["samples"] == second["samples"] > 0
    # another seed: same protocol and length, other sensor noise, so other bytes
    assert other["seed"] == 4
    assert other["samples"] == first["samples"]
    assert c != a
    assert other["sha256"] == c
    # ... and not only in the ``run`` metadata: the sensor noise differs, while the truth of the
    # open-loop start (rest:start; the approach onto the first end stop reads the sensors)
    # does not
    log_a, log_c = read_run_log(tmp_path / "a.mcap"), read_run_log(tmp_path / "c.mcap")
    assert log_a.run["seed"] == "3" and log_c.run["seed"] == "4"
    sens_a, sens_c = log_a["/rig/sensors"], log_c["/rig/sensors"]
    assert sens_a.shape == sens_c.shape
    assert not np.array_equal(sens_a.to_numpy(), sens_c.to_numpy())
    open_loop = log_a["/sim/truth"].index < 2.0  # rest:start (segment table)
    np.testing.assert_array_equal(log_a["/sim/truth"].to_numpy()[open_loop],
                                  log_c["/sim/truth"].to_numpy()[open_loop])
