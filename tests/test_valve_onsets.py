"""The step onsets of the valves: the delay from a full-opening command to the chamber pressure.

data/run.mcap is the 0.5 ms identification run of the paper's rig as simulated by default
(``PlantConfig()``: every valve opens 2 ms after its command, no IO delay), so each valve's
onset is 2 ms. A rig whose duties act 2 ms after their samples (``io.delay``) adds those 2 ms:
4 ms. The tolerances are the onset grid's 0.1 ms plus the spread the noise gives over five or
six edges (measured: 1.95-2.00 ms on data/run.mcap, 4.05-4.20 ms with the IO delay).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.constants import VALVES
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.rig.identification_run import simulate_identification
from pneutune.identify.dataset import load_dataset
from pneutune.identify.pipeline import identify
from pneutune.identify.valve_onsets import MIN_EDGES, step_onsets
from pneutune.identify.valves import ONSET_MARGIN

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "data" / "run.mcap"
PLANT = PlantConfig()
C = np.full(4, PLANT.valves.a_in.C)
B = np.full(4, PLANT.valves.a_in.b)
MAX_DELAY = 0.5 / PLANT.rig.pwm_hz


def test_onsets_of_the_simulated_rig_are_its_opening_delays() -> None:
    """Every valve of data/run.mcap: onset within 0.15 ms of its 2 ms opening delay, and its
    range holding it."""
    onsets = step_onsets([load_dataset(RUN)], C, B, MAX_DELAY)
    true = PLANT.valves.a_in.delay_on
    for on in onsets:
        assert on is not None
        assert on.edges >= MIN_EDGES
        assert on.delay == pytest.approx(true, abs=1.5e-4)
        assert on.low - 1e-12 <= true <= on.high + 1e-12


def test_no_onsets_where_the_log_cannot_time_them() -> None:
    """A latched PWM update starts a command at the next carrier period (unknown here), and a
    log at the 4 ms control rate has no shape to fit: no onsets, rather than wrong ones."""
    d = load_dataset(RUN)
    latched = dataclasses.replace(d, rig=d.rig.model_copy(update={"pwm_update": "latched"}))
    assert step_onsets([latched], C, B, MAX_DELAY) == [None] * 4
    assert step_onsets([d.at_control_rate()], C, B, MAX_DELAY) == [None] * 4


@pytest.mark.slow
def test_an_io_delay_adds_to_the_onsets_and_bounds_the_fitted_delays(tmp_path: Path) -> None:
    """The paper's rig with a 2 ms IO delay: every onset 4 ms (±0.25 ms), and identify's
    opening delays plus its IO delay inside each valve's onset range (its margin added). Before
    the onsets bounded them, the control-rate search put two of the four at 2.2 and 2.9 ms."""
    plant = PLANT.with_updates({"io": {"delay": 2.0e-3}})
    rec = simulate_identification(plant, seed=1)
    path = tmp_path / "io-delay.mcap"
    rec.save(path, rig=plant.rig_metadata(), run={"seed": "1", "experiment": "identification"})
    onsets = step_onsets([load_dataset(path)], C, B, MAX_DELAY)
    true = plant.io.delay + plant.valves.a_in.delay_on
    for on in onsets:
        assert on is not None
        assert on.delay == pytest.approx(true, abs=2.5e-4)
    model = identify(path, seed=0).model
    io = model.effects["io.delay"].nominal if model.effects else 0.0
    for on, name in zip(onsets, VALVES, strict=True):
        v = getattr(model.valves, name)
        assert on is not None
        assert on.low - ONSET_MARGIN - 1e-9 <= v.delay_on + io <= on.high + ONSET_MARGIN + 1e-9
    assert model.loop_delay is not None
    lo, hi = model.loop_delay.range
    assert lo <= true <= hi
