"""The flat float64 vector the compiled control step reads: its slots, and :func:`pack`.

The slots are declared once, in order, in :data:`SLOTS` (name, width, meaning); their indices
follow from the order. The module-level ``CFG_*`` integers are what the numba code indexes with
(numba freezes module globals at compile time), and :func:`_offsets` checks that every one of
them equals its declared place, so the table and the names cannot drift apart.

Derived slots (the Kalman matrices of Eq. 34, nR, A_r) are computed by :func:`pack` once, not
per step. :data:`CFG_LAYOUT_ID` is written into the vector and checked by the step (a mismatch
closes every valve and sets the state's status): a vector packed for another layout never runs.
"""

from __future__ import annotations

import numpy as np

from pneutune.control.contracts.controller import (
    DEAD_ZONE_MODES,
    ORIGINAL_DARC_ACCEL,
    POSITION_FEEDBACK,
    PWM_MAX_POINTS,
    VARIANTS,
    ControllerConfig,
)
from pneutune.control.law.duty import dead_zone_knee
from pneutune.control.law.kalman import force_model, motion_model, process_cov

#: The slots in order: (name, width, meaning). SI units.
SLOTS: tuple[tuple[str, int, str], ...] = (
    ("CFG_LAYOUT", 1, "layout id written by pack, checked by the step"),
    ("CFG_VARIANT", 1, "variant code (VARIANTS)"),
    ("CFG_POS_FB", 1, "position feedback code (POSITION_FEEDBACK)"),
    ("CFG_ORIG_ACCEL", 1, "original_darc dx2/dt code (ORIGINAL_DARC_ACCEL)"),
    ("CFG_TS", 1, "rig.Ts [s]"),
    ("CFG_A_A", 1, "rig.A_a [m^2]"),
    ("CFG_A_B", 1, "rig.A_b [m^2]"),
    ("CFG_A_R", 1, "A_a - A_b [m^2]"),
    ("CFG_X_MIN", 1, "rig.x_min [m]"),
    ("CFG_X_MAX", 1, "rig.x_max [m]"),
    ("CFG_V0A", 1, "rig.V0a [m^3]"),
    ("CFG_V0B", 1, "rig.V0b [m^3]"),
    ("CFG_P0", 1, "rig.p0 [Pa]"),
    ("CFG_T0", 1, "rig.T0 [K]"),
    ("CFG_N", 1, "rig.n, polytropic exponent [-]"),
    ("CFG_NR", 1, "rig.n * rig.R [J/(kg K)]"),
    ("CFG_VALVE_C", 4, "C of a_in, a_out, b_in, b_out [m^3/(s Pa)]"),
    ("CFG_VALVE_B", 4, "b of a_in, a_out, b_in, b_out [-]"),
    ("CFG_K1", 1, "k1 [1/s]"),
    ("CFG_K2", 1, "k2 [N s/m]"),
    ("CFG_K3", 1, "k3 [1/s]"),
    ("CFG_R2", 1, "r2 [-]"),
    ("CFG_R3", 1, "r3 [-]"),
    ("CFG_EPS2", 1, "eps2"),
    ("CFG_EPS3", 1, "eps3"),
    ("CFG_H2", 1, "h2 [N]"),
    ("CFG_H3", 1, "h3 [N/s]"),
    ("CFG_GAMMA", 6, "Γ diagonal"),
    ("CFG_RATE_MAX", 6, "adaptation rate limits"),
    ("CFG_THETA_MIN", 6, "θ_min"),
    ("CFG_THETA_MAX", 6, "θ_max"),
    ("CFG_THETA_0", 6, "θ_0"),
    ("CFG_MIN_REF_SPEED", 1, "adaptation only above this reference speed [m/s]"),
    ("CFG_KM_Q", 1, "motion filter Q [m^2/s^4]"),
    ("CFG_KM_R", 1, "motion filter R [m^2]"),
    ("CFG_KF_Q", 1, "force filter Q [N^2/s^4]"),
    ("CFG_KF_R", 1, "force filter R [N^2]"),
    ("CFG_KM_A", 9, "motion A_d (3x3 row-major), Eq. (34)"),
    ("CFG_KM_WQW", 9, "motion W_d Q W_d^T (3x3)"),
    ("CFG_KM_H", 3, "motion H_d"),
    ("CFG_KF_A", 4, "force A_d (2x2)"),
    ("CFG_KF_WQW", 4, "force W_d Q W_d^T (2x2)"),
    ("CFG_KF_H", 2, "force H_d"),
    ("CFG_PID_KP", 1, "pid kp"),
    ("CFG_PID_KI", 1, "pid ki"),
    ("CFG_PID_KD", 1, "pid kd"),
    ("CFG_PID_IMAX", 1, "pid integral limit"),
    ("CFG_PWM_N", 4, "number of points m_v of each valve's PWM curve"),
    ("CFG_PWM_DUTY", 4 * PWM_MAX_POINTS,
     "duty[:m_v] of valve v (a_in, a_out, b_in, b_out) from v * PWM_MAX_POINTS"),
    ("CFG_PWM_RATIO", 4 * PWM_MAX_POINTS, "ratio[:m_v] of valve v, laid out as duty"),
    ("CFG_PWM_PERIOD", 1, "PWM carrier period 1/rig.pwm_hz [s]"),
    ("CFG_DZ_MODE", 1, "dead_zone code (DEAD_ZONE_MODES)"),
    ("CFG_DZ_DUTY", 4, "duty at each valve curve's dead-zone knee (duty.dead_zone_knee)"),
    ("CFG_DZ_RATIO", 4, "open fraction at each knee; 0: the curve has no dead zone"),
)

CFG_LAYOUT, CFG_VARIANT, CFG_POS_FB, CFG_ORIG_ACCEL = 0, 1, 2, 3
CFG_TS, CFG_A_A, CFG_A_B, CFG_A_R, CFG_X_MIN, CFG_X_MAX = 4, 5, 6, 7, 8, 9
CFG_V0A, CFG_V0B, CFG_P0, CFG_T0, CFG_N, CFG_NR = 10, 11, 12, 13, 14, 15
CFG_VALVE_C, CFG_VALVE_B = 16, 20
CFG_K1, CFG_K2, CFG_K3, CFG_R2, CFG_R3, CFG_EPS2, CFG_EPS3, CFG_H2, CFG_H3 = range(24, 33)
CFG_GAMMA, CFG_RATE_MAX, CFG_THETA_MIN, CFG_THETA_MAX, CFG_THETA_0 = 33, 39, 45, 51, 57
CFG_MIN_REF_SPEED, CFG_KM_Q, CFG_KM_R, CFG_KF_Q, CFG_KF_R = 63, 64, 65, 66, 67
CFG_KM_A, CFG_KM_WQW, CFG_KM_H, CFG_KF_A, CFG_KF_WQW, CFG_KF_H = 68, 77, 86, 89, 93, 97
CFG_PID_KP, CFG_PID_KI, CFG_PID_KD, CFG_PID_IMAX, CFG_PWM_N = 99, 100, 101, 102, 103
#: Distance between two valves' curves in CFG_PWM_DUTY and CFG_PWM_RATIO.
PWM_STRIDE: int = PWM_MAX_POINTS
CFG_PWM_DUTY = 107
CFG_PWM_RATIO = CFG_PWM_DUTY + 4 * PWM_STRIDE
CFG_PWM_PERIOD = CFG_PWM_RATIO + 4 * PWM_STRIDE
CFG_DZ_MODE, CFG_DZ_DUTY, CFG_DZ_RATIO = CFG_PWM_PERIOD + 1, CFG_PWM_PERIOD + 2, CFG_PWM_PERIOD + 6


def _offsets() -> int:
    """Check every ``CFG_*`` name against its place in :data:`SLOTS`; the vector's size."""
    index = 0
    names = globals()
    for name, width, _ in SLOTS:
        if names[name] != index:
            raise RuntimeError(f"layout: {name} = {names[name]}, but SLOTS puts it at {index}")
        index += width
    return index


#: Length of the vector.
CFG_SIZE: int = _offsets()
#: Identifies this layout; changes whenever a slot is added or moved.
CFG_LAYOUT_ID: float = float(1_000_000 + CFG_SIZE * 100 + CFG_PWM_DUTY % 100)


def pack(cfg: ControllerConfig) -> np.ndarray:
    """Flatten a config into the float64 vector read by the compiled step.

    Parameters
    ----------
    cfg : ControllerConfig
        A validated config.

    Returns
    -------
    (CFG_SIZE,) float64
        Values at the ``CFG_*`` indices of this module, SI units.
    """
    v = np.zeros(CFG_SIZE)
    rig = cfg.rig
    v[CFG_LAYOUT] = CFG_LAYOUT_ID
    v[CFG_VARIANT] = VARIANTS.index(cfg.variant)
    v[CFG_POS_FB] = POSITION_FEEDBACK.index(cfg.position_feedback)
    v[CFG_ORIG_ACCEL] = ORIGINAL_DARC_ACCEL.index(cfg.original_darc_accel)
    v[CFG_TS] = rig.Ts
    v[CFG_A_A], v[CFG_A_B], v[CFG_A_R] = rig.A_a, rig.A_b, rig.A_a - rig.A_b
    v[CFG_X_MIN], v[CFG_X_MAX] = rig.x_min, rig.x_max
    v[CFG_V0A], v[CFG_V0B] = rig.V0a, rig.V0b
    v[CFG_P0], v[CFG_T0], v[CFG_N], v[CFG_NR] = rig.p0, rig.T0, rig.n, rig.n * rig.R
    for i, valve in enumerate(cfg.valves.ordered()):
        v[CFG_VALVE_C + i] = valve.C
        v[CFG_VALVE_B + i] = valve.b
    g = cfg.gains
    v[CFG_K1], v[CFG_K2], v[CFG_K3] = g.k1, g.k2, g.k3
    v[CFG_R2], v[CFG_R3], v[CFG_EPS2], v[CFG_EPS3] = g.r2, g.r3, g.eps2, g.eps3
    v[CFG_H2], v[CFG_H3] = g.h2, g.h3
    a = cfg.adaptation
    v[CFG_GAMMA:CFG_GAMMA + 6] = a.gamma
    v[CFG_RATE_MAX:CFG_RATE_MAX + 6] = a.rate_max
    v[CFG_THETA_MIN:CFG_THETA_MIN + 6] = a.theta_min
    v[CFG_THETA_MAX:CFG_THETA_MAX + 6] = a.theta_max
    v[CFG_THETA_0:CFG_THETA_0 + 6] = a.theta_0
    v[CFG_MIN_REF_SPEED] = a.min_ref_speed
    k = cfg.kalman
    v[CFG_KM_Q], v[CFG_KM_R] = k.motion.Q, k.motion.R
    v[CFG_KF_Q], v[CFG_KF_R] = k.force.Q, k.force.R
    A, W, H = motion_model(rig.Ts)
    v[CFG_KM_A:CFG_KM_A + 9] = A.ravel()
    v[CFG_KM_WQW:CFG_KM_WQW + 9] = process_cov(W, k.motion.Q).ravel()
    v[CFG_KM_H:CFG_KM_H + 3] = H
    A, W, H = force_model(rig.Ts)
    v[CFG_KF_A:CFG_KF_A + 4] = A.ravel()
    v[CFG_KF_WQW:CFG_KF_WQW + 4] = process_cov(W, k.force.Q).ravel()
    v[CFG_KF_H:CFG_KF_H + 2] = H
    p = cfg.pid
    v[CFG_PID_KP], v[CFG_PID_KI], v[CFG_PID_KD], v[CFG_PID_IMAX] = p.kp, p.ki, p.kd, p.i_max
    for i, curve in enumerate(cfg.valve_curves):
        m = len(curve.duty)
        v[CFG_PWM_N + i] = m
        at = i * PWM_STRIDE
        v[CFG_PWM_DUTY + at:CFG_PWM_DUTY + at + m] = curve.duty
        v[CFG_PWM_RATIO + at:CFG_PWM_RATIO + at + m] = curve.ratio
        v[CFG_DZ_DUTY + i], v[CFG_DZ_RATIO + i] = dead_zone_knee(curve.duty, curve.ratio)
    v[CFG_PWM_PERIOD] = rig.pwm_period
    v[CFG_DZ_MODE] = DEAD_ZONE_MODES.index(cfg.dead_zone)
    return v
