"""Magnitudes of the real-rig effects: typical values and published ranges, as plant.yaml updates.

The simulator's optional effects (contract 2: valve armature lag, lines, heat transfer, LuGre
pre-sliding, sensor lags, IO delay, supply droop; see :mod:`pneutune.control.plant.dynamics`)
are described here once, by a few physical magnitudes, for everything that draws or sets them:
the paper-rig plant (``benchmarks/paper_rig.py``), the fleet benchmark and the closed-loop
benchmark's cost per effect. docs/real-rig.md gives each range's sources; in short:

* valve opening/closing time constants: 20-30 % of datasheet switching times of fast 3/2
  solenoid valves (Festo MH/MHE, Matrix 821, SMC SX: 1-15 ms);
* a line of ``BORE`` inner diameter and 0.1-1.5 m length: delay = length / speed of sound,
  volume = its bore's area times length; its sonic conductance from choked tube flow
  (4-8 mm tubes of 0.1-2 m: 1e-8 to 8.1e-8 m^3/(s Pa));
* wall heat transfer 5-300 W/(m^2 K) (Carneiro and de Almeida 2006);
* LuGre bristle stiffness 1e5-1e7 N/m and damping 3e2-1e4 N s/m (Canudas de Wit et al. 1995,
  scaled to a seal's pre-sliding deflection of 5-500 um);
* pressure transmitter time constant 0.05-4.5 ms (10-90 % response 0.1-10 ms), position
  conditioning 0.02-1.6 ms;
* IO delay 0.05-4 ms (software-timed output after a hardware-timed read, up to one sample);
* supply regulator conductance 1e-8 to 1e-7 m^3/(s Pa) into 0.2-5 l at the valves.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from pneutune.control.constants import VALVES

#: Speed of sound in the lines [m/s] (air at 283 K).
SOUND_SPEED: float = 337.0
#: Inner diameter of the lines [m] (a 6 x 1 mm tube has 4 mm; 6 mm is an 8 x 1 tube).
BORE: float = 4.0e-3


@dataclass(frozen=True, slots=True)
class Magnitude:
    """One effect magnitude: its published range and a typical value.

    Attributes
    ----------
    low, high : float
        The range (SI units).
    typical : float
        A value for a rig like the paper's.
    log : bool
        Whether the range spans decades (drawn log-uniformly).
    unit : str
        SI unit.
    """

    low: float
    high: float
    typical: float
    log: bool
    unit: str


#: Every magnitude, by name (:func:`plant_updates` turns a set of them into plant.yaml keys).
MAGNITUDES: dict[str, Magnitude] = {
    "tau_open": Magnitude(1.0e-4, 3.0e-3, 5.0e-4, True, "s"),
    "tau_close": Magnitude(1.0e-4, 4.0e-3, 7.0e-4, True, "s"),
    "line_length": Magnitude(0.1, 1.5, 0.3, False, "m"),
    "line_C": Magnitude(1.0e-8, 8.1e-8, 1.71e-8, True, "m^3/(s Pa)"),
    "heat_h": Magnitude(5.0, 300.0, 30.0, True, "W/(m^2 K)"),
    "sigma0": Magnitude(1.0e5, 1.0e7, 2.5e6, True, "N/m"),
    "sigma1": Magnitude(3.0e2, 1.0e4, 3.2e3, True, "N s/m"),
    "p_lag": Magnitude(5.0e-5, 4.5e-3, 4.5e-4, True, "s"),
    "x_lag": Magnitude(2.0e-5, 1.6e-3, 1.6e-4, True, "s"),
    "io_delay": Magnitude(5.0e-5, 4.0e-3, 5.0e-4, True, "s"),
    "supply_C": Magnitude(1.0e-8, 1.0e-7, 3.0e-8, True, "m^3/(s Pa)"),
    "supply_volume": Magnitude(2.0e-4, 5.0e-3, 5.0e-3, True, "m^3"),
}

#: The effects and the magnitudes each needs (a name of PlantConfig.effects -> magnitudes).
EFFECTS: dict[str, tuple[str, ...]] = {
    "valve lag": ("tau_open", "tau_close"),
    "lines": ("line_length", "line_C"),
    "heat transfer": ("heat_h",),
    "pre-sliding": ("sigma0", "sigma1"),
    "sensor lag": ("p_lag", "x_lag"),
    "IO delay": ("io_delay",),
    "supply droop": ("supply_C", "supply_volume"),
}


def typical() -> dict[str, float]:
    """Every magnitude at its typical value."""
    return {k: m.typical for k, m in MAGNITUDES.items()}


def draw(rng: np.random.Generator) -> dict[str, float]:
    """Every magnitude drawn inside its range (log-uniform where it spans decades)."""
    out = {}
    for k, m in MAGNITUDES.items():
        if m.log:
            out[k] = float(np.exp(rng.uniform(np.log(m.low), np.log(m.high))))
        else:
            out[k] = float(rng.uniform(m.low, m.high))
    return out


def plant_updates(magnitudes: Mapping[str, float],
                  effects: tuple[str, ...] | None = None) -> dict[str, Any]:
    """plant.yaml updates that switch on ``effects`` (default: all) at ``magnitudes``.

    Parameters
    ----------
    magnitudes : mapping
        Values of the :data:`MAGNITUDES` the effects need (SI units).
    effects : tuple of str, optional
        Names of :data:`EFFECTS`; default every one.

    Returns
    -------
    dict
        Nested updates for :meth:`~pneutune.control.contracts.plant.PlantConfig.with_updates`.

    Raises
    ------
    KeyError
        An unknown effect, or a magnitude an effect needs is missing.
    """
    names = tuple(EFFECTS) if effects is None else effects
    m = magnitudes
    out: dict[str, Any] = {}
    for name in names:
        if name not in EFFECTS:
            raise KeyError(f"unknown effect {name!r}; expected one of {', '.join(EFFECTS)}")
        if name == "valve lag":
            out["valves"] = {v: {"tau_open": m["tau_open"], "tau_close": m["tau_close"]}
                             for v in VALVES}
        elif name == "lines":
            line = {"delay": m["line_length"] / SOUND_SPEED,
                    "volume": float(np.pi * BORE**2 / 4.0 * m["line_length"]),
                    "C": m["line_C"]}
            out["lines"] = {"a": dict(line), "b": dict(line)}
        elif name == "heat transfer":
            out["heat"] = {"h": m["heat_h"]}
        elif name == "pre-sliding":
            out["friction"] = {"sigma0": m["sigma0"], "sigma1": m["sigma1"]}
        elif name == "sensor lag":
            out["sensors"] = {"p_lag": m["p_lag"], "x_lag": m["x_lag"]}
        elif name == "IO delay":
            out["io"] = {"delay": m["io_delay"]}
        else:
            out["supply"] = {"C": m["supply_C"], "volume": m["supply_volume"]}
    return out
