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
Integration
    Classical RK4 with steps of at most ``sim.dt``, split at every valve switching instant,
    controller sample and force step, so that the right-hand side is smooth inside every step.
    The step size comes from a convergence study (docs/integration.md). While sliding, a step
    is also at most ``1.4 M / k(u)``, k the largest |dF_f/dv| of Eq. (2) at the speeds u the
    step passes through (:func:`~pneutune.control.physics.friction.stribeck_stiffness`): the
    falling Stribeck branch of a steep friction law (large F_S - F_C, small v_s) needs steps
    of tens of microseconds, but only near v = 0; elsewhere, and while stuck, ``sim.dt``
    stands. A step that ends slower than the speed its length was chosen for is taken again,
    shorter. (A plant whose friction never limits the step is integrated on exactly the grid
    of ``sim.dt``.)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pneutune.control.logs.topics import topic_fields
from pneutune.control.physics.flow import iso6358_flow, signed_flow
from pneutune.control.physics.friction import stribeck_force, stribeck_stiffness
from pneutune.control.plant.params import (
    N_STATE,
    P_AA,
    P_AB,
    P_ALPHA,
    P_B,
    P_BV,
    P_C,
    P_DA,
    P_DB,
    P_DT,
    P_DTMIN,
    P_FC,
    P_FN,
    P_FS,
    P_LEAKC,
    P_M,
    P_N,
    P_P0,
    P_PNOISE,
    P_R,
    P_RPEAK,
    P_T0,
    P_UFREE,
    P_V0A,
    P_V0B,
    P_VS,
    P_XMAX,
    P_XMIN,
    P_XNOISE,
    P_XSTEP,
    S_OPEN,
    S_PA,
    S_PB,
    S_STUCK,
    S_T,
    S_V,
    S_X,
    STEP_STIFFNESS,
)
from pneutune.control.plant.valves import EPS_T, next_event, process_events, set_duties

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
def chamber_flows(p: np.ndarray, s: np.ndarray, pa: float, pb: float,
                  p_s: float) -> tuple[float, float]:
    """Net mass flows into chambers A and B [kg/s] with the valves as they are in ``s``."""
    T0 = p[P_T0]
    p0 = p[P_P0]
    ma = 0.0
    mb = 0.0
    if s[S_OPEN + 0] > 0.5:
        ma += signed_flow(p[P_C + 0], p[P_B + 0], p_s, pa, T0)
    if s[S_OPEN + 1] > 0.5:
        ma -= signed_flow(p[P_C + 1], p[P_B + 1], pa, p0, T0)
    if s[S_OPEN + 2] > 0.5:
        mb += signed_flow(p[P_C + 2], p[P_B + 2], p_s, pb, T0)
    if s[S_OPEN + 3] > 0.5:
        mb -= signed_flow(p[P_C + 3], p[P_B + 3], pb, p0, T0)
    if p[P_LEAKC] > 0.0:
        leak = signed_flow(p[P_LEAKC], 0.0, pa, pb, T0)
        ma -= leak
        mb += leak
    return ma, mb


@njit(cache=True)
def applied_force(p: np.ndarray, pa: float, pb: float, f_ext: float) -> float:
    """Pressure and external forces on the piston, friction excluded [N]."""
    return pa * p[P_AA] - pb * p[P_AB] - p[P_P0] * (p[P_AA] - p[P_AB]) + f_ext


@njit(cache=True)
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
        ff = stribeck_force(v, direction, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_BV])
        dv = (applied_force(p, pa, pb, f_ext) - ff) / p[P_M]
    dpa = (-p[P_N] * pa * p[P_AA] * dx + nRT * ma) / Va + p[P_DA]
    dpb = (p[P_N] * pb * p[P_AB] * dx + nRT * mb) / Vb + p[P_DB]
    return dx, dv, dpa, dpb


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
def _stick_limits(p: np.ndarray, x: float) -> tuple[float, float]:
    """Range of applied force for which a piston at rest at ``x`` stays at rest [N]."""
    lo = -p[P_FS]
    hi = p[P_FS]
    if x >= p[P_XMAX] - 1.0e-12:
        hi = np.inf
    if x <= p[P_XMIN] + 1.0e-12:
        lo = -np.inf
    return lo, hi


@njit(cache=True)
def _locate(p: np.ndarray, s: np.ndarray, x: float, v: float, pa: float, pb: float, d: float,
            p_s: float, f_ext: float, h: float, comp: int, target: float, end: float) -> float:
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
        xc, vc, _, _ = _rk4(p, s, x, v, pa, pb, False, d, p_s, f_ext, c * h)
        fc = (xc if comp == 0 else vc) - target
        if abs(fc) < tol or (b - a) * h < 1.0e-13:
            break
        if fc * fb > 0.0:
            b, fb = c, fc
            if side == -1:
                fa *= 0.5
            side = -1
        else:
            a, fa = c, fc
            if side == 1:
                fb *= 0.5
            side = 1
    return c


@njit(cache=True)
def _sliding_step(p: np.ndarray, u: float) -> float:
    """Longest RK4 step while sliding at speeds of at least ``u`` [s] (module docstring)."""
    k = stribeck_stiffness(u, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_BV], p[P_RPEAK])
    return STEP_STIFFNESS * p[P_M] / k


@njit(cache=True)
def _integrate(p: np.ndarray, s: np.ndarray, h_total: float, p_s: float, f_ext: float) -> None:
    """Integrate ``s`` over ``h_total`` seconds with the valves as they are (no events inside)."""
    dt = p[P_DT]
    nsteps = math.ceil(h_total / dt - 1.0e-9)
    if nsteps < 1:
        nsteps = 1
    h = h_total / nsteps
    # friction can limit the step only where the plant's stiffest point needs less than h
    h_min = p[P_DTMIN]
    stiff = h_min < h
    u_free = p[P_UFREE]  # above this speed only the viscous mode limits the step, to h_visc
    h_visc = STEP_STIFFNESS * p[P_M] / p[P_BV] if p[P_BV] > 0.0 else np.inf
    max_steps = nsteps
    if stiff:
        max_steps = max(nsteps, math.ceil(h_total / h_min - 1.0e-9))
    x, v, pa, pb = s[S_X], s[S_V], s[S_PA], s[S_PB]
    stuck = s[S_STUCK] > 0.5
    xmin, xmax = p[P_XMIN], p[P_XMAX]
    remaining = h_total
    guard = 0
    while remaining > 1.0e-13 and guard < 4 * max_steps + 64:
        guard += 1
        step = h if h < remaining else remaining
        if stuck:
            x1, v1, pa1, pb1 = _rk4(p, s, x, v, pa, pb, True, 0.0, p_s, f_ext, step)
            lo, hi = _stick_limits(p, x)
            f0 = applied_force(p, pa, pb, f_ext)
            f1 = applied_force(p, pa1, pb1, f_ext)
            if lo <= f1 <= hi:
                pa, pb = pa1, pb1
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
                x1, v1, pa, pb = _rk4(p, s, x, v, pa, pb, True, 0.0, p_s, f_ext, sub)
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
        x1, v1, pa1, pb1 = _rk4(p, s, x, v, pa, pb, False, d, p_s, f_ext, step)
        if stiff and (abs(v) < u_free or abs(v1) < u_free or v1 * d <= 0.0):
            # the step must suit the slowest speed it reached; else take it again, shorter
            for _ in range(8):
                u = min(abs(v), abs(v1)) if v1 * d > 0.0 else 0.0
                h_ok = _sliding_step(p, u)
                if step <= h_ok * (1.0 + 1.0e-12):
                    break
                step = remaining / math.ceil(remaining / h_ok - 1.0e-9)
                x1, v1, pa1, pb1 = _rk4(p, s, x, v, pa, pb, False, d, p_s, f_ext, step)
        hit_stop = x1 > xmax or x1 < xmin
        reversed_ = (v1 * d) <= 0.0
        if not hit_stop and not reversed_:
            x, v, pa, pb = x1, v1, pa1, pb1
            remaining -= step
            continue
        # an event inside the step: the earlier of the stop contact and the velocity zero
        frac = 1.0
        edge = xmax
        if hit_stop:
            edge = xmax if x1 > xmax else xmin
            frac = _locate(p, s, x, v, pa, pb, d, p_s, f_ext, step, 0, edge, x1)
        if reversed_ and v1 != v:
            fv = _locate(p, s, x, v, pa, pb, d, p_s, f_ext, step, 1, 0.0, v1)
            if fv < frac:
                frac = fv
                hit_stop = False
        frac = min(max(frac, 0.0), 1.0)
        sub = frac * step
        if sub > 1.0e-12:
            x, v, pa, pb = _rk4(p, s, x, v, pa, pb, False, d, p_s, f_ext, sub)
        remaining -= sub
        if hit_stop:
            x = edge  # located to 1e-12 m; land exactly on the stop
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
            x1, v1, pa1, pb1 = _rk4(p, s, x, 0.0, pa, pb, False, d2, p_s, f_ext, step)
            x, v, pa, pb = x1, v1, pa1, pb1
            remaining -= step
    s[S_X], s[S_V], s[S_PA], s[S_PB] = x, v, pa, pb
    s[S_STUCK] = 1.0 if stuck else 0.0


@njit(cache=True)
def advance(p: np.ndarray, s: np.ndarray, t_end: float, p_s: float,
            force_steps: np.ndarray) -> None:
    """Advance the plant state ``s`` from its clock ``s[S_T]`` to ``t_end``.

    Valve switching, PWM edges and force steps inside the interval are handled exactly: the
    integration stops at each of them.

    Parameters
    ----------
    p : ndarray
        Packed plant parameters (:func:`~pneutune.control.plant.params.pack_plant`).
    s : ndarray
        Plant state, updated in place.
    t_end : float
        Time to stop at [s].
    p_s : float
        Supply pressure over the interval [Pa abs].
    force_steps : ndarray
        (K, 2) external force levels [[t, F], ...].
    """
    t = s[S_T]
    while t < t_end - EPS_T:
        t_next = next_event(p, s, t, t_end)
        t_next = _next_force_step(force_steps, t, t_next)
        if t_next - t > EPS_T:
            f_ext = external_force(p, force_steps, t)
            _integrate(p, s, t_next - t, p_s, f_ext)
        t = t_next
        s[S_T] = t
        process_events(p, s, t)
    s[S_T] = t_end


@njit(cache=True)
def truth(p: np.ndarray, s: np.ndarray, p_s: float, force_steps: np.ndarray,
          out: np.ndarray) -> None:
    """Fill ``out`` with the true [v, a, F_friction, F_ext, mdot_a, mdot_b] at the current time.

    ``F_friction`` is F_f of Eq. (1): the Stribeck force while sliding, the applied force while
    stuck (Eq. 2's F_e), and at an end stop the part of the applied force that friction can
    hold (at most F_S); the stop takes the rest.
    """
    x, v, pa, pb = s[S_X], s[S_V], s[S_PA], s[S_PB]
    f_ext = external_force(p, force_steps, s[S_T])
    stuck = s[S_STUCK] > 0.5
    f_app = applied_force(p, pa, pb, f_ext)
    d = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else (1.0 if f_app > 0.0 else -1.0))
    _, dv, _, _ = _deriv(p, s, x, v, pa, pb, stuck, d, p_s, f_ext)
    if stuck:
        ff = min(max(f_app, -p[P_FS]), p[P_FS])
    else:
        ff = f_app - p[P_M] * dv
    ma, mb = chamber_flows(p, s, pa, pb, p_s)
    out[0], out[1], out[2], out[3], out[4], out[5] = v, dv, ff, f_ext, ma, mb


@njit(cache=True)
def measure(p: np.ndarray, s: np.ndarray, p_s: float, noise: np.ndarray,
            out: np.ndarray) -> None:
    """Fill ``out`` with the sensor readings [x, p_a, p_b, p_s].

    ``noise`` holds four standard-normal draws. Position: true x plus ``x_noise`` times a draw,
    then rounded to the ``x_step`` quantum. Pressures: true value plus ``p_noise`` times a draw.
    """
    xm = s[S_X] + p[P_XNOISE] * noise[0]
    q = p[P_XSTEP]
    if q > 0.0:
        xm = q * math.floor(xm / q + 0.5)
    out[0] = xm
    out[1] = s[S_PA] + p[P_PNOISE] * noise[1]
    out[2] = s[S_PB] + p[P_PNOISE] * noise[2]
    out[3] = p_s + p[P_PNOISE] * noise[3]


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
    "chamber_flows",
    "external_force",
    "initial_state",
    "iso6358_flow",
    "measure",
    "run_open_loop",
    "set_duties",
    "truth",
]
