"""The control law, once: modified DARC (Eqs. 9-36) and its variants, one compiled step.

The step is C99 (``control/law/c/ptlaw.c``, ``pt_step_into``): the same sources that
``deploy --emit c`` gives a target, compiled by the install into the library numba calls
(:mod:`pneutune.control.law.clib`). ``step(state, meas, cfg) -> (state, duties)`` and
:func:`step_into` (the zero-allocation form, callable from compiled code) are its Python entry
points; the simulator, the tuner and the deploy runtime all call them. The description below
is of what the C computes; ``ptlaw.c`` follows it line by line.

* ``state``: flat float64 vector, :data:`STATE_SIZE` long, fields at the ``S_*`` indices below
  (θ̂, both Kalman means and covariances, the previous F_pd and a_r, the PID integral, the logged
  quantities). Made by :func:`init_state`; updated in place. :func:`state_view` reads it.
* ``meas``: ``[t, x, p_a, p_b, p_s, x_r, v_r, a_r]`` (``M_*`` indices), SI units: s, m, Pa abs,
  m, m/s, m/s^2. :func:`make_meas` builds one.
* ``cfg``: the packed config, :func:`pneutune.control.law.layout.pack` (``CFG_*``).
* ``duties``: commanded duties (0..1) of a_in, a_out, b_in, b_out.

One step, every Ts (the names are the paper's):

1. Motion Kalman filter (Sec. 4, Eqs. 34-36): predict, update with the measured x; gives x̂, v̂,
   â. ``x1`` = measured x or x̂ (``position_feedback``), ``x2`` = v̂.
2. Step 1 (Eqs. 13-17, 20): e1 = x1 - x_r, x2eq = v_r - k1 e1, e2 = x2 - x2eq,
   ẋ2eq = a_r - k1 (x2 - v_r), F_pd = -θ̂2 + θ̂3 x2 + θ̂4 S_f(x2) + θ̂1 ẋ2eq - k2 e2
   - h2² e2/(4 ε2), with S_f(v) = (2/π) atan(1000 v) (Eq. 4) and h2 a constant (docs/controller.md).
3. F_p = A_a p_a - A_b p_b - p0 A_r (Eq. 8 with the typo p0 A_f -> p0 A_r), e3 = F_p - F_pd.
4. τ = r2 φ2 e2 + r3 φ3 e3 (Eqs. 17, 26); θ̂ <- clip(θ̂ + Ts sat(Proj(Γτ))) while
   |v_r| > min_ref_speed (Sec. 5.3), else held (:mod:`pneutune.control.law.projection`).
   The control of this step uses θ̂ from before the update.
5. dF_pd/dt by variant: ``modified_darc``: the force Kalman filter (predict, update with F_pd);
   ``direct_diff``: (F_pd - F_pd,prev)/Ts (0 at the first step, the paper's Fig. 11);
   ``original_darc``: the calculable part, docs/original_darc.md (dx2/dt = â by default,
   or the model's (F_p + θ̂2 - θ̂3 x2 - θ̂4 S_f(x2))/θ̂1: ``original_darc_accel``).
6. Step 2 (Eqs. 26, 29): Q_Ld = -e2 r2/r3 + n A_a² x2 p_a/V_a + n A_b² x2 p_b/V_b - A_a θ̂5
   + A_b θ̂6 + dF_pd - k3 e3 - h3² e3/(4 ε3), V_a, V_b of Eq. (6) at x1 (clipped to the stroke).
7. Step 3 (Eqs. 32-33 corrected, :mod:`pneutune.control.law.duty`): Q_L,F from the measured
   pressures, the five cases, the inverse PWM curve; with ``dead_zone: dither`` the openings
   below the curve's dead-zone knee become whole pulses in some PWM periods (a sigma-delta).

``pid``: step 1 runs for v̂ and the logs; Q_Ld = -(kp e1 + ki ∫e1 + kd (v̂ - v_r)), then step 7.

No allocation in :func:`step_into`, no Python objects, no exceptions (IEEE arithmetic: a
division by zero gives inf/nan, and a non-finite Q_Ld closes every valve, Eq. 33 case 3).
"""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from pneutune.control.contracts.controller import (
    VARIANT_DIRECT_DIFF,
    VARIANT_MODIFIED_DARC,
    VARIANT_ORIGINAL_DARC,
    VARIANT_PID,
    ControllerConfig,
)
from pneutune.control.law import clib
from pneutune.control.law.layout import (
    CFG_LAYOUT,
    CFG_LAYOUT_ID,
    CFG_SIZE,
    pack,
)
from pneutune.control.logs.topics import topic_fields
from pneutune.control.numba_cache import njit

# --- measurement vector ------------------------------------------------------------------------
M_T, M_X, M_P_A, M_P_B, M_P_S, M_X_R, M_V_R, M_A_R = 0, 1, 2, 3, 4, 5, 6, 7
MEAS_SIZE = 8
#: Names of the measurement slots, in order.
MEAS_FIELDS: tuple[str, ...] = ("t", "x", "p_a", "p_b", "p_s", "x_r", "v_r", "a_r")

# --- state vector ------------------------------------------------------------------------------
S_THETA = 0          #: θ̂ (6): M [kg], F_n [N], b_v [N s/m], A_f [N], D_an, D_bn [Pa/s]
S_MX = 6             #: motion filter mean (3): x̂ [m], v̂ [m/s], â [m/s^2]
S_MP = 9             #: motion filter covariance (9, 3x3 row-major)
S_FX = 18            #: force filter mean (2): F̂_pd [N], dF̂_pd [N/s]
S_FP = 20            #: force filter covariance (4, 2x2 row-major)
S_F_PD_PREV = 24     #: F_pd of the previous step [N] (direct_diff)
S_A_R_PREV = 25      #: a_r of the previous step [m/s^2] (original_darc: reference jerk)
S_PID_I = 26         #: ∫e1 dt [m s] (pid)
S_N_STEPS = 27       #: steps taken so far
S_STATUS = 28        #: 0 ok; 1 cfg vector of another layout (every valve closed)
S_E1 = 29            #: e1 = x1 - x_r [m]
S_E2 = 30            #: e2 = x2 - x2eq [m/s]
S_E3 = 31            #: e3 = F_p - F_pd [N]
S_X_HAT = 32         #: x̂ [m]
S_V_HAT = 33         #: v̂ [m/s]
S_A_HAT = 34         #: â [m/s^2]
S_F_PD = 35          #: F_pd [N]
S_DF_PD = 36         #: dF_pd/dt used [N/s]
S_Q_LD = 37          #: Q_Ld [N/s]
S_Q_LF = 38          #: Q_L,F of the active mode [N/s]
S_CASE = 39          #: Eq. (33) case, 1..5
S_THETA_DOT = 40     #: effective dθ̂/dt of this step (6)
S_TAU = 46           #: τ (6)
S_U = 52             #: effective open fractions wanted (4), before the PWM inverse
S_F_P = 56           #: F_p [N]
S_DZ_ACC = 57        #: dead-zone sigma-delta accumulators (4) [open fraction x periods]
S_DZ_PULSE = 61      #: 1 if the valve has its dead-zone pulse in this PWM period (4)
S_DZ_PERIOD = 65     #: index of the last PWM period decided by the dither (-1 before)
S_WORK = 66          #: scratch for the Kalman kernels (21); no meaning between steps
STATE_SIZE = S_WORK + 21

#: Fields of the ``/control/state`` log topic (contract 1) and their state indices;
#: ``theta_hat`` is the 6-vector at S_THETA.
_STATE_INDEX = {
    "e1": S_E1, "e2": S_E2, "e3": S_E3, "x_hat": S_X_HAT, "v_hat": S_V_HAT, "a_hat": S_A_HAT,
    "F_pd": S_F_PD, "dF_pd": S_DF_PD, "Q_Ld": S_Q_LD,
}
CONTROL_STATE_FIELDS: dict[str, int] = {name: _STATE_INDEX[name]
                                        for name in topic_fields("/control/state")[:-1]}



@njit(cache=True, error_model="numpy")
def step_into(state: np.ndarray, meas: np.ndarray, cfg: np.ndarray,
              duties_out: np.ndarray) -> int:
    """One controller step (see the module docstring), writing the duties into ``duties_out``.

    Parameters
    ----------
    state : (STATE_SIZE,) float64
        Controller state, updated in place.
    meas : (MEAS_SIZE,) float64
        ``[t, x, p_a, p_b, p_s, x_r, v_r, a_r]`` [s, m, Pa, Pa, Pa, m, m/s, m/s^2].
    cfg : (CFG_SIZE,) float64
        Packed config (:func:`pneutune.control.law.layout.pack`).
    duties_out : (4,) float64
        Receives the duties of a_in, a_out, b_in, b_out (0..1).

    Returns
    -------
    int
        The Eq. (33) case (1..5), or 0 when ``cfg`` has another layout (all valves closed).
    """
    return clib.pt_step_into(state.ctypes, meas.ctypes, cfg.ctypes, duties_out.ctypes)


@njit(cache=True, error_model="numpy")
def step(state: np.ndarray, meas: np.ndarray, cfg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One controller step: ``(state, duties)``; ``state`` is updated in place and returned.

    Parameters
    ----------
    state : (STATE_SIZE,) float64
        Controller state (:func:`init_state`).
    meas : (MEAS_SIZE,) float64
        ``[t, x, p_a, p_b, p_s, x_r, v_r, a_r]`` [s, m, Pa, Pa, Pa, m, m/s, m/s^2].
    cfg : (CFG_SIZE,) float64
        Packed config.

    Returns
    -------
    state : (STATE_SIZE,) float64
        The same array, updated.
    duties : (4,) float64
        Commanded duties of a_in, a_out, b_in, b_out (0..1).
    """
    duties = np.empty(4)
    step_into(state, meas, cfg, duties)
    return state, duties


def init_state(cfg: ControllerConfig | np.ndarray, x0: float, p_a0: float,
               p_b0: float) -> np.ndarray:
    """The controller state at the start of a run.

    θ̂ = θ_0; the motion filter at x̂ = [x0, 0, 0] (piston at rest) with
    P0 = diag(R, R/Ts², R/Ts⁴) (one measurement-noise standard deviation per sample of each
    derivative); the force filter is set at the first step to [F_pd, 0] with P0 = diag(R_f,
    R_f/Ts²); the PID integral is 0. The logged F_p and F_pd start at the force of the initial
    pressures, F_p0 = A_a p_a0 - A_b p_b0 - p0 A_r.

    Parameters
    ----------
    cfg : ControllerConfig or (CFG_SIZE,) float64
        The config or its packed vector.
    x0 : float
        Initial position [m].
    p_a0, p_b0 : float
        Initial chamber pressures [Pa abs].

    Returns
    -------
    (STATE_SIZE,) float64
    """
    v = pack(cfg) if isinstance(cfg, ControllerConfig) else np.asarray(cfg, dtype=np.float64)
    if v.shape != (CFG_SIZE,) or v[CFG_LAYOUT] != CFG_LAYOUT_ID:
        raise ValueError(f"cfg must be a ControllerConfig or a vector from pack() "
                         f"(length {CFG_SIZE}), got shape {v.shape}")
    v = np.ascontiguousarray(v)
    s = np.zeros(STATE_SIZE)
    ptr = ctypes.POINTER(ctypes.c_double)
    clib.LIB.pt_init_state(s.ctypes.data_as(ptr), v.ctypes.data_as(ptr), float(x0), float(p_a0),
                           float(p_b0))
    return s


def make_meas(t: float, x: float, p_a: float, p_b: float, p_s: float, x_r: float, v_r: float,
              a_r: float) -> np.ndarray:
    """The measurement vector ``[t, x, p_a, p_b, p_s, x_r, v_r, a_r]`` (SI units)."""
    return np.array([t, x, p_a, p_b, p_s, x_r, v_r, a_r], dtype=np.float64)


def state_view(state: np.ndarray) -> dict[str, Any]:
    """Named, readable copy of a state vector (for Python users and tests).

    Returns
    -------
    dict
        ``theta_hat`` (6), ``x_motion`` (3), ``P_motion`` (3x3), ``x_force`` (2),
        ``P_force`` (2x2), ``theta_dot`` (6), ``tau`` (6), ``u`` (4), ``dither_acc`` and
        ``dither_pulse`` (4 each, ``dead_zone: dither``), every
        :data:`CONTROL_STATE_FIELDS` entry, and ``F_p``, ``Q_LF``, ``case``, ``pid_integral``,
        ``n_steps``, ``status``.
    """
    s = np.asarray(state, dtype=np.float64)
    out: dict[str, Any] = {
        "theta_hat": s[S_THETA:S_THETA + 6].copy(),
        "x_motion": s[S_MX:S_MX + 3].copy(),
        "P_motion": s[S_MP:S_MP + 9].reshape(3, 3).copy(),
        "x_force": s[S_FX:S_FX + 2].copy(),
        "P_force": s[S_FP:S_FP + 4].reshape(2, 2).copy(),
        "theta_dot": s[S_THETA_DOT:S_THETA_DOT + 6].copy(),
        "tau": s[S_TAU:S_TAU + 6].copy(),
        "u": s[S_U:S_U + 4].copy(),
        "dither_acc": s[S_DZ_ACC:S_DZ_ACC + 4].copy(),
        "dither_pulse": s[S_DZ_PULSE:S_DZ_PULSE + 4].copy(),
    }
    for name, idx in CONTROL_STATE_FIELDS.items():
        out[name] = float(s[idx])
    out.update(F_p=float(s[S_F_P]), Q_LF=float(s[S_Q_LF]), case=int(s[S_CASE]),
               pid_integral=float(s[S_PID_I]), n_steps=int(s[S_N_STEPS]),
               status=int(s[S_STATUS]))
    return out


def control_state_record(state: np.ndarray) -> dict[str, Any]:
    """The ``/control/state`` message of contract 1 for this state (floats and a list)."""
    rec: dict[str, Any] = {name: float(state[idx]) for name, idx in CONTROL_STATE_FIELDS.items()}
    rec["theta_hat"] = [float(v) for v in state[S_THETA:S_THETA + 6]]
    return rec


__all__ = [
    "CONTROL_STATE_FIELDS", "MEAS_FIELDS", "MEAS_SIZE", "STATE_SIZE", "VARIANT_DIRECT_DIFF",
    "VARIANT_MODIFIED_DARC", "VARIANT_ORIGINAL_DARC", "VARIANT_PID", "control_state_record",
    "init_state", "make_meas", "state_view", "step", "step_into",
]
