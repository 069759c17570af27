"""The plants a model stands for: its nominal plant and the box of its uncertain coordinates.

The nominal plant is the model read as a plant.yaml: rig, mass, Stribeck friction, valves (C, b,
delays, minimum pulse), leak, sensor noise, the constant disturbances F_n, D_a, D_b at θ's
nominal values, and the real-rig effects of ``effects`` at their nominal values. For
``model_from_plant(PlantConfig())`` it equals ``PlantConfig()``.

The box of each coordinate (:func:`uncertainty_box`):

========================  =====================================================================
mass (total moving)       θ box [θ1_min, θ1_max] ∩ ``mass_range``
friction.b_v              θ box [θ3_min, θ3_max] ∩ ``friction.ranges.b_v``
friction.F_C              θ box of A_f [θ4_min, θ4_max] ∩ ``friction.ranges.F_C``, ≥ 0
friction.F_S              ``friction.ranges.F_S`` (raised to F_C where it would fall below)
friction.v_s, alpha       ``friction.ranges``
disturbance.F_n           θ box [θ2_min, θ2_max]
disturbance.D_a, D_b      θ box [θ5_min, θ5_max], [θ6_min, θ6_max]
valves.<v>.C, .b          [C_min, C_max], [b_min, b_max] per valve
valves.<v>.min_pulse      [min_pulse_min, min_pulse_max] where the model gives that range and
                          it is wider than :data:`MIN_PULSE_SPAN`; the slow corner has the
                          longest
``effects`` keys          the model's ``effects.<key>.range`` (IO delay, sensor lags, valve
                          armature lags), where it is not a single value; the slow corner has
                          the most lag
========================  =====================================================================

Where an intersection is empty (an identified range outside the projection box), the identified
range is used. A model without ``friction.ranges`` or ``mass_range`` uses the θ box alone (and
F_S scaled with F_C, v_s and alpha nominal).

``box`` overrides narrow coordinates further (key -> (lo, hi), intersected with the box above,
the nominal value always kept inside): :mod:`pneutune.tune.feasibility` narrows the ranges a
log does not rule out but no controller can track.

One definition for both users: ``identify`` checks every range end against the log
(:mod:`pneutune.identify.crosscheck`) and ``tune`` draws its plants from the same box
(:mod:`pneutune.tune.plants`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from pneutune.control.constants import VALVES
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.contracts.yamlio import validate_model

#: Narrowest minimum-pulse range drawn [s]: identify scans the minimum pulse in steps of 1/400
#: of a PWM period (0.042 ms at 60 Hz), so a narrower range is a point at its resolution.
MIN_PULSE_SPAN = 1.0e-4


@dataclass(frozen=True)
class Coordinate:
    """One uncertain plant parameter: its plant.yaml key path, box and nominal value.

    Attributes
    ----------
    key : str
        Dotted plant.yaml path (``friction.b_v``, ``valves.a_in.C``).
    low, high : float
        Box, SI units.
    nominal : float
        The nominal plant's value.
    slow : str
        Which end the ``slow`` corner takes: ``"low"``, ``"high"`` or ``"nominal"``.
    """

    key: str
    low: float
    high: float
    nominal: float
    slow: str


def _meet(box: tuple[float, float], rng: tuple[float, float] | None) -> tuple[float, float]:
    if rng is None:
        return box
    lo, hi = max(box[0], rng[0]), min(box[1], rng[1])
    return (lo, hi) if lo <= hi else (float(rng[0]), float(rng[1]))


def uncertainty_box(model: ModelConfig,
                    box: Mapping[str, tuple[float, float]] | None = None
                    ) -> tuple[Coordinate, ...]:
    """The uncertain coordinates of ``model`` and their boxes (module docstring).

    Parameters
    ----------
    model : ModelConfig
    box : mapping, optional
        Narrower ranges for some coordinates (key -> (lo, hi)); each is intersected with the
        model's range and widened to keep the nominal value.

    Returns
    -------
    tuple of Coordinate

    Raises
    ------
    KeyError
        A key of ``box`` that is not a coordinate.
    """
    th = model.theta
    f = model.friction
    r = f.ranges
    coords = []
    lo, hi = _meet((th.min[0], th.max[0]), model.mass_range)
    coords.append(Coordinate("mass", max(lo, 1e-3), hi, model.mass, "high"))
    lo, hi = _meet((th.min[2], th.max[2]), None if r is None else r.b_v)
    coords.append(Coordinate("friction.b_v", max(lo, 0.0), max(hi, 0.0), f.b_v, "high"))
    lo, hi = _meet((th.min[3], th.max[3]), None if r is None else r.F_C)
    coords.append(Coordinate("friction.F_C", max(lo, 0.0), max(hi, 0.0), f.F_C, "high"))
    if r is not None:
        coords.append(Coordinate("friction.F_S", r.F_S[0], r.F_S[1], f.F_S, "high"))
        coords.append(Coordinate("friction.v_s", r.v_s[0], r.v_s[1], f.v_s, "nominal"))
        coords.append(Coordinate("friction.alpha", r.alpha[0], r.alpha[1], f.alpha, "nominal"))
    coords.append(Coordinate("disturbance.F_n", th.min[1], th.max[1], th.nominal[1], "high"))
    coords.append(Coordinate("disturbance.D_a", th.min[4], th.max[4], th.nominal[4], "low"))
    coords.append(Coordinate("disturbance.D_b", th.min[5], th.max[5], th.nominal[5], "high"))
    for name, v in zip(VALVES, model.valves.ordered(), strict=True):
        coords.append(Coordinate(f"valves.{name}.C", v.C_min, v.C_max, v.C, "low"))
        coords.append(Coordinate(f"valves.{name}.b", v.b_min, v.b_max, v.b, "high"))
        if (v.min_pulse_min is not None and v.min_pulse_max is not None
                and v.min_pulse_max - v.min_pulse_min > MIN_PULSE_SPAN):
            coords.append(Coordinate(f"valves.{name}.min_pulse", v.min_pulse_min,
                                     v.min_pulse_max, v.min_pulse, "high"))
    for key, eff in sorted((model.effects or {}).items()):
        if eff.range[1] > eff.range[0]:  # a lag or delay: the slow corner has the most of it
            coords.append(Coordinate(key, eff.range[0], eff.range[1], eff.nominal, "high"))
    if not box:
        return tuple(coords)
    unknown = sorted(set(box) - {c.key for c in coords})
    if unknown:
        raise KeyError(f"box overrides for unknown coordinates {unknown}; expected keys of "
                       f"{[c.key for c in coords]}")
    out = []
    for c in coords:
        if c.key in box:
            lo, hi = box[c.key]
            c = replace(c, low=min(max(c.low, lo), c.nominal), high=max(min(c.high, hi),
                                                                         c.nominal))
        out.append(c)
    return tuple(out)


def _nominal_dict(model: ModelConfig, seed: int) -> dict[str, Any]:
    f = model.friction
    th = model.theta
    valves = {name: {"C": v.C, "b": v.b, "delay_on": v.delay_on, "delay_off": v.delay_off,
                     "min_pulse": v.min_pulse}
              for name, v in zip(VALVES, model.valves.ordered(), strict=True)}
    data: dict[str, Any] = {
        "schema": "pneutune.plant/1",
        "rig": model.rig.model_dump(),
        "mass": model.mass,
        "payload": 0.0,
        "friction": {"F_S": f.F_S, "F_C": f.F_C, "v_s": f.v_s, "alpha": f.alpha, "b_v": f.b_v},
        "valves": valves,
        "leak": {"C": model.leak.C},
        "disturbance": {"F_n": th.nominal[1], "D_a": th.nominal[4], "D_b": th.nominal[5],
                        "force_steps": []},
        "sim": {"seed": int(seed)},
    }
    if model.sensors is not None:
        data["sensors"] = {"x_noise": model.sensors.x_noise, "p_noise": model.sensors.p_noise}
    for key, eff in (model.effects or {}).items():
        node = data
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = float(eff.nominal)
    return data


def nominal_plant(model: ModelConfig, seed: int = 1) -> PlantConfig:
    """The model read as a plant (module docstring), sensor-noise seed ``seed``.

    Parameters
    ----------
    model : ModelConfig
    seed : int
        ``sim.seed`` of the plant (>= 0).

    Returns
    -------
    PlantConfig
    """
    defaults = PlantConfig().to_dict()
    data = _nominal_dict(model, seed)
    for key in ("sensors", "sim"):
        merged = dict(defaults[key])
        merged.update(data.get(key, {}))
        data[key] = merged
    return validate_model(PlantConfig, data, "<model>")


def _set(data: dict[str, Any], key: str, value: float) -> None:
    node = data
    *parents, leaf = key.split(".")
    for p in parents:
        node = node[p]
    node[leaf] = float(value)


def plant_from_values(model: ModelConfig, values: dict[str, float], noise_seed: int,
                      label: str) -> PlantConfig:
    """The nominal plant of ``model`` with some coordinates set (key path -> value).

    F_S follows F_C in proportion when it is not given, and is kept >= F_C.

    Parameters
    ----------
    model : ModelConfig
    values : dict
        Coordinate values (:func:`uncertainty_box` keys), SI units.
    noise_seed : int
        ``sim.seed`` of the plant.
    label : str
        Name for error messages.

    Returns
    -------
    PlantConfig
    """
    data = nominal_plant(model, noise_seed).to_dict()
    for key, value in values.items():
        _set(data, key, value)
    fr = data["friction"]
    if "friction.F_S" not in values and model.friction.F_C > 0.0:
        fr["F_S"] = model.friction.F_S * fr["F_C"] / model.friction.F_C
    fr["F_S"] = max(fr["F_S"], fr["F_C"])
    return validate_model(PlantConfig, data, f"<plant draw {label}>")


def corner(coords: tuple[Coordinate, ...], slow: bool) -> dict[str, float]:
    """The ``slow`` corner of the box (valves that deliver least, the load that asks most: each
    coordinate at the end its ``slow`` field names) or the opposite, ``fast`` one.

    Parameters
    ----------
    coords : tuple of Coordinate
        From :func:`uncertainty_box`.
    slow : bool
        Which corner.

    Returns
    -------
    dict
        Key path -> value.
    """
    out = {}
    for c in coords:
        if c.slow == "nominal":
            out[c.key] = c.nominal
        elif (c.slow == "high") == slow:
            out[c.key] = c.high
        else:
            out[c.key] = c.low
    return out


__all__ = ["MIN_PULSE_SPAN", "Coordinate", "corner", "nominal_plant", "plant_from_values",
           "uncertainty_box"]
