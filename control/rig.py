"""The rig interface and the simulated rig.

A rig is whatever the runtime talks to: it is sampled every ``Ts``, takes four duties and has a
clock. :class:`SimRig` is the in-process simulated rig over the compiled plant
(:mod:`pneutune.control.plant`); a hardware driver implements the same three calls.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from . import plant
from .plant_config import PlantConfig
from .plant_params import P_AA, P_AB, P_P0, P_TS, PlantParams, pack_plant


class Rig(Protocol):
    """What the runtime needs from a rig (hardware or simulation).

    Attributes
    ----------
    Ts : float
        Sampling period [s].
    t : float
        Time of the current sample [s] since the start of the run.
    """

    Ts: float
    t: float

    def read(self) -> np.ndarray:
        """Sensors at the current sample: [x [m], p_a, p_b, p_s [Pa abs]]."""
        ...

    def write(self, duties: np.ndarray) -> None:
        """Command the duties [a_in, a_out, b_in, b_out] (0..1) from the current sample on."""
        ...

    def advance(self) -> None:
        """Move to the next sample (simulation: integrate; hardware: wait for the tick)."""
        ...


def rest_pressures(p: np.ndarray, f_ext: float, p_b: float | None = None) -> tuple[float, float]:
    """Chamber pressures that hold the piston at rest against ``f_ext`` (Eq. 1 with v = a = 0).

    ``p_b`` defaults to ambient; if that would need ``p_a`` below ambient, ``p_a`` is set to
    ambient and ``p_b`` follows from the balance instead.
    """
    p0 = p[P_P0]
    pa, pb = plant.balanced_pressures(p, p0 if p_b is None else p_b, f_ext)
    if pa < p0:
        pa = p0
        pb = (pa * p[P_AA] - p0 * (p[P_AA] - p[P_AB]) + f_ext) / p[P_AB]
    return pa, pb


class SimRig:
    """The simulated rig: the compiled plant with sensors, in this process.

    Parameters
    ----------
    plant_cfg : PlantConfig or PlantParams
        The plant.
    x0 : float, optional
        Initial position [m]; default mid-stroke. The piston starts at rest with the chamber
        pressures of :func:`rest_pressures` (force balance, B at ambient) unless
        ``pressures0`` is given.
    pressures0 : (float, float), optional
        Initial (p_a, p_b) [Pa abs].
    seed : int, optional
        Seed of the sensor noise; default ``sim.seed`` of the plant.
    """

    def __init__(self, plant_cfg: PlantConfig | PlantParams, x0: float | None = None,
                 pressures0: tuple[float, float] | None = None, seed: int | None = None) -> None:
        self.params = plant_cfg if isinstance(plant_cfg, PlantParams) else pack_plant(plant_cfg)
        cfg = self.params.config
        p = self.params.vec
        self.Ts = float(p[P_TS])
        if x0 is None:
            x0 = 0.5 * (cfg.rig.x_min + cfg.rig.x_max)
        f0 = float(plant.external_force(p, self.params.force_steps, 0.0))
        pa0, pb0 = pressures0 if pressures0 is not None else rest_pressures(p, f0)
        self.state = plant.initial_state(p, float(x0), pa0, pb0)
        self.rng = np.random.default_rng(self.params.seed if seed is None else seed)
        self.k = 0
        self.supply = float(self.params.p_s)
        self._sensors = np.zeros(4)
        self._truth = np.zeros(6)

    @property
    def t(self) -> float:
        """Time of the current sample [s]."""
        return self.k * self.Ts

    def read(self) -> np.ndarray:
        """Sensors at the current sample: [x, p_a, p_b, p_s] (noisy, quantised)."""
        plant.measure(self.params.vec, self.state, self.supply, self.rng.standard_normal(4),
                      self._sensors)
        return self._sensors.copy()

    def truth(self) -> np.ndarray:
        """True [v, a, F_friction, F_ext, mdot_a, mdot_b] at the current sample."""
        plant.truth(self.params.vec, self.state, self.supply, self.params.force_steps,
                    self._truth)
        return self._truth.copy()

    def write(self, duties: np.ndarray) -> None:
        """Command the four duties from now on."""
        plant.set_duties(self.params.vec, self.state, self.t,
                         np.ascontiguousarray(duties, dtype=np.float64))

    def advance(self) -> None:
        """Integrate the plant to the next sample."""
        plant.advance(self.params.vec, self.state, (self.k + 1) * self.Ts, self.supply,
                      self.params.force_steps)
        self.k += 1
