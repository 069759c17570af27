"""Dead-zone handling of the duty logic (contract 4 ``dead_zone``): the knee of the PWM curve,
the sigma-delta dither across PWM periods, and its path through the config, the step and tune."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pneutune.control.contracts.controller import (
    PAPER_CONTROLLER,
    ControllerConfig,
    load_controller,
)
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.contracts.yamlio import validate_model
from pneutune.control.errors import ConfigError
from pneutune.control.law.duty import dead_zone_knee, dither_into, pwm_inverse
from pneutune.control.law.layout import (
    CFG_DZ_DUTY,
    CFG_DZ_MODE,
    CFG_DZ_RATIO,
    CFG_PWM_PERIOD,
    pack,
)
from pneutune.control.physics.pwm import sample_pwm_curve
from pneutune.control.plant.dynamics import initial_state
from pneutune.control.plant.params import pack_plant
from pneutune.control.plant.valves import open_fractions
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS
from pneutune.tune.objective import ObjectiveSettings, TuneError
from pneutune.tune.study import default_study_name

# Default plant valves at 60 Hz: the dead-zone jump at duty 1.5 ms * 60 Hz = 0.09 lifts the
# effective fraction from 0 to (1.5 ms + 3 ms - 2 ms) * 60 Hz = 0.15.
PERIOD, D_ON, D_OFF, MIN_PULSE = 1.0 / 60.0, 2.0e-3, 3.0e-3, 1.5e-3
TS = 0.004


def _paper(dead_zone: str) -> ControllerConfig:
    data = load_controller(PAPER_CONTROLLER).to_dict()
    data["dead_zone"] = dead_zone
    return ControllerConfig.model_validate(data)


def test_knee_of_the_plant_curve_is_its_jump() -> None:
    """A curve computed from the valves jumps at the minimum pulse: the knee is the top of the
    jump, (0.09, 0.15) (values from the module constants above)."""
    duty, ratio = (np.array(v) for v in sample_pwm_curve(PERIOD, D_ON, D_OFF, MIN_PULSE, 41))
    d_k, r_k = dead_zone_knee(duty, ratio)
    assert d_k == pytest.approx(MIN_PULSE / PERIOD, abs=1e-12)
    assert r_k == pytest.approx((MIN_PULSE + D_OFF - D_ON) / PERIOD, abs=1e-12)


def test_knee_of_a_gridded_curve_is_the_end_of_its_steep_rise() -> None:
    """An identified curve has no vertical step, only a steep segment on its duty grid (as in
    fleet plant 0's model): the knee is that segment's end; small noisy ratios before it and a
    second, milder rise after it do not move it."""
    duty = [0.0, 0.0125, 0.025, 0.05, 0.0625, 0.075, 0.0875, 0.1, 0.5, 0.94, 1.0]
    ratio = [0.0, 0.0, 0.003, 0.009, 0.02, 0.119, 0.125, 0.131, 0.52, 1.0, 1.0]
    assert dead_zone_knee(duty, ratio) == (0.075, 0.119)


def test_a_curve_without_a_dead_zone_has_no_knee() -> None:
    """Effective fraction = duty (no minimum pulse, equal delays): nothing to dither."""
    assert dead_zone_knee([0.0, 1.0], [0.0, 1.0]) == (0.0, 0.0)
    assert dead_zone_knee([0.0, 0.5, 1.0], [0.0, 0.4, 1.0]) == (0.0, 0.0)


@pytest.mark.parametrize("update", ["immediate", "latched"])
@pytest.mark.parametrize("wanted", [0.01, 0.05, 0.12])
def test_dither_delivers_the_wanted_mean_through_the_plant_valves(update: str,
                                                                  wanted: float) -> None:
    """Duties written every 4 ms by the dither, switched by the plant's own valves (carrier,
    delays, minimum pulse; :func:`open_fractions`) for 12 s: the mean open fraction is the wanted
    one within one pulse over the run (0.15 / 180 periods < 1e-3). Rounding up gives the knee's
    0.15 whatever is wanted (the error dithering removes)."""
    plant = PlantConfig().with_updates({"rig": {"pwm_update": update}})
    p = pack_plant(plant).vec
    duty, ratio = (np.array(v) for v in sample_pwm_curve(PERIOD, D_ON, D_OFF, MIN_PULSE, 41))
    d_k, r_k = dead_zone_knee(duty, ratio)
    n = 3000
    u = np.array([wanted, 0.0, 0.0, wanted])
    dithered = np.zeros((n, 4))
    rounded = np.zeros((n, 4))
    acc, pulse, last = np.full(4, 0.5 * r_k), np.zeros(4), np.array([-1.0])  # as init_state
    for k in range(n):
        d = np.array([pwm_inverse(x, duty, ratio) for x in u])
        rounded[k] = d
        dither_into(u, d, k * TS, TS, PERIOD, np.full(4, d_k), np.full(4, r_k), acc, pulse,
                    last)
        dithered[k] = d
    for duties, expected in ((dithered, wanted), (rounded, r_k)):
        out = np.zeros((n, 4))
        open_fractions(p, initial_state(p, 0.02, 2e5, 2e5), duties, 0.0, TS, out)
        assert out[:, 0].mean() == pytest.approx(expected, abs=1e-3)
        assert out[:, 3].mean() == pytest.approx(expected, abs=1e-3)
        assert out[:, 1].max() == 0.0 and out[:, 2].max() == 0.0
    # whole periods: every dithered duty is the knee's or 0, and the first wanted period pulses
    assert set(np.unique(dithered[:, 0])) <= {0.0, d_k}
    assert dithered[0, 0] == d_k


def test_dither_uses_each_valves_own_knee() -> None:
    """One curve per valve: a_in's knee (0.09, 0.15) and b_out's (0.15, 0.25), both wanting 0.05.
    Over 300 PWM periods a_in pulses in a third of them (0.05 / 0.15), b_out in a fifth
    (0.05 / 0.25), each with its own knee's duty (the sigma-delta's count is exact to one
    pulse)."""
    d_k = np.array([0.09, 0.0, 0.0, 0.15])
    r_k = np.array([0.15, 0.0, 0.0, 0.25])
    u = np.array([0.05, 0.0, 0.0, 0.05])
    acc, pulse, last = 0.5 * r_k, np.zeros(4), np.array([-1.0])
    periods = 300
    n = round(periods * PERIOD / TS)
    seen = np.zeros((n, 4))
    for k in range(n):
        d = np.array([0.09, 0.0, 0.0, 0.15])  # what the inverse gives: each valve's knee
        dither_into(u, d, k * TS, TS, PERIOD, d_k, r_k, acc, pulse, last)
        seen[k] = d
    assert set(np.unique(seen[:, 0])) == {0.0, 0.09}
    assert set(np.unique(seen[:, 3])) == {0.0, 0.15}
    starts = (np.floor(np.arange(n) * TS / PERIOD) != np.floor((np.arange(n) - 1) * TS / PERIOD))
    assert np.count_nonzero(seen[starts, 0] > 0) == pytest.approx(periods / 3, abs=1)
    assert np.count_nonzero(seen[starts, 3] > 0) == pytest.approx(periods / 5, abs=1)


def test_dither_leaves_openings_above_the_knee_alone() -> None:
    """u >= r_k is deliverable in one period: the inverse's duty is kept."""
    duty, ratio = (np.array(v) for v in sample_pwm_curve(PERIOD, D_ON, D_OFF, MIN_PULSE, 41))
    d_k, r_k = dead_zone_knee(duty, ratio)
    u = np.array([0.5, 0.0, 0.0, r_k])
    d = np.array([pwm_inverse(x, duty, ratio) for x in u])
    before = d.copy()
    dither_into(u, d, 0.0, TS, PERIOD, np.full(4, d_k), np.full(4, r_k), np.zeros(4),
                np.zeros(4), np.array([-1.0]))
    np.testing.assert_array_equal(d, before)


def test_dead_zone_key_in_the_config_and_the_packed_vector() -> None:
    """Default ``up``; ``dither`` packs the knee and the carrier period; a misspelt value is a
    ConfigError naming the key."""
    up = load_controller(PAPER_CONTROLLER)
    assert up.dead_zone == "up"
    v = pack(_paper("dither"))
    assert v[CFG_DZ_MODE] == 1.0 and pack(up)[CFG_DZ_MODE] == 0.0
    assert v[CFG_PWM_PERIOD] == pytest.approx(1.0 / 60.0)
    for i in range(4):  # the paper's valves share the top-level curve
        assert (v[CFG_DZ_DUTY + i], v[CFG_DZ_RATIO + i]) == dead_zone_knee(up.pwm.duty,
                                                                             up.pwm.ratio)
    with pytest.raises(ConfigError, match="dead_zone"):
        validate_model(ControllerConfig, {**up.to_dict(), "dead_zone": "dithered"}, "c.yaml")


def test_dithering_controller_commands_only_whole_pulses_in_the_dead_zone() -> None:
    """The paper's controller on the paper's rig, sine-0.5hz, 3 s: with ``dither`` every duty
    below the knee's is 0 (the knee's own duty is the pulse), with ``up`` some are not (the
    inverse's duties between 0 and the knee; here the knee is a vertical jump, so ``up``
    commands it exactly, and the runs must still differ, the dither skipping periods)."""
    sc = dataclasses.replace(SCENARIOS["sine-0.5hz"], duration=3.0)
    runs = {m: simulate_scenario(_paper(m), sc, PlantConfig(), seed=1) for m in ("up", "dither")}
    for res in runs.values():
        assert res.metrics.status == "ok"
    d_k = 0.09
    dith = runs["dither"].duties
    assert not np.any((dith > 1e-12) & (dith < d_k - 1e-12))
    # up commands the knee in every period it is wanted; dither skips some of those periods
    n_knee = {m: int(np.count_nonzero(np.isclose(r.duties, d_k))) for m, r in runs.items()}
    n_zero = {m: int(np.count_nonzero(r.duties == 0.0)) for m, r in runs.items()}
    assert n_zero["dither"] > n_zero["up"]
    assert n_knee["up"] > 0


def test_tune_keeps_the_dead_zone_in_the_study_name_and_settings() -> None:
    """``tune --dead-zone dither`` is its own study; ``up`` leaves old names and settings as they
    were (studies made before the key existed resume)."""
    assert default_study_name("ab" * 32, 1) == "tune-abababababab-seed1"
    assert default_study_name("ab" * 32, 1, dead_zone="dither") == "tune-abababababab-seed1-dither"
    assert "dead_zone" not in ObjectiveSettings().to_dict()
    assert ObjectiveSettings(dead_zone="dither").to_dict()["dead_zone"] == "dither"
    with pytest.raises(TuneError, match=r"^dead_zone must be one of"):
        ObjectiveSettings(dead_zone="down")
