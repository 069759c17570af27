"""Plain-Python reading of the paper's equations: the test oracle of the compiled DARC step.

Written from the paper (Eqs. 4, 6-13, 17, 20, 26, 29, 32-36) and docs/controller.md, not from
control/law/darc.py: it reads the validated ControllerConfig (not the packed vector), uses numpy
matrix algebra for the Kalman filters, Python loops elsewhere, and its own Eq. (7) flow (without
the plant's regularisation within 0.1 % of p_d = p_u, so tests keep pressures away from it).
Used only by tests/test_darc_step.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pneutune.control.constants import RHO0, T_REF
from pneutune.control.contracts.controller import ControllerConfig


def s_f(v: float) -> float:
    """Eq. (4)."""
    return 2.0 / math.pi * math.atan(1000.0 * v)


def eq7(C: float, b: float, p_u: float, p_d: float, T_u: float) -> float:
    """Eq. (7), ISO 6358 mass flow [kg/s] (0 for p_d >= p_u)."""
    if p_d >= p_u:
        return 0.0
    choked = C * RHO0 * p_u * math.sqrt(T_REF / T_u)
    r = p_d / p_u
    if r <= b:
        return choked
    return choked * math.sqrt(1.0 - ((r - b) / (1.0 - b)) ** 2)


def pwm_inverse(u: float, duty: list[float], ratio: list[float]) -> float:
    """Smallest duty whose effective fraction on the piecewise-linear curve reaches u; a full
    opening (u at or above the curve's top) is duty 1, the valve always on (control/law/duty.py:
    one curve for four valves whose delays differ)."""
    if u <= 0.0:
        return 0.0
    if u >= ratio[-1]:
        return 1.0
    for i in range(1, len(duty)):
        if ratio[i] >= u:
            if ratio[i] == u:
                return duty[i]
            return duty[i - 1] + (u - ratio[i - 1]) / (ratio[i] - ratio[i - 1]) * (
                duty[i] - duty[i - 1])
    return duty[-1]


def f_pd(cfg: ControllerConfig, theta: np.ndarray, x1: float, x2: float, x_r: float,
         v_r: float, a_r: float) -> float:
    """F_pd of Eq. (17) with F_pds2 of Eq. (20) (h2 constant)."""
    g = cfg.gains
    e1 = x1 - x_r
    e2 = x2 - (v_r - g.k1 * e1)
    dx2eq = a_r - g.k1 * (x2 - v_r)
    return (-theta[1] + theta[2] * x2 + theta[3] * s_f(x2) + theta[0] * dx2eq - g.k2 * e2
            - g.h2**2 * e2 / (4 * g.eps2))


@dataclass
class OracleState:
    theta: np.ndarray
    xm: np.ndarray
    Pm: np.ndarray
    xf: np.ndarray = field(default_factory=lambda: np.zeros(2))
    Pf: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    f_pd_prev: float = 0.0
    a_r_prev: float = 0.0
    integral: float = 0.0
    n: int = 0
    log: dict = field(default_factory=dict)


class DarcOracle:
    """The controller of the paper, step by step, in plain Python."""

    def __init__(self, cfg: ControllerConfig, x0: float) -> None:
        self.cfg = cfg
        Ts = cfg.rig.Ts
        self.Am = np.array([[1, Ts, Ts**2 / 2], [0, 1, Ts], [0, 0, 1]], dtype=float)
        self.Wm = np.array([[Ts**2 / 2], [Ts], [1.0]])
        self.Hm = np.array([[1.0, 0.0, 0.0]])
        self.Af = np.array([[1, Ts], [0, 1]], dtype=float)
        self.Wf = np.array([[Ts**2 / 2], [Ts]])
        self.Hf = np.array([[1.0, 0.0]])
        R = cfg.kalman.motion.R
        self.s = OracleState(theta=np.array(cfg.adaptation.theta_0, dtype=float),
                             xm=np.array([x0, 0.0, 0.0]),
                             Pm=np.diag([R, R / Ts**2, R / Ts**4]))

    @staticmethod
    def _kf(x, P, A, W, H, Q, R, z):
        """Eqs. (35)-(36), Joseph form, matrix algebra."""
        x = A @ x
        P = A @ P @ A.T + W @ W.T * Q
        S = (H @ P @ H.T).item() + R
        K = (P @ H.T) / S
        x = x + (K * (z - (H @ x).item())).ravel()
        IKH = np.eye(len(x)) - K @ H
        P = IKH @ P @ IKH.T + K @ K.T * R
        return x, P

    def step(self, meas: np.ndarray) -> np.ndarray:
        """meas = [t, x, p_a, p_b, p_s, x_r, v_r, a_r]; returns the four duties."""
        cfg, s = self.cfg, self.s
        rig, g, ad = cfg.rig, cfg.gains, cfg.adaptation
        Ts = rig.Ts
        _, x, p_a, p_b, p_s, x_r, v_r, a_r = (float(m) for m in meas)
        first = s.n == 0
        s.xm, s.Pm = self._kf(s.xm, s.Pm, self.Am, self.Wm, self.Hm, cfg.kalman.motion.Q,
                              cfg.kalman.motion.R, x)
        x1 = s.xm[0] if cfg.position_feedback == "filtered" else x
        x2 = s.xm[1]
        xc = min(max(x1, rig.x_min), rig.x_max)
        V_a = rig.V0a + rig.A_a * (xc - rig.x_min)
        V_b = rig.V0b + rig.A_b * (rig.x_max - xc)
        A_r = rig.A_a - rig.A_b
        F_p = rig.A_a * p_a - rig.A_b * p_b - rig.p0 * A_r
        e1 = x1 - x_r
        e2 = x2 - (v_r - g.k1 * e1)
        dx2eq = a_r - g.k1 * (x2 - v_r)
        th = s.theta.copy()
        F_pd = e3 = dF = 0.0
        thdot = np.zeros(6)
        if cfg.variant == "pid":
            s.integral = min(max(s.integral + Ts * e1, -cfg.pid.i_max), cfg.pid.i_max)
            q_ld = -(cfg.pid.kp * e1 + cfg.pid.ki * s.integral + cfg.pid.kd * (x2 - v_r))
        else:
            F_pd = f_pd(cfg, th, x1, x2, x_r, v_r, a_r)
            e3 = F_p - F_pd
            phi2 = np.array([-dx2eq, 1.0, -x2, -s_f(x2), 0.0, 0.0])
            phi3 = np.array([0.0, 0.0, 0.0, 0.0, rig.A_a, -rig.A_b])
            tau = g.r2 * phi2 * e2 + g.r3 * phi3 * e3
            if abs(v_r) > ad.min_ref_speed:
                for i in range(6):
                    r = ad.gamma[i] * tau[i]
                    if (th[i] >= ad.theta_max[i] and r > 0) or (th[i] <= ad.theta_min[i]
                                                                 and r < 0):
                        r = 0.0
                    r = max(-ad.rate_max[i], min(ad.rate_max[i], r))
                    new = min(max(th[i] + Ts * r, ad.theta_min[i]), ad.theta_max[i])
                    thdot[i] = (new - th[i]) / Ts
                    s.theta[i] = new
            if cfg.variant == "modified_darc":
                if first:
                    Rf = cfg.kalman.force.R
                    s.xf = np.array([F_pd, 0.0])
                    s.Pf = np.diag([Rf, Rf / Ts**2])
                else:
                    s.xf, s.Pf = self._kf(s.xf, s.Pf, self.Af, self.Wf, self.Hf,
                                          cfg.kalman.force.Q, cfg.kalman.force.R, F_pd)
                dF = s.xf[1]
            elif cfg.variant == "direct_diff":
                dF = 0.0 if first else (F_pd - s.f_pd_prev) / Ts
            else:  # original_darc: docs/original_darc.md
                j_r = 0.0 if first else (a_r - s.a_r_prev) / Ts
                kappa2 = g.k2 + g.h2**2 / (4 * g.eps2)
                dsf = 2 / math.pi * 1000.0 / (1 + (1000.0 * x2) ** 2)
                if cfg.original_darc_accel == "model":
                    x2dot = (F_p + th[1] - th[2] * x2 - th[3] * s_f(x2)) / th[0]
                else:
                    x2dot = s.xm[2]
                dF = (-kappa2 * g.k1 * x2
                      + (th[2] + th[3] * dsf - th[0] * g.k1 - kappa2) * x2dot
                      + th[0] * (j_r + g.k1 * a_r) + kappa2 * (a_r + g.k1 * v_r)
                      - float(phi2 @ thdot))
            n = rig.n
            q_ld = (-e2 * g.r2 / g.r3 + n * rig.A_a**2 * x2 * p_a / V_a
                    + n * rig.A_b**2 * x2 * p_b / V_b - rig.A_a * th[4] + rig.A_b * th[5] + dF
                    - g.k3 * e3 - g.h3**2 * e3 / (4 * g.eps3))
        # Eq. (32) corrected and Eq. (33) with Q_L,F
        v = cfg.valves
        nRT = rig.n * rig.R * rig.T0
        if q_ld > 0:
            q_lf = nRT * (rig.A_a * eq7(v.a_in.C, v.a_in.b, p_s, p_a, rig.T0) / V_a
                          + rig.A_b * eq7(v.b_out.C, v.b_out.b, p_b, rig.p0, rig.T0) / V_b)
            u = min(q_ld / q_lf, 1.0) if q_lf > 0 else 1.0
            fr = [u, 0.0, 0.0, u]
        elif q_ld < 0:
            q_lf = nRT * (rig.A_a * eq7(v.a_out.C, v.a_out.b, p_a, rig.p0, rig.T0) / V_a
                          + rig.A_b * eq7(v.b_in.C, v.b_in.b, p_s, p_b, rig.T0) / V_b)
            u = min(-q_ld / q_lf, 1.0) if q_lf > 0 else 1.0
            fr = [0.0, u, u, 0.0]
        else:
            q_lf = 0.0
            fr = [0.0, 0.0, 0.0, 0.0]
        duties = np.array([pwm_inverse(f, list(c.duty), list(c.ratio))  # each valve's curve
                           for f, c in zip(fr, cfg.valve_curves, strict=True)])
        s.f_pd_prev = F_pd
        s.a_r_prev = a_r
        s.n += 1
        s.log = {"e1": e1, "e2": e2, "e3": e3, "x_hat": s.xm[0], "v_hat": s.xm[1],
                 "a_hat": s.xm[2], "F_pd": F_pd, "dF_pd": dF, "Q_Ld": q_ld, "Q_LF": q_lf,
                 "theta_hat": s.theta.copy()}
        return duties
