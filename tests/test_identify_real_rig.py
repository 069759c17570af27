"""identify on a rig with dynamics its model lacks: what it says must be true of the log.

The loop delay: a closed-loop log of a rig whose duties act 2 ms after their samples.

The log is the 0.5 ms identification run of the paper's rig with a 2 ms pressure-transmitter
lag (``sensors.p_lag``), typical of an industrial transmitter (10-90 % response of a few ms).
The lag puts the measured pressure force several times further behind the motion than the
0.3 ms lag that carries the mass, so no mass estimate is usable and the prior must stand; the
notes must say so without printing an impossible interval, and must not advise a faster
sampling than the log already has.

The valves' b: the identification run of the paper's rig with every real-rig effect at its
typical magnitude (lines in series with the valves, armature and transmitter lags among them),
whose full-opening charges and vents follow ISO 6358's curve for no b.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.rig.identification_run import simulate_identification
from pneutune.control.sim import rig_effects
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS
from pneutune.identify.pipeline import identify

ROOT = Path(__file__).resolve().parents[1]

LAGGED = PlantConfig().with_updates({"sensors": {"p_lag": 2.0e-3}})


@pytest.mark.slow
def test_mass_notes_on_a_lagging_transmitter_are_true(tmp_path: Path) -> None:
    """No interval whose ends are reversed or that reaches below zero as if it were a range,
    no advice to log every 0.5 ms on a 0.5 ms log, and the mass range is the geometry prior
    (the estimate is unusable, so identify must fall back, not use it)."""
    rec = simulate_identification(LAGGED, seed=1)
    path = tmp_path / "lagged.mcap"
    rec.save(path, rig=LAGGED.rig_metadata(), run={"seed": "1",
                                                    "experiment": "identification"})
    assert rec.Ts == pytest.approx(5.0e-4)  # the log the advice would ask for
    res = identify(path, seed=0)
    mass_notes = [n for n in res.notes if n.startswith("mass:")]
    assert mass_notes, res.notes
    text = " ".join(mass_notes)
    # an interval [lo, hi] with hi < lo, or [0, negative], is not a range
    for lo, hi in re.findall(r"\[(-?[\d.e+-]+), (-?[\d.e+-]+)\] kg", text):
        assert float(lo) <= float(hi), text
    assert "logged every 0.5 ms resolves" not in text
    assert "record --sample-period" not in text
    # the prior from the cylinder geometry stands, and holds the true 1.05 kg
    assert "prior from the cylinder geometry" in res.mass_basis, res.mass_basis
    assert res.mass_range[0] <= LAGGED.total_mass <= res.mass_range[1]


@pytest.mark.slow
def test_a_closed_loop_log_gives_the_loop_delay_of_a_rig_with_an_io_delay(tmp_path: Path
                                                                          ) -> None:
    """A 12 s closed-loop log at 4 ms (the paper's gains on sine-0.5hz, as ``deploy --log``
    writes it) of the paper's rig with a 2 ms IO delay: the whole loop delay, from a written
    duty to the chamber flow, is the IO delay plus a valve's opening delay (2 ms here), 4 ms.
    model.yaml's ``loop_delay`` range must hold it; the log cannot tell the IO delay from the
    valves' own (their duties change every sample), so the valves' delays carry it and
    ``effects.io.delay`` states what is left beyond them."""
    plant = PlantConfig().with_updates({"io": {"delay": 2.0e-3}})
    ctl = load_controller(ROOT / "data" / "controller-paper.yaml")
    res = simulate_scenario(ctl, SCENARIOS["sine-0.5hz"], plant, seed=2)
    path = tmp_path / "closed-loop.mcap"
    res.recording().save(path, rig=plant.rig_metadata(), run={"seed": "2"})
    model = identify(path, seed=0).model
    true_loop = plant.io.delay + plant.valves.a_in.delay_on
    assert model.loop_delay is not None
    lo, hi = model.loop_delay.range
    assert lo <= true_loop <= hi, (lo, true_loop, hi)
    # and it says something: narrower than a PWM period's tenth either side (1.7 ms)
    assert hi - lo < 0.2 / plant.rig.pwm_hz
    assert model.effects is not None and "io.delay" in model.effects


@pytest.mark.slow
def test_b_at_its_bound_on_a_rig_with_lines_gets_a_true_note(tmp_path: Path) -> None:
    """Every valve was held fully open for 1.5-8 s, yet the line in series bends its charges and
    vents so that the fit puts b at its bound 0 (measured: about 1e-13 on all four). The note
    must say that, and must not ask for the charges and vents this log already has."""
    plant = PlantConfig().with_updates(rig_effects.plant_updates(rig_effects.typical()))
    rec = simulate_identification(plant, seed=1)
    path = tmp_path / "effects.mcap"
    rec.save(path, rig=plant.rig_metadata(), run={"seed": "1", "experiment": "identification"})
    res = identify(path, seed=0)
    pinned = [n for n in res.notes if "put b at its bound" in n]
    assert len(pinned) == 4, res.notes
    assert not [n for n in res.notes if "needs charges or vents" in n], res.notes
    for name in ("a_in", "a_out", "b_in", "b_out"):
        v = getattr(res.model.valves, name)
        assert v.b < 1e-3 and v.b_min == 0.0, (name, v.b_min, v.b, v.b_max)
        assert any(n.startswith(f"valve {name}: the fit put b at its bound") for n in pinned)
