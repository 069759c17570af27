"""The simulated rig in process.

:class:`SimRig` is the compiled plant (:mod:`pneutune.control.plant.dynamics`) behind the
:class:`~pneutune.control.rig.protocol.SimulatedRig` protocol: the calls a hardware driver
implements (:class:`~pneutune.control.rig.protocol.Rig`) plus ``truth()``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import P_TS, S_PA, S_PB, S_V, S_X, PlantParams, pack_plant
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES
from pneutune.control.rig.wire import RigIOError


class SimRig:
    """The simulated rig: the compiled plant with sensors, in this process.

    Parameters
    ----------
    plant_cfg : PlantConfig or PlantParams
        The plant.
    x0 : float, optional
        Initial position [m]; default mid-stroke. The piston starts at rest with the chamber
        pressures of :func:`~pneutune.control.plant.dynamics.rest_pressures` (force balance, B at
        ambient) unless
        ``pressures0`` is given.
    pressures0 : (float, float), optional
        Initial (p_a, p_b) [Pa abs].
    seed : int, optional
        Seed of the sensor noise; default ``sim.seed`` of the plant.
    sample_period : float, optional
        Sampling period of the rig [s], dividing the plant's ``rig.Ts`` (a data-acquisition
        card that samples faster than the valves are updated); default ``rig.Ts``. The rig
        block (:meth:`rig_metadata`) keeps ``rig.Ts``, the control period the rig is built for.
    """

    def __init__(self, plant_cfg: PlantConfig | PlantParams, x0: float | None = None,
                 pressures0: tuple[float, float] | None = None, seed: int | None = None,
                 sample_period: float | None = None) -> None:
        params = plant_cfg if isinstance(plant_cfg, PlantParams) else pack_plant(plant_cfg)
        self._rig_meta = params.config.rig_metadata()
        if sample_period is not None and sample_period != params.config.rig.Ts:
            from pneutune.control.rig.identification_run import samples_per_control

            per_control = samples_per_control(params.config.rig.Ts, sample_period)
            fast_Ts = params.config.rig.Ts / per_control
            params = pack_plant(params.config.with_updates({"rig": {"Ts": fast_Ts}}))
        self.params = params
        cfg = self.params.config
        p = self.params.vec
        self.Ts = float(p[P_TS])
        if x0 is None:
            x0 = 0.5 * (cfg.rig.x_min + cfg.rig.x_max)
        f0 = float(plant.external_force(p, self.params.force_steps, 0.0))
        pa0, pb0 = pressures0 if pressures0 is not None else plant.rest_pressures(p, f0)
        self.state = plant.initial_state(p, float(x0), pa0, pb0)
        self.rng = np.random.default_rng(self.params.seed if seed is None else seed)
        self.k = 0
        self.supply = float(self.params.p_s)
        self._scenario_steps = self.params.force_steps.copy()
        self._sensors = np.zeros(4)
        self._truth = np.zeros(6)
        self.closed = False

    @property
    def t(self) -> float:
        """Time of the current sample [s]."""
        return self.k * self.Ts

    def read(self) -> np.ndarray:
        """Sensors at the current sample: [x, p_a, p_b, p_s] (noisy, quantised)."""
        plant.measure(self.params.vec, self.state, self.supply, self.rng.standard_normal(4),
                      self._sensors)
        return self._sensors.copy()

    def sample_times(self) -> np.ndarray | None:
        """Every channel is refreshed at every sample: ``[t, t, t, t]``."""
        return np.full(4, self.t)

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
        if plant.diverged(self.state):
            st = self.state
            raise RigIOError(
                f"the simulated plant diverged before t={self.t:.4f} s (x {st[S_X]:.3g} m, "
                f"v {st[S_V]:.3g} m/s, p_a {st[S_PA]:.3g} Pa, p_b {st[S_PB]:.3g} Pa): check "
                "the plant file's mass, friction and volumes")

    def set_scenario_start(self, t0: float | None) -> None:
        """Time the plant's timed changes (``disturbance.force_steps``) from the scenario's start.

        Parameters
        ----------
        t0 : float or None
            Rig time at which the scenario starts [s] (after a homing move): each step comes
            ``t0`` later than in the plant file. None: a homing move is under way, the external
            force holds its level at t = 0 (a constant load stays, no step fires).
        """
        steps = self._scenario_steps.copy()
        if t0 is None:
            steps = steps[steps[:, 0] <= 0.0]
        else:
            steps[:, 0] += float(t0)
        self.params = dataclasses.replace(self.params, force_steps=steps)

    def rig_metadata(self) -> dict[str, float | str]:
        """The plant's ``rig`` block (``Ts`` the control period, whatever the sample period)."""
        return dict(self._rig_meta)

    def close(self) -> None:
        """Write the fail-safe duties (all closed); idempotent. The plant stays usable."""
        if not self.closed:
            self.write(np.asarray(FAIL_SAFE_DUTIES, dtype=np.float64))
            self.closed = True
