"""What the supervisor's and the homing tests share: the paper's controller file, the scenario
they run, the control period and the staleness rule's expected fault time."""

from __future__ import annotations

import math
from pathlib import Path

from pneutune.control.sim.scenarios import SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
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
