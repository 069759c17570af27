"""Transmitters at the valves' side of a line, told from the log (identify/transmitters.py).

Chamber A's valve tests of the identification run (0.5 ms samples, the piston held on its
stop) on the paper's plant with 0.3 m lines (1.71e-8 m^3/(s Pa)), the transmitters at the
valves or at the chambers. Expected values come from the physics: a chamber charged through its
inlet alone cannot lose pressure and one vented through its exhaust alone cannot gain any, so
a chamber's reading gives folded z-scores of about 2 (the most extreme of ~33 phase bins of
noise); a reading at the valves steps by the line's pressure drop each time a valve closes
(measured: median z 21 charging and 39 venting at 300 Pa noise)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.rig.excitation import record_on_sim
from pneutune.identify.dataset import load_dataset
from pneutune.identify.transmitters import Z_LEAD, check_transmitters

LINES = {"lines": {"a": {"delay": 9.0e-4, "volume": 3.8e-6, "C": 1.71e-8},
                   "b": {"delay": 9.0e-4, "volume": 3.8e-6, "C": 1.71e-8}}}


def _valve_tests(tmp_path: Path, p_at: str):
    plant = PlantConfig().with_updates(LINES).with_updates({"sensors": {"p_at": p_at}})
    run = record_on_sim("identification", plant, seed=3, sample_period=5.0e-4,
                        segments="valves:a")
    path = tmp_path / f"{p_at}.mcap"
    run.recording.save(path, rig=plant.rig_metadata(), run={"seed": "3"})
    return check_transmitters([load_dataset(path)])


@pytest.mark.parametrize("p_at", ["chamber", "valves"])
def test_a_reading_at_the_valves_steps_when_a_valve_closes(tmp_path: Path, p_at: str) -> None:
    """Only chamber A's valves pulse in these segments, so only A is judged; at the chamber
    its medians stay under 3, at the valves both pass Z_LEAD = 6 and identify's note names
    it."""
    check = _valve_tests(tmp_path, p_at)
    assert check is not None
    assert set(check.charge) == {"a"}
    assert min(check.stretches["a"]) >= 3
    if p_at == "chamber":
        assert check.charge["a"] < 3.0 and check.vent["a"] < 3.0
        assert check.at_valves == ()
        assert check.note() is None
    else:
        assert check.charge["a"] > 2 * Z_LEAD and check.vent["a"] > 2 * Z_LEAD
        assert check.at_valves == ("a",)
        assert "chamber A's" in (check.note() or "")
