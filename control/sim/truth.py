"""The model a perfect identification would give: a plant read as model.yaml.

:func:`model_from_plant` is the truth that tests and tools compare ``identify`` with, and the
model ``tune`` can start from when the plant is known (benchmarks). Its PWM curve is the plant's,
sampled by :func:`~pneutune.control.physics.pwm.sample_pwm_curve` (one implementation with the
controller's view of the curve).
"""

from __future__ import annotations

from typing import Any

from pneutune.control.constants import MODEL_SCHEMA, VALVES
from pneutune.control.contracts.model import EFFECT_KEYS, ModelConfig, SourceInfo
from pneutune.control.contracts.plant import PlantConfig, ValveConfig
from pneutune.control.physics.pwm import sample_pwm_curve


def model_from_plant(plant: PlantConfig, rel_margin: float = 0.2,
                     source: SourceInfo | None = None) -> ModelConfig:
    """The model a perfect identification of ``plant`` would give (truth, for tests and tools).

    The PWM curves are the plant's (:func:`~pneutune.control.physics.pwm.sample_pwm_curve`): the
    top-level ``pwm`` from valve a_in's timing, and ``valves.<v>.pwm`` for each valve whose
    timing gives another curve. A_f = F_C, and every range is the value ± ``rel_margin``. The
    plant's IO delay, sensor lags and valve armature lags become the model's ``effects``; its
    lines, heat transfer, LuGre friction and supply droop have no place in a model.
    """
    m = rel_margin

    def rng(v: float, lo_floor: float = 0.0) -> tuple[float, float]:
        return max(lo_floor, v * (1.0 - m)), v * (1.0 + m)

    def curve(v: ValveConfig) -> dict[str, list[float]]:
        duty, ratio = sample_pwm_curve(plant.rig.pwm_period, v.delay_on, v.delay_off,
                                       v.min_pulse)
        return {"duty": [float(x) for x in duty], "ratio": [float(x) for x in ratio]}

    shared = curve(plant.valves.a_in)
    valves = {}
    for name, v in zip(VALVES, plant.valves.ordered(), strict=True):
        c_lo, c_hi = rng(v.C)
        b_lo, b_hi = rng(v.b)
        valves[name] = {"C": v.C, "b": v.b, "C_min": c_lo, "C_max": min(c_hi, 1e-6),
                        "b_min": b_lo, "b_max": min(b_hi, 0.95), "delay_on": v.delay_on,
                        "delay_off": v.delay_off, "min_pulse": v.min_pulse}
        own = curve(v)
        if own != shared:
            valves[name]["pwm"] = own
    f = plant.friction
    M = plant.total_mass
    d = plant.disturbance
    nominal = (M, d.F_n, f.b_v, f.F_C, d.D_a, d.D_b)
    spans = (m * M, 10.0 + m * abs(d.F_n), m * f.b_v, 50.0 + m * f.F_C, 20.0 + m * abs(d.D_a),
             20.0 + m * abs(d.D_b))
    data = {
        "schema": MODEL_SCHEMA,
        "source": (source.model_dump() if source is not None else
                   {"log": "<truth>", "sha256": "0" * 64, "duration_s": 0.0}),
        "rig": plant.rig.model_dump(),
        "valves": valves,
        "pwm": shared,
        "friction": {"F_S": f.F_S, "F_C": f.F_C, "v_s": f.v_s, "alpha": f.alpha, "b_v": f.b_v,
                     "A_f": f.F_C,
                     "ranges": {"F_S": list(rng(f.F_S)), "F_C": list(rng(f.F_C)),
                                "v_s": list(rng(f.v_s)), "alpha": list(rng(f.alpha)),
                                "b_v": list(rng(f.b_v))}},
        "mass": M,
        "mass_range": list(rng(M)),
        "theta": {"nominal": list(nominal),
                  "min": [n - s for n, s in zip(nominal, spans, strict=True)],
                  "max": [n + s for n, s in zip(nominal, spans, strict=True)]},
        "uncertainty": {"F_max": 10.0, "D_a_max": 1.0e4, "D_b_max": 1.0e4},
        "fit": {"nrmse_x": 0.0, "nrmse_p_a": 0.0, "nrmse_p_b": 0.0},
        "leak": {"C": plant.leak.C},
        "sensors": {"x_noise": plant.sensors.x_noise, "p_noise": plant.sensors.p_noise},
        "notes": ["truth model made from a plant.yaml, not identified"],
    }
    effects = _effects(plant, m)
    if effects:
        data["effects"] = effects
    return ModelConfig.model_validate(data)


def _effects(plant: PlantConfig, m: float) -> dict[str, dict[str, Any]]:
    """The plant's real-rig effects a model can carry (EFFECT_KEYS), each ± ``m`` of itself."""
    values = {"io.delay": plant.io.delay, "sensors.p_lag": plant.sensors.p_lag,
              "sensors.x_lag": plant.sensors.x_lag}
    for name, v in zip(VALVES, plant.valves.ordered(), strict=True):
        values[f"valves.{name}.tau_open"] = v.tau_open
        values[f"valves.{name}.tau_close"] = v.tau_close
    return {k: {"nominal": v, "range": [v * (1.0 - m), min(v * (1.0 + m), EFFECT_KEYS[k])]}
            for k, v in values.items() if v > 0.0}


__all__ = ["model_from_plant"]
