"""One PWM curve per valve (``valves.<v>.pwm`` of contracts 3 and 4).

The plant here is the paper's rig with b_out slower than the others: a minimum pulse of 2.5 ms
against a_in's 1.5 ms (fleet plants differ by up to 2x, benchmarks/fleet.py). Its curves are
what :func:`~pneutune.control.physics.pwm.sample_pwm_curve` computes from each valve's timing,
the one implementation the plant switches its valves by (:mod:`pneutune.control.plant.valves`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pneutune.control.contracts.controller import PAPER_CONTROLLER, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.duty import dead_zone_knee, pwm_inverse
from pneutune.control.physics.pwm import sample_pwm_curve
from pneutune.control.plant.dynamics import initial_state
from pneutune.control.plant.params import pack_plant
from pneutune.control.plant.valves import open_fractions
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.space import controller_from_params, search_space

TS = 0.004
SLOW = {"delay_on": 3.0e-3, "delay_off": 2.0e-3, "min_pulse": 2.5e-3}


def _plant() -> PlantConfig:
    return PlantConfig().with_updates({"valves": {"b_out": SLOW}})


def _controller(per_valve: bool):
    model = model_from_plant(_plant())
    if not per_valve:
        data = model.to_dict()
        del data["valves"]["b_out"]["pwm"]
        model = type(model).model_validate(data)
    return controller_from_params(model, search_space(model).paper_params())


def test_truth_model_has_a_curve_only_for_a_valve_unlike_a_in() -> None:
    """The paper's rig has four equal valves: no valve has a curve of its own. With b_out slowed,
    b_out gets the curve of its own timing, the others none, and tune's controller carries it."""
    assert all(v.pwm is None for v in model_from_plant(PlantConfig()).valves.ordered())
    model = model_from_plant(_plant())
    assert [v.pwm is not None for v in model.valves.ordered()] == [False, False, False, True]
    duty, ratio = sample_pwm_curve(1.0 / 60.0, SLOW["delay_on"], SLOW["delay_off"],
                                   SLOW["min_pulse"])
    assert model.valves.b_out.pwm.duty == pytest.approx(duty, abs=1e-15)
    assert model.valves.b_out.pwm.ratio == pytest.approx(ratio, abs=1e-15)
    cfg = _controller(per_valve=True)
    assert cfg.valves.b_out.pwm == model.valves.b_out.pwm and cfg.valves.a_in.pwm is None
    # the knees: b_out's smallest opening pulse is 2.5 ms of 16.7 ms (duty 0.15), a_in's 1.5 ms
    assert dead_zone_knee(cfg.valve_curves[3].duty, cfg.valve_curves[3].ratio)[0] == \
        pytest.approx(0.15, abs=1e-9)
    assert dead_zone_knee(cfg.valve_curves[0].duty, cfg.valve_curves[0].ratio)[0] == \
        pytest.approx(0.09, abs=1e-9)
    assert pwm_inverse(0.01, np.array(cfg.valve_curves[3].duty),
                       np.array(cfg.valve_curves[3].ratio)) == pytest.approx(0.15, abs=1e-9)
    assert pwm_inverse(0.01, np.array(cfg.pwm.duty),
                       np.array(cfg.pwm.ratio)) == pytest.approx(0.09, abs=1e-9)


@pytest.mark.parametrize("wanted", [0.3, 0.6])
def test_each_valve_delivers_the_wanted_fraction_through_its_own_curve(wanted: float) -> None:
    """Duties from each valve's own curve, held for 12 s and switched by the plant's own valves
    (:func:`open_fractions`): a_in and b_out are open for the wanted fraction of the time, within
    the interpolation error of a curve sampled on 41 duties (0.01). On a_in's curve, b_out is
    open 0.05 or more less than wanted (its delays differ: the error one curve per valve
    removes)."""
    plant = _plant()
    p = pack_plant(plant).vec
    n = 3000
    frac = {}
    for per_valve in (True, False):
        curves = _controller(per_valve).valve_curves
        d = [pwm_inverse(wanted, np.array(c.duty), np.array(c.ratio)) for c in curves]
        duties = np.tile([d[0], 0.0, 0.0, d[3]], (n, 1))
        out = np.zeros((n, 4))
        open_fractions(p, initial_state(p, 0.02, 2e5, 2e5), duties, 0.0, TS, out)
        frac[per_valve] = out.mean(axis=0)
    assert frac[True][0] == pytest.approx(wanted, abs=0.01)
    assert frac[True][3] == pytest.approx(wanted, abs=0.01)
    assert frac[False][3] < wanted - 0.05


def test_closed_loop_never_commands_b_out_a_pulse_too_short_to_open_it() -> None:
    """The paper's gains on the slowed plant, sine-0.5hz, 4 s. With b_out's own curve every
    nonzero b_out duty opens it (at least its minimum pulse, 2.5 ms = duty 0.15); on a_in's
    curve some are 0.09-0.15, pulses b_out never opens on."""
    sc = dataclasses.replace(SCENARIOS["sine-0.5hz"], duration=4.0)
    plant = _plant()
    short = {}
    for per_valve in (True, False):
        res = simulate_scenario(_controller(per_valve), sc, plant, seed=1)
        d = res.duties[:, 3]
        short[per_valve] = int(np.count_nonzero((d > 0.0) & (d < 0.15 - 1e-9)))
    assert short[True] == 0
    assert short[False] > 0


def test_paper_controller_is_unchanged_by_the_per_valve_layout() -> None:
    """The paper's file has no valve curves: every valve inverts the top-level curve."""
    cfg = load_controller(PAPER_CONTROLLER)
    assert all(c is cfg.pwm for c in cfg.valve_curves)
