"""Every benchmark script with options answers ``--help`` (exit 0, a usage line).

``benchmarks/fleet.py --help`` once crashed in argparse on a ``%`` in a help string; a script a
user cannot ask for its options is a dead end (README, "Benchmarks").
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
WITH_OPTIONS = sorted(p for p in BENCHMARKS.glob("*.py") if "ArgumentParser" in p.read_text())


def test_the_benchmarks_with_options_are_found() -> None:
    # fleet.py, tune_speed.py and other_sim.py are documented with options in the README/docs
    names = {p.name for p in WITH_OPTIONS}
    assert {"fleet.py", "tune_speed.py", "other_sim.py"} <= names, names


@pytest.mark.parametrize("script", WITH_OPTIONS, ids=lambda p: p.name)
def test_help_exits_zero_with_a_usage_line(script: Path) -> None:
    proc = subprocess.run([sys.executable, str(script), "--help"], capture_output=True,
                          text=True, timeout=120, cwd=BENCHMARKS.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("usage:"), proc.stdout[:200]
