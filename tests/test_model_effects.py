"""model.yaml's ``effects`` block: real-rig effects a model carries into tune's plant draws.

The block maps a plant.yaml key (IO delay, sensor lags, valve armature lags) to the value of the
nominal plant and the range the draws sample. A model without it gives exactly the plants and
the box it gave before the block existed.
"""

from __future__ import annotations

from typing import Any

import pytest

from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.contracts.yamlio import validate_model
from pneutune.control.errors import ConfigError
from pneutune.control.sim.model_box import corner, nominal_plant, uncertainty_box
from pneutune.control.sim.truth import model_from_plant

BASE = model_from_plant(PlantConfig())
EFFECTS = {"io.delay": {"nominal": 1.0e-3, "range": [0.5e-3, 2.0e-3]},
           "sensors.p_lag": {"nominal": 4.0e-4, "range": [0.0, 1.0e-3]},
           "valves.a_in.tau_open": {"nominal": 5.0e-4, "range": [5.0e-4, 5.0e-4]}}


def _with(effects: dict[str, Any]) -> ModelConfig:
    data = BASE.to_dict()
    data["effects"] = effects
    return validate_model(ModelConfig, data, "<model with effects>")


def test_the_nominal_plant_carries_the_effects_at_their_nominal_values() -> None:
    plant = nominal_plant(_with(EFFECTS))
    assert plant.io.delay == 1.0e-3
    assert plant.sensors.p_lag == 4.0e-4
    assert plant.valves.a_in.tau_open == 5.0e-4
    assert set(plant.effects) == {"IO delay", "sensor lag", "valve lag"}


def test_the_box_samples_each_effect_range_and_the_slow_corner_has_the_most_lag() -> None:
    coords = {c.key: c for c in uncertainty_box(_with(EFFECTS))}
    assert (coords["io.delay"].low, coords["io.delay"].high) == (0.5e-3, 2.0e-3)
    assert (coords["sensors.p_lag"].low, coords["sensors.p_lag"].high) == (0.0, 1.0e-3)
    # a single value is no coordinate: the nominal plant already has it
    assert "valves.a_in.tau_open" not in coords
    slow = corner(tuple(coords.values()), slow=True)
    assert slow["io.delay"] == 2.0e-3 and slow["sensors.p_lag"] == 1.0e-3


def test_a_model_without_effects_gives_the_box_and_plant_it_gave_before() -> None:
    """The block is optional: absent, no coordinate and no plant key changes (the paper's rig
    read back from its own model is the paper's rig)."""
    assert BASE.effects is None
    keys = [c.key for c in uncertainty_box(BASE)]
    assert not any(k.startswith(("io.", "sensors.", "lines.")) or "tau_" in k for k in keys)
    assert nominal_plant(BASE).effects == ()


@pytest.mark.parametrize("effects, key", [
    ({"io.dleay": {"nominal": 1e-3, "range": [0.0, 2e-3]}}, "io.dleay"),
    ({"io.delay": {"nominal": 3e-3, "range": [0.0, 2e-3]}}, "lo <= nominal <= hi"),
    ({"sensors.p_lag": {"nominal": 1e-3, "range": [0.0, 0.2]}}, "<= 0.05"),
    ({"io.delay": {"nominal": -1e-3, "range": [-2e-3, 0.0]}}, "nominal"),
])
def test_bad_effects_are_an_error_naming_the_key(effects: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError, match="effects") as info:
        _with(effects)
    assert key in str(info.value)


def test_the_truth_model_of_a_plant_with_effects_carries_the_ones_a_model_can() -> None:
    """model_from_plant: IO delay, sensor lags and armature lags, each ± 20 % (its margin)."""
    plant = PlantConfig().with_updates({"io": {"delay": 1.0e-3}, "sensors": {"p_lag": 5.0e-4},
                                        "valves": {"b_out": {"tau_close": 8.0e-4}},
                                        "heat": {"h": 30.0}})
    model = model_from_plant(plant)
    assert model.effects is not None
    assert set(model.effects) == {"io.delay", "sensors.p_lag", "valves.b_out.tau_close"}
    eff = model.effects["io.delay"]
    assert eff.nominal == 1.0e-3
    assert eff.range == pytest.approx((0.8e-3, 1.2e-3), rel=1e-12)
    assert nominal_plant(model).io.delay == 1.0e-3


def test_valve_delays_beyond_four_pwm_periods_are_refused_at_load() -> None:
    """At rig.pwm_hz 2000 four PWM periods are 2 ms: a 3 ms closing delay is refused when the
    model is read, naming its own key, not later as a plant.yaml key of an unnamed file."""
    data = model_from_plant(PlantConfig()).to_dict()
    data["rig"]["pwm_hz"] = 2000.0
    data["valves"]["a_in"]["delay_off"] = 0.003
    with pytest.raises(ConfigError) as exc:
        validate_model(ModelConfig, data, "model.yaml")
    assert (exc.value.file, exc.value.key) == ("model.yaml", "valves.a_in.delay_off")
    assert exc.value.message == ("must not exceed 4 PWM periods (0.002 s at rig.pwm_hz = 2000 "
                                 "Hz), got 0.003 s")
