"""The simulated rig: the paper's Sec. 2 model with every term, compiled with numba.

State ``y = [x, v, p_a, p_b]`` plus a *stuck* flag (see :mod:`pneutune.control.plant.params`).

Motion, Eq. (1)
    ``M dv/dt = p_a A_a - p_b A_b - p0 A_r - F_f + F_ext`` with ``F_ext = F_n + F_step(t)``,
    ``M = mass + payload`` and ``F_f`` the Stribeck friction of Eq. (2) while sliding.
Stiction (Eq. 2, ``F_e`` branch)
    When the velocity reaches zero the piston sticks if the applied force
    ``F_app = p_a A_a - p_b A_b - p0 A_r + F_ext`` is at most ``F_S`` in magnitude; it stays stuck
    (x, v frozen, friction = F_app) until ``|F_app| > F_S``, then breaks away with friction
    ``F_S`` in the direction of motion. The zero crossing of v and the break-away instant are
    located inside the integration step (linear interpolation, then the step is redone to
    that instant), so stick/slip does not depend on the step grid.
End stops
    Hard and inelastic at ``x_min`` and ``x_max``: the piston stops there (v = 0) and stays while
    the force pushes it into the stop or does not exceed F_S away from it.
Chambers, Eqs. (5)-(6)
    ``dp_i/dt = -n p_i dV_i/dt / V_i + n R T0 mdot_i / V_i + D_i`` with
    ``V_a = V0a + A_a (x - x_min)``, ``V_b = V0b + A_b (x_max - x)`` and constant gas temperature
    T0 (the paper's assumption). ``mdot_i`` is the net inflow: the chamber's two valves by
    ISO 6358 (Eq. 7, reverse flow included) and the optional seal leak A<->B (ISO 6358 form,
    b = 0).
Real-rig effects (contract 2; each off by default, and then the model above is computed by
exactly the code it had before they existed)
    *Valve armature lag*: after its switching delay a valve's open fraction moves
    exponentially (``tau_open``/``tau_close``) and scales its Eq. (7) flow. *Lines*: a transport
    delay added to the chamber's valves' delays, a volume added to its dead volume, and a
    conductance in series with its valves, met at a junction of negligible volume solved
    quasi-statically. *Heat transfer*: chamber temperatures as states, the energy equation with
    ``gamma`` and wall convection ``h`` instead of the polytropic exponent. *Pre-sliding*: LuGre
    friction (bristle deflection z as a state) whose steady sliding is Eq. (2); no stick events,
    the end stops still hold the piston. *Sensor lags*: first-order lags of the position and
    pressure readings, integrated along the trajectory, and a pressure quantum. *Transmitters
    at the valves*: a chamber's pressure read at its valves' junction, upstream of the line
    (:func:`port_pressure`). *IO delay*: duty
    writes wait in the state and act later. *Supply droop*: a supply line of conductance C into a
    manifold whose pressure (a state) feeds the inlet valves and the supply transmitter.
    :func:`_deriv` is the paper's right-hand side; :func:`_deriv_rig` adds the effects, and
    :func:`_step` picks between them once per step. The flows into the chambers, with and
    without the effects, are :mod:`pneutune.control.plant.flows`.
Integration
    Classical RK4 with steps of at most ``sim.dt``, split at every valve switching instant,
    controller sample and force step, so that the right-hand side is smooth inside every step.
    The step size comes from a convergence study (docs/integration.md). While sliding, a step
    is also at most ``2 M / k(u)`` (``params.STEP_STIFFNESS``), k the largest |dF_f/dv| of
    Eq. (2) at the speeds u the step passes through, at least b_v
    (:func:`~pneutune.control.physics.friction.stribeck_stiffness`): the
    falling Stribeck branch of a steep friction law (large F_S - F_C, small v_s) needs steps
    of tens of microseconds, but only near v = 0; elsewhere, and while stuck, ``sim.dt``
    stands. A step that ends slower than the speed its length was chosen for is taken again,
    shorter. (A plant whose friction never limits the step is integrated on exactly the grid
    of ``sim.dt``.)
"""

from __future__ import annotations

import math

import numpy as np

from pneutune.control.logs.topics import topic_fields
from pneutune.control.numba_cache import njit
from pneutune.control.numba_views import unowned
from pneutune.control.physics.flow import (
    iso6358_flow,
    signed_flow,
)
from pneutune.control.physics.friction import (
    stribeck_force,
    stribeck_level,
    stribeck_stiffness,
)
from pneutune.control.plant.flows import chamber_flows, line_flow, open_fraction, rig_flows
from pneutune.control.plant.illinois import illinois_update
from pneutune.control.plant.params import (
    IO_MAX,
    N_STATE,
    P_AA,
    P_AB,
    P_ALPHA,
    P_BV,
    P_DA,
    P_DB,
    P_DT,
    P_DTLUGRE,
    P_DTMIN,
    P_EXTSTATE,
    P_FC,
    P_FN,
    P_FS,
    P_GAMMA,
    P_GENERAL,
    P_HEAT,
    P_HEATH,
    P_IODELAY,
    P_LINEC,
    P_M,
    P_N,
    P_P0,
    P_PAT,
    P_PERIM,
    P_PLAG,
    P_PNOISE,
    P_PSTEP,
    P_R,
    P_RFLAT,
    P_RPEAK,
    P_SIGMA0,
    P_SIGMA1,
    P_STEPK,
    P_SUPB,
    P_SUPC,
    P_SUPVOL,
    P_T0,
    P_UFREE,
    P_V0A,
    P_V0B,
    P_VLAG,
    P_VS,
    P_XLAG,
    P_XMAX,
    P_XMIN,
    P_XNOISE,
    P_XSTEP,
    S_IO,
    S_IO_N,
    S_OPEN,
    S_PA,
    S_PAF,
    S_PB,
    S_PBF,
    S_PJ,
    S_PSF,
    S_PSUP,
    S_STUCK,
    S_T,
    S_TA,
    S_TB,
    S_TY,
    S_V,
    S_X,
    S_XF,
    S_Y0,
    S_Z,
)
from pneutune.control.plant.valves import EPS_T, next_event, process_events, write_duty

#: Columns of the truth array produced at each sample (``/sim/truth``).
TRUTH_FIELDS = topic_fields("/sim/truth")
#: Columns of the sensor array produced at each sample (``/rig/sensors``).
SENSOR_FIELDS = topic_fields("/rig/sensors")


@njit(cache=True)
def external_force(p: np.ndarray, force_steps: np.ndarray, t: float) -> float:
    """``F_n`` plus the level of the last force step at or before ``t`` [N]."""
    level = 0.0
    for k in range(force_steps.shape[0]):
        if force_steps[k, 0] <= t + EPS_T:
            level = force_steps[k, 1]
        else:
            break
    return p[P_FN] + level


@njit(cache=True)
def _next_force_step(force_steps: np.ndarray, t: float, t_end: float) -> float:
    for k in range(force_steps.shape[0]):
        ts = force_steps[k, 0]
        if ts > t + EPS_T:
            return ts if ts < t_end else t_end
    return t_end


@njit(cache=True)
def applied_force(p: np.ndarray, pa: float, pb: float, f_ext: float) -> float:
    """Pressure and external forces on the piston, friction excluded [N]."""
    return pa * p[P_AA] - pb * p[P_AB] - p[P_P0] * (p[P_AA] - p[P_AB]) + f_ext


@njit(cache=True, inline="always")
def _deriv(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float,
           stuck: bool, direction: float, p_s: float,
           f_ext: float) -> tuple[float, float, float, float]:
    """Right-hand side of Eqs. (1), (5)-(6) for y = [x, v, p_a, p_b]."""
    Va = p[P_V0A] + p[P_AA] * (x - p[P_XMIN])
    Vb = p[P_V0B] + p[P_AB] * (p[P_XMAX] - x)
    ma, mb = chamber_flows(p, s, pa, pb, p_s)
    nRT = p[P_N] * p[P_R] * p[P_T0]
    if stuck:
        dx = 0.0
        dv = 0.0
    else:
        # The direction of motion is frozen for the whole integration step (``direction``, the
        # sign of v at the step's start): Eq. (2)'s friction is discontinuous at v = 0, and an
        # RK4 stage that strayed past zero would otherwise flip it and push the velocity back,
        # so the step would end with v of the same sign and the stop (and the stick) would be
        # missed. With the direction frozen the stages continue the sliding solution smoothly;
        # a velocity that ends the step past zero is the event, located inside the step by
        # _integrate.
        dx = v
        ff = stribeck_force(v, direction, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_BV],
                            p[P_RFLAT])
        dv = (applied_force(p, pa, pb, f_ext) - ff) / p[P_M]
    dpa = (-p[P_N] * pa * p[P_AA] * dx + nRT * ma) / Va + p[P_DA]
    dpb = (p[P_N] * pb * p[P_AB] * dx + nRT * mb) / Vb + p[P_DB]
    return dx, dv, dpa, dpb


@njit(cache=True)
def _deriv_rig(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float,
           stuck: bool, direction: float, p_s: float, f_ext: float, t: float, ta: float,
           tb: float, z: float,
           psup: float) -> tuple[float, float, float, float, float, float, float, float]:
    """:func:`_deriv` with the real-rig effects: the flows through lagging valves, lines and a
    supply line, LuGre friction, the energy equation; and the derivatives of their states
    [T_a, T_b, z, p_sup] (zero while an effect is off)."""
    Va = p[P_V0A] + p[P_AA] * (x - p[P_XMIN])
    Vb = p[P_V0B] + p[P_AB] * (p[P_XMAX] - x)
    heat = p[P_HEAT] > 0.5
    T0 = p[P_T0]
    ha = 0.0
    hb = 0.0
    msup = 0.0
    if p[P_GENERAL] > 0.5:
        feed = psup if p[P_SUPC] > 0.0 else p_s
        ma, mb, ha, hb, msup = rig_flows(p, s, pa, pb, feed, ta if heat else T0,
                                      tb if heat else T0, t)
    else:
        ma, mb = chamber_flows(p, s, pa, pb, p_s)
    nRT = p[P_N] * p[P_R] * p[P_T0]
    dz = 0.0
    if stuck:
        dx = 0.0
        dv = 0.0
    elif p[P_SIGMA0] > 0.0:
        # LuGre: the bristles' deflection z carries the friction; no direction is frozen
        dx = v
        av = abs(v)
        g = stribeck_level(av, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_RFLAT])
        dz = v - p[P_SIGMA0] * av * z / g
        ff = p[P_SIGMA0] * z + p[P_SIGMA1] * dz + p[P_BV] * v
        dv = (applied_force(p, pa, pb, f_ext) - ff) / p[P_M]
    else:  # Eq. (2), the direction frozen over the step as in _deriv
        dx = v
        ff = stribeck_force(v, direction, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_BV],
                            p[P_RFLAT])
        dv = (applied_force(p, pa, pb, f_ext) - ff) / p[P_M]
    dta = 0.0
    dtb = 0.0
    if heat:
        # energy equation: inflow enthalpy, compression work, wall heat; then T from m = pV/RT
        gam = p[P_GAMMA]
        R = p[P_R]
        dVa = p[P_AA] * dx
        dVb = -p[P_AB] * dx
        qa = p[P_HEATH] * (2.0 * p[P_AA] + p[P_PERIM] * Va / p[P_AA]) * (T0 - ta)
        qb = p[P_HEATH] * (2.0 * p[P_AB] + p[P_PERIM] * Vb / p[P_AB]) * (T0 - tb)
        dpa = (gam * R * ha - gam * pa * dVa + (gam - 1.0) * qa) / Va + p[P_DA]
        dpb = (gam * R * hb - gam * pb * dVb + (gam - 1.0) * qb) / Vb + p[P_DB]
        dta = ta * (dpa / pa + dVa / Va - R * ta * ma / (pa * Va))
        dtb = tb * (dpb / pb + dVb / Vb - R * tb * mb / (pb * Vb))
    else:
        dpa = (-p[P_N] * pa * p[P_AA] * dx + nRT * ma) / Va + p[P_DA]
        dpb = (p[P_N] * pb * p[P_AB] * dx + nRT * mb) / Vb + p[P_DB]
    dps = 0.0
    if p[P_SUPC] > 0.0:
        m_reg = signed_flow(p[P_SUPC], p[P_SUPB], p_s, psup, T0)
        dps = nRT * (m_reg - msup) / p[P_SUPVOL]
    return dx, dv, dpa, dpb, dta, dtb, dz, dps


@njit(cache=True)
def _rk4(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float, stuck: bool,
         direction: float, p_s: float, f_ext: float,
         h: float) -> tuple[float, float, float, float]:
    k1x, k1v, k1a, k1b = _deriv(p, s, x, v, pa, pb, stuck, direction, p_s, f_ext)
    hh = 0.5 * h
    k2x, k2v, k2a, k2b = _deriv(p, s, x + hh * k1x, v + hh * k1v, pa + hh * k1a, pb + hh * k1b,
                                stuck, direction, p_s, f_ext)
    k3x, k3v, k3a, k3b = _deriv(p, s, x + hh * k2x, v + hh * k2v, pa + hh * k2a, pb + hh * k2b,
                                stuck, direction, p_s, f_ext)
    k4x, k4v, k4a, k4b = _deriv(p, s, x + h * k3x, v + h * k3v, pa + h * k3a, pb + h * k3b,
                                stuck, direction, p_s, f_ext)
    h6 = h / 6.0
    return (x + h6 * (k1x + 2.0 * (k2x + k3x) + k4x),
            v + h6 * (k1v + 2.0 * (k2v + k3v) + k4v),
            pa + h6 * (k1a + 2.0 * (k2a + k3a) + k4a),
            pb + h6 * (k1b + 2.0 * (k2b + k3b) + k4b))


@njit(cache=True)
def _rk4_rig(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float,
             stuck: bool, direction: float, p_s: float, f_ext: float, h: float, t: float,
             ta: float, tb: float, z: float,
             psup: float) -> tuple[float, float, float, float, float, float, float, float]:
    hh = 0.5 * h
    h6 = h / 6.0
    k1x, k1v, k1a, k1b, k1ta, k1tb, k1z, k1s = _deriv_rig(p, s, x, v, pa, pb, stuck, direction, p_s,
                                                      f_ext, t, ta, tb, z, psup)
    k2x, k2v, k2a, k2b, k2ta, k2tb, k2z, k2s = _deriv_rig(
        p, s, x + hh * k1x, v + hh * k1v, pa + hh * k1a, pb + hh * k1b, stuck, direction, p_s,
        f_ext, t + hh, ta + hh * k1ta, tb + hh * k1tb, z + hh * k1z, psup + hh * k1s)
    k3x, k3v, k3a, k3b, k3ta, k3tb, k3z, k3s = _deriv_rig(
        p, s, x + hh * k2x, v + hh * k2v, pa + hh * k2a, pb + hh * k2b, stuck, direction, p_s,
        f_ext, t + hh, ta + hh * k2ta, tb + hh * k2tb, z + hh * k2z, psup + hh * k2s)
    k4x, k4v, k4a, k4b, k4ta, k4tb, k4z, k4s = _deriv_rig(
        p, s, x + h * k3x, v + h * k3v, pa + h * k3a, pb + h * k3b, stuck, direction, p_s,
        f_ext, t + h, ta + h * k3ta, tb + h * k3tb, z + h * k3z, psup + h * k3s)
    return (x + h6 * (k1x + 2.0 * (k2x + k3x) + k4x),
            v + h6 * (k1v + 2.0 * (k2v + k3v) + k4v),
            pa + h6 * (k1a + 2.0 * (k2a + k3a) + k4a),
            pb + h6 * (k1b + 2.0 * (k2b + k3b) + k4b),
            ta + h6 * (k1ta + 2.0 * (k2ta + k3ta) + k4ta),
            tb + h6 * (k1tb + 2.0 * (k2tb + k3tb) + k4tb),
            z + h6 * (k1z + 2.0 * (k2z + k3z) + k4z),
            psup + h6 * (k1s + 2.0 * (k2s + k3s) + k4s))




@njit(cache=True, inline="always")
def _step(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float, stuck: bool,
          direction: float, p_s: float, f_ext: float, h: float, t: float, ta: float, tb: float,
          z: float,
          psup: float) -> tuple[float, float, float, float, float, float, float, float]:
    """One RK4 step of ``h`` from time ``t``: of the paper's model (:func:`_deriv`) when no
    real-rig effect acts on the derivatives, else of :func:`_deriv_rig`."""
    if p[P_GENERAL] < 0.5 and p[P_EXTSTATE] < 0.5:
        x1, v1, pa1, pb1 = _rk4(p, s, x, v, pa, pb, stuck, direction, p_s, f_ext, h)
        return x1, v1, pa1, pb1, ta, tb, z, psup
    return _rk4_rig(p, s, x, v, pa, pb, stuck, direction, p_s, f_ext, h, t, ta, tb, z, psup)


@njit(cache=True)
def _stick_limits(p: np.ndarray, x: float) -> tuple[float, float]:
    """Range of applied force for which a piston at rest at ``x`` stays at rest [N].

    With LuGre friction the piston never sticks in mid-stroke (the bristles let it creep), so
    only an end stop holds it, against any force that pushes it into the stop.
    """
    fs = 0.0 if p[P_SIGMA0] > 0.0 else p[P_FS]
    lo = -fs
    hi = fs
    if x >= p[P_XMAX] - 1.0e-12:
        hi = np.inf
    if x <= p[P_XMIN] + 1.0e-12:
        lo = -np.inf
    return lo, hi


@njit(cache=True)
def _locate(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float, d: float,
            p_s: float, f_ext: float, h: float, comp: int, target: float, end: float,
            t: float, ta: float, tb: float, z: float, psup: float) -> float:
    """Fraction of the step ``h`` at which the RK4 solution's component ``comp`` (0: x, 1: v)
    reaches ``target``; ``end`` is its value after the whole step.

    Regula falsi (Illinois variant) on the RK4 map, so the instant is as accurate as the
    integration itself: a straight-line guess is poor when the piston accelerates towards a
    stop, or when the velocity decays through the stiff viscous mode (b_v / M ~ 3e3 1/s).
    """
    start = x if comp == 0 else v
    a, fa = 0.0, start - target
    b, fb = 1.0, end - target
    side = 0
    c = 1.0
    tol = 1.0e-12 if comp == 0 else 1.0e-10
    for _ in range(40):
        c = (a * fb - b * fa) / (fb - fa)
        xc, vc, _, _, _, _, _, _ = _step(p, s, x, v, pa, pb, False, d, p_s, f_ext, c * h, t, ta,
                                        tb, z, psup)
        fc = (xc if comp == 0 else vc) - target
        if abs(fc) < tol or (b - a) * h < 1.0e-13:
            break
        a, fa, b, fb, side = illinois_update(a, fa, b, fb, c, fc, side)
    return c


@njit(cache=True)
def _sliding_step(p: np.ndarray, u: float) -> float:
    """Longest RK4 step while sliding at speeds of at least ``u`` [s] (module docstring)."""
    k = stribeck_stiffness(u, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_BV], p[P_RPEAK])
    return p[P_STEPK] * p[P_M] / k


@njit(cache=True)
def _lugre_step(p: np.ndarray, v: float) -> float:
    """Longest RK4 step with LuGre friction at speed ``v`` [s]: the bristles' mode
    (``P_DTLUGRE``) and their relaxation rate ``sigma0 |v| / g(v)``."""
    h = p[P_DTLUGRE]
    av = abs(v)
    if av > 0.0:
        g = stribeck_level(av, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_RFLAT])
        h_z = p[P_STEPK] * g / (p[P_SIGMA0] * av)
        if h_z < h:
            h = h_z
    return h


@njit(cache=True)
def _lagged(y0: float, u0: float, u1: float, h: float, tau: float) -> float:
    """A first-order lag ``tau dy/dt = u - y`` over ``h``, its input moving linearly from ``u0``
    to ``u1`` (exact for that input)."""
    if tau <= 0.0:
        return u1
    r = h / tau
    if r < 1.0e-6:
        return y0 + r * (0.5 * (u0 + u1) - y0)
    a = math.exp(-r)
    return a * y0 + (1.0 - a) * u0 + (u1 - u0) * (1.0 - (1.0 - a) / r)


@njit(cache=True)
def port_pressure(p: np.ndarray, s: np.ndarray, side: int, t: float, pc: float, tc: float,
                  p_sup: float) -> float:
    """What chamber ``side``'s transmitter reads without noise or lag [Pa abs].

    At the chamber (``sensors.p_at: chamber``, or no line conductance): ``pc``. At the valves'
    side of a line: the junction where the chamber's two valves meet the line, solved as the
    flows solve it at time ``t`` (``tc``: the chamber's gas temperature; ``p_sup``: the inlet's
    pressure); with both valves shut no air flows through the line and it reads ``pc``. The
    lines' solver state is left as it was.
    """
    if p[P_PAT] < 0.5 or p[P_LINEC + side] <= 0.0:
        return pc
    y_in = open_fraction(p, s, 2 * side, t)
    y_out = open_fraction(p, s, 2 * side + 1, t)
    if y_in <= 0.0 and y_out <= 0.0:
        return pc
    keep = s[S_PJ + side]
    line_flow(p, s, side, y_in, y_out, p_sup, pc, tc)
    pj = s[S_PJ + side]
    s[S_PJ + side] = keep
    return pj


@njit(cache=True)
def port_pressures(p: np.ndarray, s: np.ndarray, t: float, pa: float, pb: float, ta: float,
                   tb: float, p_sup: float) -> tuple[float, float]:
    """:func:`port_pressure` of both chambers (``ta``/``tb``: their gas temperatures, read only
    with heat transfer)."""
    heat = p[P_HEAT] > 0.5
    return (port_pressure(p, s, 0, t, pa, ta if heat else p[P_T0], p_sup),
            port_pressure(p, s, 1, t, pb, tb if heat else p[P_T0], p_sup))


@njit(cache=True)
def _lag_sensors(p: np.ndarray, s: np.ndarray, h: float, x0: float, pa0: float, pb0: float,
                 ps0: float, x1: float, pa1: float, pb1: float, ps1: float) -> None:
    """Move the lagged sensor states over a step of ``h`` along the true values."""
    s[S_XF] = _lagged(s[S_XF], x0, x1, h, p[P_XLAG])
    tau = p[P_PLAG]
    s[S_PAF] = _lagged(s[S_PAF], pa0, pa1, h, tau)
    s[S_PBF] = _lagged(s[S_PBF], pb0, pb1, h, tau)
    s[S_PSF] = _lagged(s[S_PSF], ps0, ps1, h, tau)


@njit(cache=True)
def _integrate(p: np.ndarray, s: np.ndarray, h_total: float, p_s: float, f_ext: float) -> None:
    """Integrate ``s`` over ``h_total`` seconds with the valves as they are (no events inside)."""
    dt = p[P_DT]
    nsteps = math.ceil(h_total / dt - 1.0e-9)
    if nsteps < 1:
        nsteps = 1
    h = h_total / nsteps
    lugre = p[P_SIGMA0] > 0.0
    # friction can limit the step only where the plant's stiffest point needs less than h
    h_min = p[P_DTMIN]
    stiff = h_min < h and not lugre
    u_free = p[P_UFREE]  # above this speed only the viscous mode limits the step, to h_visc
    h_visc = p[P_STEPK] * p[P_M] / p[P_BV] if p[P_BV] > 0.0 else np.inf
    max_steps = nsteps
    if stiff:
        max_steps = max(nsteps, math.ceil(h_total / h_min - 1.0e-9))
    if lugre:
        max_steps = max(nsteps, math.ceil(h_total / _lugre_step(p, 10.0) - 1.0e-9))
    x, v, pa, pb = s[S_X], s[S_V], s[S_PA], s[S_PB]
    ta, tb, z, psup = s[S_TA], s[S_TB], s[S_Z], s[S_PSUP]
    t0 = s[S_T]
    stuck = s[S_STUCK] > 0.5
    xmin, xmax = p[P_XMIN], p[P_XMAX]
    # the lagged sensors follow the true values from one committed state to the next
    lag = p[P_XLAG] > 0.0 or p[P_PLAG] > 0.0
    supply = p[P_SUPC] > 0.0
    # transmitters at the valves: the lags follow the junctions' pressures
    at_valves = lag and p[P_PAT] > 0.5
    xq, paq, pbq, psq, remq = x, pa, pb, psup if supply else p_s, h_total
    if at_valves:
        paq, pbq = port_pressures(p, s, t0, pa, pb, ta, tb, psq)
    remaining = h_total
    guard = 0
    while remaining > 1.0e-13 and guard < 4 * max_steps + 64:
        guard += 1
        if lag and remq - remaining > 0.0:
            ps_now = psup if supply else p_s
            ra, rb = pa, pb
            if at_valves:
                ra, rb = port_pressures(p, s, t0 + (h_total - remaining), pa, pb, ta, tb,
                                        ps_now)
            _lag_sensors(p, s, remq - remaining, xq, paq, pbq, psq, x, ra, rb, ps_now)
            xq, paq, pbq, psq, remq = x, ra, rb, ps_now, remaining
        t = t0 + (h_total - remaining)
        step = h if h < remaining else remaining
        if stuck:
            x1, v1, pa1, pb1, ta1, tb1, z1, ps1 = _step(p, s, x, v, pa, pb, True, 0.0, p_s,
                                                      f_ext, step, t, ta, tb, z, psup)
            lo, hi = _stick_limits(p, x)
            f0 = applied_force(p, pa, pb, f_ext)
            f1 = applied_force(p, pa1, pb1, f_ext)
            if lo <= f1 <= hi:
                pa, pb, ta, tb, psup = pa1, pb1, ta1, tb1, ps1
                remaining -= step
                continue
            # break-away inside the step: locate it, integrate to it, start sliding
            thr = hi if f1 > hi else lo
            if f0 > hi or f0 < lo or f1 == f0:
                frac = 0.0  # already beyond the limit at the start of the step
            else:
                frac = min(max((thr - f0) / (f1 - f0), 0.0), 1.0)
            sub = frac * step
            if sub > 1.0e-12:
                x1, v1, pa, pb, ta, tb, z1, psup = _step(p, s, x, v, pa, pb, True, 0.0, p_s,
                                                        f_ext, sub, t, ta, tb, z, psup)
            stuck = False
            v = 0.0
            remaining -= sub
            continue
        # sliding
        f_now = applied_force(p, pa, pb, f_ext)
        d = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else (1.0 if f_now > 0.0 else -1.0))
        if stiff:
            h_ok = _sliding_step(p, abs(v)) if abs(v) < u_free else h_visc
            if h_ok < step:  # split what is left evenly (no sliver of a step at the end)
                step = remaining / math.ceil(remaining / h_ok - 1.0e-9)
        elif lugre:
            h_ok = _lugre_step(p, v)
            if h_ok < step:
                step = remaining / math.ceil(remaining / h_ok - 1.0e-9)
        x1, v1, pa1, pb1, ta1, tb1, z1, ps1 = _step(p, s, x, v, pa, pb, False, d, p_s, f_ext,
                                                  step, t, ta, tb, z, psup)
        if stiff and (abs(v) < u_free or abs(v1) < u_free or v1 * d <= 0.0):
            # the step must suit the slowest speed it reached; else take it again, shorter
            for _ in range(8):
                u = min(abs(v), abs(v1)) if v1 * d > 0.0 else 0.0
                h_ok = _sliding_step(p, u)
                if step <= h_ok * (1.0 + 1.0e-12):
                    break
                step = remaining / math.ceil(remaining / h_ok - 1.0e-9)
                x1, v1, pa1, pb1, ta1, tb1, z1, ps1 = _step(p, s, x, v, pa, pb, False, d, p_s,
                                                          f_ext, step, t, ta, tb, z, psup)
        hit_stop = x1 > xmax or x1 < xmin
        # with LuGre friction a velocity through zero is no event: the bristles carry it
        reversed_ = (v1 * d) <= 0.0 and not lugre
        if not hit_stop and not reversed_:
            x, v, pa, pb, ta, tb, z, psup = x1, v1, pa1, pb1, ta1, tb1, z1, ps1
            remaining -= step
            continue
        # an event inside the step: the earlier of the stop contact and the velocity zero
        frac = 1.0
        edge = xmax
        if hit_stop:
            edge = xmax if x1 > xmax else xmin
            frac = _locate(p, s, x, v, pa, pb, d, p_s, f_ext, step, 0, edge, x1, t, ta, tb, z,
                           psup)
        if reversed_ and v1 != v:
            fv = _locate(p, s, x, v, pa, pb, d, p_s, f_ext, step, 1, 0.0, v1, t, ta, tb, z,
                         psup)
            if fv < frac:
                frac = fv
                hit_stop = False
        frac = min(max(frac, 0.0), 1.0)
        sub = frac * step
        if sub > 1.0e-12:
            x, v, pa, pb, ta, tb, z, psup = _step(p, s, x, v, pa, pb, False, d, p_s, f_ext, sub,
                                                 t, ta, tb, z, psup)
        remaining -= sub
        if hit_stop:
            x = edge  # located to 1e-12 m; land exactly on the stop
            z = 0.0  # the stop takes the load off the seal's bristles
        elif x > xmax:
            x = xmax
        elif x < xmin:
            x = xmin
        v = 0.0
        f_at = applied_force(p, pa, pb, f_ext)
        lo, hi = _stick_limits(p, x)
        if hit_stop or (lo <= f_at <= hi):
            stuck = True
        elif sub <= 1.0e-12:
            # zero velocity at the start of the step and still pushed on: slide the whole step
            d2 = 1.0 if f_at > 0.0 else -1.0
            x1, v1, pa1, pb1, ta1, tb1, z1, ps1 = _step(p, s, x, 0.0, pa, pb, False, d2, p_s,
                                                      f_ext, step, t, ta, tb, z, psup)
            x, v, pa, pb, ta, tb, z, psup = x1, v1, pa1, pb1, ta1, tb1, z1, ps1
            remaining -= step
    if lag and remq - remaining > 0.0:
        ps_now = psup if supply else p_s
        ra, rb = pa, pb
        if at_valves:
            ra, rb = port_pressures(p, s, t0 + h_total, pa, pb, ta, tb, ps_now)
        _lag_sensors(p, s, remq - remaining, xq, paq, pbq, psq, x, ra, rb, ps_now)
    s[S_X], s[S_V], s[S_PA], s[S_PB] = x, v, pa, pb
    s[S_TA], s[S_TB], s[S_Z], s[S_PSUP] = ta, tb, z, psup
    s[S_STUCK] = 1.0 if stuck else 0.0


@njit(cache=True, inline="always")
def _switch(p: np.ndarray, s: np.ndarray, t: float) -> None:
    """The valves' events at ``t`` (:func:`~pneutune.control.plant.valves.process_events`);
    with armature time constants, a valve that switches starts its lag from where it is."""
    if p[P_VLAG] < 0.5:
        process_events(p, s, t)
        return
    y = np.empty(4)
    o = np.empty(4)
    for i in range(4):
        y[i] = open_fraction(p, s, i, t)
        o[i] = s[S_OPEN + i]
    process_events(p, s, t)
    for i in range(4):
        if s[S_OPEN + i] != o[i]:
            s[S_Y0 + i] = y[i]
            s[S_TY + i] = t


@njit(cache=True)
def _write(p: np.ndarray, s: np.ndarray, duties: np.ndarray) -> None:
    for i in range(4):
        write_duty(p, s, i, duties[i])


@njit(cache=True)
def _release_writes(p: np.ndarray, s: np.ndarray, t: float) -> None:
    """Write the duties whose IO delay has passed by ``t`` (oldest first)."""
    n = int(s[S_IO_N])
    k = 0
    while k < n and s[S_IO + 5 * k] <= t + EPS_T:
        _write(p, s, s[S_IO + 5 * k + 1:S_IO + 5 * k + 5])
        k += 1
    if k > 0:
        for j in range(5 * (n - k)):
            s[S_IO + j] = s[S_IO + 5 * k + j]
        s[S_IO_N] = n - k


@njit(cache=True)
def set_duties(p: np.ndarray, s: np.ndarray, t: float, duties: np.ndarray) -> None:
    """Write the four commanded duties at time ``t`` (clipped to 0..1; NaN counts as 0).

    Without an IO delay they act at once (:func:`~pneutune.control.plant.valves.set_duties`).
    With one (``io.delay``), they wait in the state and act that much later, inside
    :func:`advance`; if more writes wait than the state holds, the oldest acts now.
    """
    if p[P_IODELAY] <= 0.0:
        _write(p, s, duties)
        _switch(p, s, t)
        return
    n = int(s[S_IO_N])
    if n == IO_MAX:
        _write(p, s, s[S_IO + 1:S_IO + 5])
        _switch(p, s, t)
        for j in range(5 * (n - 1)):
            s[S_IO + j] = s[S_IO + 5 + j]
        n -= 1
    base = S_IO + 5 * n
    s[base] = t + p[P_IODELAY]
    for i in range(4):
        s[base + 1 + i] = duties[i]
    s[S_IO_N] = n + 1


@njit(cache=True)
def advance(p: np.ndarray, s: np.ndarray, t_end: float, p_s: float,
            force_steps: np.ndarray) -> None:
    """Advance the plant state ``s`` from its clock ``s[S_T]`` to ``t_end``.

    Valve switching, PWM edges, force steps and delayed duty writes inside the interval are
    handled exactly: the integration stops at each of them.

    Parameters
    ----------
    p : ndarray
        Packed plant parameters (:func:`~pneutune.control.plant.params.pack_plant`).
    s : ndarray
        Plant state, updated in place.
    t_end : float
        Time to stop at [s].
    p_s : float
        Supply pressure over the interval [Pa abs] (upstream of the supply line, if any).
    force_steps : ndarray
        (K, 2) external force levels [[t, F], ...].
    """
    # the step's functions take p and s by the thousand: views without reference counting
    p = unowned(p)
    s = unowned(s)
    t = s[S_T]
    if p[P_SUPC] > 0.0 and s[S_PSUP] <= 0.0:
        s[S_PSUP] = p_s  # the manifold starts charged
    if p[P_PLAG] > 0.0 and s[S_PSF] <= 0.0:
        s[S_PSF] = s[S_PSUP] if p[P_SUPC] > 0.0 else p_s
    io = p[P_IODELAY] > 0.0
    while t < t_end - EPS_T:
        t_next = next_event(p, s, t, t_end)
        t_next = _next_force_step(force_steps, t, t_next)
        if io and s[S_IO_N] > 0.5 and s[S_IO] < t_next:
            t_next = max(s[S_IO], t)
        if t_next - t > EPS_T:
            f_ext = external_force(p, force_steps, t)
            _integrate(p, s, t_next - t, p_s, f_ext)
        t = t_next
        s[S_T] = t
        if io:
            _release_writes(p, s, t)
        _switch(p, s, t)
    s[S_T] = t_end


@njit(cache=True)
def diverged(s: np.ndarray) -> bool:
    """Whether the plant state ``s`` is no state: a non-finite position, speed or chamber
    pressure, or an absolute chamber pressure at or below zero."""
    return not (np.isfinite(s[S_X]) and np.isfinite(s[S_V]) and np.isfinite(s[S_PA])
                and np.isfinite(s[S_PB]) and s[S_PA] > 0.0 and s[S_PB] > 0.0)


@njit(cache=True)
def truth(p: np.ndarray, s: np.ndarray, p_s: float, force_steps: np.ndarray,
          out: np.ndarray) -> None:
    """Fill ``out`` with the true [v, a, F_friction, F_ext, mdot_a, mdot_b] at the current time.

    ``F_friction`` is F_f of Eq. (1): the Stribeck force while sliding (LuGre's, with
    pre-sliding), the applied force while stuck (Eq. 2's F_e), and at an end stop the part of
    the applied force that friction can hold (at most F_S); the stop takes the rest.
    """
    x, v, pa, pb = s[S_X], s[S_V], s[S_PA], s[S_PB]
    t = s[S_T]
    f_ext = external_force(p, force_steps, t)
    stuck = s[S_STUCK] > 0.5
    f_app = applied_force(p, pa, pb, f_ext)
    d = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else (1.0 if f_app > 0.0 else -1.0))
    psup = s[S_PSUP] if s[S_PSUP] > 0.0 else p_s
    pj_a, pj_b = s[S_PJ], s[S_PJ + 1]  # the lines' solver starts from these: keep them
    if p[P_GENERAL] < 0.5 and p[P_EXTSTATE] < 0.5:
        _, dv, _, _ = _deriv(p, s, x, v, pa, pb, stuck, d, p_s, f_ext)
    else:
        _, dv, _, _, _, _, _, _ = _deriv_rig(p, s, x, v, pa, pb, stuck, d, p_s, f_ext, t,
                                             s[S_TA], s[S_TB], s[S_Z], psup)
        s[S_PJ], s[S_PJ + 1] = pj_a, pj_b
    if stuck:
        ff = min(max(f_app, -p[P_FS]), p[P_FS])
    else:
        ff = f_app - p[P_M] * dv
    if p[P_GENERAL] > 0.5:
        heat = p[P_HEAT] > 0.5
        ma, mb, _, _, _ = rig_flows(p, s, pa, pb, psup if p[P_SUPC] > 0.0 else p_s,
                                 s[S_TA] if heat else p[P_T0], s[S_TB] if heat else p[P_T0], t)
        s[S_PJ], s[S_PJ + 1] = pj_a, pj_b  # looking leaves the state as it was
    else:
        ma, mb = chamber_flows(p, s, pa, pb, p_s)
    out[0], out[1], out[2], out[3], out[4], out[5] = v, dv, ff, f_ext, ma, mb


@njit(cache=True)
def measure(p: np.ndarray, s: np.ndarray, p_s: float, noise: np.ndarray,
            out: np.ndarray) -> None:
    """Fill ``out`` with the sensor readings [x, p_a, p_b, p_s].

    ``noise`` holds four standard-normal draws. Position: true x (lagged by ``x_lag``) plus
    ``x_noise`` times a draw, then rounded to the ``x_step`` quantum. Pressures: true value
    (of the chamber, or of the valves' junction with ``sensors.p_at: valves``,
    :func:`port_pressure`; lagged by ``p_lag``; the supply reading is the manifold's with a
    supply line) plus
    ``p_noise`` times a draw, then rounded to the ``p_step`` quantum.
    """
    x = s[S_X]
    pa = s[S_PA]
    pb = s[S_PB]
    ps = s[S_PSUP] if p[P_SUPC] > 0.0 and s[S_PSUP] > 0.0 else p_s
    if p[P_XLAG] > 0.0:
        x = s[S_XF]
    if p[P_PLAG] > 0.0:  # the lag states follow what the transmitters read
        pa = s[S_PAF]
        pb = s[S_PBF]
        if s[S_PSF] > 0.0:
            ps = s[S_PSF]
    elif p[P_PAT] > 0.5:
        pa, pb = port_pressures(p, s, s[S_T], pa, pb, s[S_TA], s[S_TB], ps)
    xm = x + p[P_XNOISE] * noise[0]
    q = p[P_XSTEP]
    if q > 0.0:
        xm = q * math.floor(xm / q + 0.5)
    out[0] = xm
    out[1] = pa + p[P_PNOISE] * noise[1]
    out[2] = pb + p[P_PNOISE] * noise[2]
    out[3] = ps + p[P_PNOISE] * noise[3]
    qp = p[P_PSTEP]
    if qp > 0.0:
        for j in range(1, 4):
            out[j] = qp * math.floor(out[j] / qp + 0.5)


@njit(cache=True)
def run_open_loop(p: np.ndarray, s: np.ndarray, duties: np.ndarray, p_s: np.ndarray,
                  force_steps: np.ndarray, noise: np.ndarray, Ts: float,
                  sensors: np.ndarray, truth_out: np.ndarray) -> None:
    """Run the plant for ``len(duties)`` samples under given duties (no controller).

    At sample k (t_k = k Ts) the sensors and the truth are recorded, then the duties
    ``duties[k]`` are written and the plant advances to t_{k+1}.

    Parameters
    ----------
    duties : ndarray, shape (N, 4)
        Commanded duties per sample.
    p_s : ndarray, shape (N,)
        Supply pressure per sample [Pa abs].
    noise : ndarray, shape (N, 4)
        Standard-normal draws for the sensors.
    sensors, truth_out : ndarray, shapes (N, 4) and (N, 6)
        Outputs.
    """
    n = duties.shape[0]
    for k in range(n):
        t = k * Ts
        measure(p, s, p_s[k], noise[k], sensors[k])
        truth(p, s, p_s[k], force_steps, truth_out[k])
        set_duties(p, s, t, duties[k])
        advance(p, s, (k + 1) * Ts, p_s[k], force_steps)


@njit(cache=True)
def initial_state(p: np.ndarray, x0: float, p_a0: float, p_b0: float,
                  t0: float = 0.0) -> np.ndarray:
    """A plant state at rest at ``x0`` with the given chamber pressures and all valves closed.

    The piston starts stuck (v = 0). Use :func:`balanced_pressures` for pressures in force
    balance. Compiled, so that the prediction kernels of identify start from it too.
    """
    s = np.zeros(N_STATE)
    s[S_X], s[S_V], s[S_PA], s[S_PB] = x0, 0.0, p_a0, p_b0
    s[S_STUCK] = 1.0
    s[S_T] = t0
    # the real-rig effects' states: gas at T0, valves closed since t0, sensors settled
    s[S_TA] = p[P_T0]
    s[S_TB] = p[P_T0]
    for i in range(4):
        s[S_TY + i] = t0
    s[S_XF], s[S_PAF], s[S_PBF] = x0, p_a0, p_b0
    return s


def balanced_pressures(p: np.ndarray, p_b: float, f_ext: float = 0.0) -> tuple[float, float]:
    """Chamber pressures with zero net force: ``p_a`` from Eq. (1) at rest for a chosen ``p_b``.

    Returns
    -------
    (p_a, p_b) : tuple of float
        [Pa abs].
    """
    A_a, A_b, p0 = p[P_AA], p[P_AB], p[P_P0]
    p_a = (p_b * A_b + p0 * (A_a - A_b) - f_ext) / A_a
    return p_a, p_b


def rest_pressures(p: np.ndarray, f_ext: float, p_b: float | None = None) -> tuple[float, float]:
    """Chamber pressures that hold the piston at rest against ``f_ext`` (Eq. 1 with v = a = 0).

    ``p_b`` defaults to ambient; if that would need ``p_a`` below ambient, ``p_a`` is set to
    ambient and ``p_b`` follows from the balance instead.
    """
    p0 = p[P_P0]
    pa, pb = balanced_pressures(p, p0 if p_b is None else p_b, f_ext)
    if pa < p0:
        pa = p0
        pb = (pa * p[P_AA] - p0 * (p[P_AA] - p[P_AB]) + f_ext) / p[P_AB]
    return pa, pb


__all__ = [
    "SENSOR_FIELDS",
    "TRUTH_FIELDS",
    "advance",
    "applied_force",
    "balanced_pressures",
    "external_force",
    "initial_state",
    "iso6358_flow",
    "measure",
    "run_open_loop",
    "set_duties",
    "truth",
]
