"""Four simulated plants that differ from the defaults: the truths identification is checked on.

Each variant is a plant.yaml update (contract 2) of the default :class:`PlantConfig`. Between
them they vary friction ±40 %, C ±25 % per valve, b, the delays, mass and payload, a small seal
leak, the constant disturbance terms and the sensor noise. The identification tests recover
each one from its simulated identification run (tests/test_identify.py), and
``benchmarks/mass_sampling.py`` measures the mass estimate on them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pneutune.control.constants import VALVES
from pneutune.control.contracts.plant import PlantConfig

#: The paper's sonic conductance [m^3/(s Pa)] (the default plant's), which the variants scale.
_C_DEFAULT = 8.373e-9


def _valves(C_scale: Sequence[float], b: Sequence[float], d_on: float, d_off: float,
            min_pulse: float) -> dict[str, dict[str, float]]:
    """The ``valves`` block: C scaled per valve, b per valve, the timings shared."""
    return {name: {"C": _C_DEFAULT * c, "b": bb, "delay_on": d_on, "delay_off": d_off,
                   "min_pulse": min_pulse}
            for name, c, bb in zip(VALVES, C_scale, b, strict=True)}


#: The variants by name, each a plant.yaml update of the default plant.
PLANT_VARIANTS: dict[str, dict[str, Any]] = {
    "stiff-friction-heavy": {
        "friction": {"F_S": 105.0, "F_C": 70.0, "b_v": 4900.0, "v_s": 0.004},
        "valves": _valves([1.25, 0.8, 1.1, 0.9], [0.25] * 4, 2.5e-3, 3.5e-3, 2.0e-3),
        "payload": 1.0,
    },
    "light-friction-leaky": {
        "friction": {"F_S": 45.0, "F_C": 30.0, "b_v": 2100.0, "v_s": 0.006},
        "valves": _valves([0.8, 1.2, 0.95, 1.15], [0.15, 0.3, 0.2, 0.15], 1.5e-3, 2.0e-3,
                          1.0e-3),
        "mass": 0.8, "leak": {"C": 1.0e-11},
        "sensors": {"x_noise": 1.0e-5, "p_noise": 600.0},
    },
    # friction -40 % on both Coulomb and viscous terms and a heavier piston: slow ramps
    # stick-slip. Fitted jointly with the Stribeck terms, F_C came out 15-17 % low here.
    "low-damping-light-coulomb": {
        "friction": {"F_S": 45.0, "F_C": 30.0, "b_v": 2100.0},
        "mass": 1.5,
    },
    "disturbed-latched": {
        "rig": {"pwm_update": "latched"},
        "valves": _valves([1.1, 1.2, 0.75, 0.85], [0.35, 0.35, 0.22, 0.22], 2.0e-3, 3.0e-3,
                          1.5e-3),
        "payload": 1.136,
        "disturbance": {"F_n": 5.0, "D_a": 150.0, "D_b": -100.0},
    },
}


def variant_plant(name: str) -> PlantConfig:
    """The plant of one variant: the default plant with its updates.

    Parameters
    ----------
    name : str
        A key of :data:`PLANT_VARIANTS`.

    Returns
    -------
    PlantConfig
        ``PlantConfig().with_updates(PLANT_VARIANTS[name])``.

    Raises
    ------
    KeyError
        When ``name`` is no variant.
    """
    return PlantConfig().with_updates(PLANT_VARIANTS[name], source=f"plant variant {name}")


__all__ = ["PLANT_VARIANTS", "variant_plant"]
