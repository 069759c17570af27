"""The plant's frozen parameters as the flat float64 vector that the compiled code reads.

:func:`pack_plant` turns a validated :class:`~pneutune.control.contracts.plant.PlantConfig` into a
:class:`PlantParams` record. The index constants below are module-level ints, which numba treats
as compile-time constants. Per-valve quantities occupy four consecutive slots in the order
a_in, a_out, b_in, b_out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.physics.friction import stribeck_peak, stribeck_stiffness

P_AA, P_AB, P_XMIN, P_XMAX, P_V0A, P_V0B, P_P0, P_T0, P_N, P_R = range(10)
P_TS, P_TPWM, P_LATCHED, P_M, P_FS, P_FC, P_VS, P_ALPHA, P_BV = range(10, 19)
P_C = 19  # 4 slots: sonic conductance [m^3/(s Pa)]
P_B = 23  # 4 slots: critical pressure ratio
P_DON = 27  # 4 slots: opening delay [s]
P_DOFF = 31  # 4 slots: closing delay [s]
P_MINP = 35  # 4 slots: minimum pulse [s]
P_LEAKC, P_FN, P_DA, P_DB, P_DT, P_XNOISE, P_XSTEP, P_PNOISE = range(39, 47)
P_DTMIN = 47  # the step the steepest sliding friction needs, <= P_DT (set_step_limits) [s]
P_RPEAK = 48  # where the Stribeck slope peaks, |v|/v_s (physics.friction.stribeck_peak) [-]
P_UFREE = 49  # above this speed only b_v may shorten the step (set_step_limits) [m/s]
N_PARAMS = 50
#: RK4 keeps ``h * stiffness / M`` at most this (its stability limit on the real axis is 2.79).
STEP_STIFFNESS: float = 1.4


@dataclass(frozen=True, slots=True)
class PlantParams:
    """Frozen numeric form of a plant.yaml, for the compiled simulator.

    Attributes
    ----------
    vec : numpy.ndarray
        float64 vector of length :data:`N_PARAMS` (read-only), indexed by the ``P_*`` constants.
    force_steps : numpy.ndarray
        float64 array of shape (K, 2): [[t_s, F_N], ...] with strictly increasing t (K may be 0).
    p_s : float
        Nominal supply pressure [Pa abs].
    seed : int
        Seed of the sensor noise.
    config : PlantConfig
        The validated configuration it came from.
    """

    vec: np.ndarray
    force_steps: np.ndarray
    p_s: float
    seed: int
    config: PlantConfig


def set_step_limits(v: np.ndarray) -> None:
    """Fill ``P_RPEAK``, ``P_DTMIN`` and ``P_UFREE`` of a parameter vector from its friction,
    mass and ``P_DT`` (call again after changing any of them).

    ``P_DTMIN = min(P_DT, STEP_STIFFNESS M / k_max)``, k_max the largest |dF_f/dv| at any speed
    (:func:`~pneutune.control.physics.friction.stribeck_stiffness` at u = 0): the shortest step
    the integrator may take while sliding. When it equals ``P_DT`` the friction never shortens
    a step. ``P_UFREE``: the speed above which the Stribeck branch needs no shorter step than
    ``min(P_DT, STEP_STIFFNESS M / b_v)`` (0 when it never does), so that a fast step costs no
    evaluation of the slope.
    """
    v[P_RPEAK] = stribeck_peak(v[P_ALPHA])

    def k(u: float) -> float:
        return stribeck_stiffness(u, v[P_FS], v[P_FC], v[P_VS], v[P_ALPHA], v[P_BV], v[P_RPEAK])

    # above P_UFREE the step needs no more than min(P_DT, 1.4 M / b_v): the Stribeck branch is
    # no steeper there than what P_DT or the viscous mode allows anyway
    k_flat = max(STEP_STIFFNESS * v[P_M] / v[P_DT], v[P_BV])
    v[P_DTMIN] = min(v[P_DT], STEP_STIFFNESS * v[P_M] / k(0.0))
    if k(0.0) <= k_flat:
        v[P_UFREE] = 0.0
    else:  # k(u) falls with u above the peak: bisect for k(u) = k_flat
        lo = v[P_RPEAK] * v[P_VS]
        hi = 2.0 * lo + v[P_VS]
        while k(hi) > k_flat:
            hi *= 2.0
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if k(mid) > k_flat:
                lo = mid
            else:
                hi = mid
        v[P_UFREE] = hi


def pack_plant(cfg: PlantConfig) -> PlantParams:
    """Pack a validated plant configuration into a :class:`PlantParams`.

    Parameters
    ----------
    cfg : PlantConfig
        The plant (already validated).

    Returns
    -------
    PlantParams
    """
    v = np.zeros(N_PARAMS)
    r = cfg.rig
    v[P_AA], v[P_AB], v[P_XMIN], v[P_XMAX] = r.A_a, r.A_b, r.x_min, r.x_max
    v[P_V0A], v[P_V0B], v[P_P0], v[P_T0], v[P_N], v[P_R] = r.V0a, r.V0b, r.p0, r.T0, r.n, r.R
    v[P_TS], v[P_TPWM] = r.Ts, 1.0 / r.pwm_hz
    v[P_LATCHED] = 1.0 if r.pwm_update == "latched" else 0.0
    v[P_M] = cfg.total_mass
    f = cfg.friction
    v[P_FS], v[P_FC], v[P_VS], v[P_ALPHA], v[P_BV] = f.F_S, f.F_C, f.v_s, f.alpha, f.b_v
    for i, valve in enumerate(cfg.valves.ordered()):
        v[P_C + i], v[P_B + i] = valve.C, valve.b
        v[P_DON + i], v[P_DOFF + i] = valve.delay_on, valve.delay_off
        v[P_MINP + i] = valve.min_pulse
    v[P_LEAKC] = cfg.leak.C
    d = cfg.disturbance
    v[P_FN], v[P_DA], v[P_DB] = d.F_n, d.D_a, d.D_b
    v[P_DT] = cfg.sim.dt  # the longest step; sliding friction may shorten it (dynamics)
    set_step_limits(v)
    s = cfg.sensors
    v[P_XNOISE], v[P_XSTEP], v[P_PNOISE] = s.x_noise, s.x_step, s.p_noise
    v.setflags(write=False)
    steps = np.array(d.force_steps, dtype=np.float64).reshape(-1, 2)
    steps.setflags(write=False)
    return PlantParams(vec=v, force_steps=steps, p_s=r.p_s, seed=cfg.sim.seed, config=cfg)


# ---------------------------------------------------------------------------------------------
# Plant state vector (float64). Continuous states, the stuck flag, the clock and, per valve, the
# PWM/valve switching state (see pneutune.control.plant.valves).
S_X, S_V, S_PA, S_PB, S_STUCK, S_T = range(6)
S_SIG = 6  # 4 slots: command signal of the PWM comparator (0/1)
S_OPEN = 10  # 4 slots: physical valve state (0 closed / 1 open)
S_RISE = 14  # 4 slots: time of the last rising edge of the command signal [s]
S_DUTY = 18  # 4 slots: duty the comparator uses now (latched mode: from the period start)
S_CMD = 22  # 4 slots: duty last commanded by the controller
S_NPEND = 26  # 4 slots: number of pending valve transitions
PEND_MAX = 16  # pending transitions per valve (sorted by time)
S_PEND_T = 30  # 4 * PEND_MAX slots: transition times [s]
S_PEND_V = S_PEND_T + 4 * PEND_MAX  # 4 * PEND_MAX slots: target state (0/1)
N_STATE = S_PEND_V + 4 * PEND_MAX
