"""From the desired flow Q_Ld to the four valve duties: Eqs. (32)-(33) and the PWM inverse.

The kernels are the C of ``control/law/c/ptlaw.c`` (``pt_fully_open_q_l``, ``pt_eq33_into``,
``pt_pwm_inverse``, ``pt_duties_into``, ``pt_dither_into``), called through
:mod:`pneutune.control.law.clib`; :func:`dead_zone_knee` is the Python that packs the knees.

Eq. (32), as corrected (docs/controller.md)
    Q_L,F is the virtual input Q_L of Eq. (25) with the two valves of the active mode fully open,
    computed from the measured pressures (the paper typesets the B term inside the A fraction)::

        mode 1 (Q_Ld > 0): Q_L,F = nR T0 [A_a mdot(a_in: p_s -> p_a) / V_a
                                          + A_b mdot(b_out: p_b -> p0) / V_b]
        mode 2 (Q_Ld < 0): Q_L,F = nR T0 [A_a mdot(a_out: p_a -> p0) / V_a
                                          + A_b mdot(b_in: p_s -> p_b) / V_b]

    with mdot the ISO 6358 flow of Eq. (7) at upstream temperature T0 (T_a = T_b = T0, Eq. 5).
    Q_L,F >= 0 in both modes (it is the magnitude of the fully-open Q_L) [N/s].
Eq. (33), as corrected
    The paper's ``sat(Q_Ld / Q_L)`` is ``sat(Q_Ld / Q_L,F)`` (docs/controller.md): the fraction
    of the fully-open flow wanted, saturated to [0, 1]. The five cases (:data:`CASE_NAMES`)::

        1  Q_Ld > 0, Q_L,F = 0:  u(a_in, b_out) = 1,                 u(a_out, b_in) = 0
        2  Q_Ld > 0, Q_L,F > 0:  u(a_in, b_out) = sat(Q_Ld / Q_L,F),  u(a_out, b_in) = 0
        3  Q_Ld = 0:             all closed
        4  Q_Ld < 0, Q_L,F > 0:  u(a_out, b_in) = sat(-Q_Ld / Q_L,F), u(a_in, b_out) = 0
        5  Q_Ld < 0, Q_L,F = 0:  u(a_out, b_in) = 1                  (the paper's "-1": full
                                 opening in mode 2; duties are never negative)

    A non-finite Q_Ld falls into case 3 (all valves closed), the safe state.
PWM inverse
    ``u`` above is an *effective open fraction*. The valves' delays and minimum pulse make it
    differ from the commanded duty (docs/controller.md); the controller config holds the measured
    curve ``pwm: {duty, ratio}`` (effective fraction vs duty, non-decreasing, from (0, 0)).
    :func:`pwm_inverse` returns the *smallest* duty whose effective fraction reaches ``u`` on the
    piecewise-linear curve: 0 for u <= 0; inside the dead zone (the curve jumps from 0 to
    ratio_j at the minimum pulse) the duty of the jump, so a small demand gives the smallest
    pulse that opens the valve rather than a pulse that never opens it; at or above the curve's
    largest ratio duty 1, the valve always on. The curve reaches its top before duty 1 (0.94
    on the default plant, where a short off-gap is swallowed by delay_off > delay_on), but a
    curve shared by the four valves is not every valve's: a valve whose delay_off is shorter
    than its delay_on closes in every off-gap, so a smaller duty would leave the bottleneck
    valve short of flow exactly where Eq. (33) asks for all of it (fleet plant 4's a_out: 2.6 ms
    shut per 16.7 ms period at 0.94).
One curve per valve
    Contract 4's ``valves.<v>.pwm`` gives a valve a curve of its own (its delays and minimum
    pulse); the others use the top-level ``pwm``. :func:`duties_into` inverts each valve on its
    curve, and each has its own dead-zone knee.
Dead zone: ``up`` or ``dither`` (contract 4 ``dead_zone``)
    A wanted fraction ``0 < u < r_k`` below the curve's dead-zone knee ``(d_k, r_k)``
    (:func:`dead_zone_knee`) cannot be delivered in one PWM period: a pulse shorter than the
    valve's minimum opens it not at all or unreliably. ``up`` commands the inverse above (the
    smallest pulse that opens the valve, or a duty on the steep rise of an identified curve),
    every period: the valve passes ``r_k`` or more however small ``u`` is. ``dither``
    (:func:`dither_into`) commands either the knee's duty ``d_k`` or 0 for a whole PWM period,
    chosen by a first-order sigma-delta per valve, so that the open fraction averaged over
    periods is ``u``: at each period start the accumulator gains ``u`` and, if it reaches
    ``r_k / 2``, the period gets the pulse and the accumulator loses ``r_k``. A valve that was
    not wanted open starts with the accumulator at ``r_k / 2``, so its first wanted period gets a
    pulse at once (what ``up`` does) and the later ones the mean. The carrier is taken to start
    at the controller's t = 0 (the plant's convention, :mod:`pneutune.control.plant.valves`);
    with another phase a decision still holds for one whole carrier period, so each period still
    gets one decision (off by at most one period at the edges of a dithered stretch).
"""

from __future__ import annotations

import numpy as np

from pneutune.control.law import clib
from pneutune.control.numba_cache import njit

#: A segment of the PWM curve is part of the dead-zone rise when it is at least this many times
#: steeper than the chord from (0, 0) to the curve's top (:func:`dead_zone_knee`).
KNEE_STEEPNESS: float = 2.0

#: Eq. (33) cases, numbered as in the docstring.
CASE_A_FILL_NO_FLOW = 1
CASE_A_FILL = 2
CASE_CLOSED = 3
CASE_B_FILL = 4
CASE_B_FILL_NO_FLOW = 5
CASE_NAMES: dict[int, str] = {
    CASE_A_FILL_NO_FLOW: "Q_Ld>0, Q_LF=0: a_in+b_out fully open",
    CASE_A_FILL: "Q_Ld>0, Q_LF>0: a_in+b_out at sat(Q_Ld/Q_LF)",
    CASE_CLOSED: "Q_Ld=0: all closed",
    CASE_B_FILL: "Q_Ld<0, Q_LF>0: a_out+b_in at sat(-Q_Ld/Q_LF)",
    CASE_B_FILL_NO_FLOW: "Q_Ld<0, Q_LF=0: a_out+b_in fully open",
}


@njit(cache=True, error_model="numpy")
def fully_open_q_l(q_ld: float, p_a: float, p_b: float, p_s: float, p0: float, T0: float,
                   nR: float, A_a: float, A_b: float, V_a: float, V_b: float, C: np.ndarray,
                   b: np.ndarray) -> float:
    """Q_L,F of Eq. (32) (corrected) for the mode selected by the sign of ``q_ld``.

    Parameters
    ----------
    q_ld : float
        Desired Q_L [N/s]; only its sign is used (0 gives 0).
    p_a, p_b, p_s, p0 : float
        Measured chamber, supply and ambient pressures [Pa abs].
    T0 : float
        Gas temperature [K].
    nR : float
        Polytropic exponent times gas constant [J/(kg K)].
    A_a, A_b : float
        Piston areas [m^2].
    V_a, V_b : float
        Chamber volumes [m^3].
    C, b : (4,) float64
        Sonic conductance [m^3/(s Pa)] and critical ratio of a_in, a_out, b_in, b_out.

    Returns
    -------
    float
        Q_L,F >= 0 [N/s].
    """
    return clib.pt_fully_open_q_l(q_ld, p_a, p_b, p_s, p0, T0, nR, A_a, A_b, V_a, V_b, C.ctypes,
                                  b.ctypes)


@njit(cache=True, error_model="numpy")
def eq33_into(q_ld: float, q_lf: float, u_out: np.ndarray) -> int:
    """The five cases of Eq. (33) (corrected): effective open fractions of the four valves.

    Parameters
    ----------
    q_ld : float
        Desired Q_L [N/s].
    q_lf : float
        Fully-open Q_L,F of the mode of ``q_ld`` [N/s], >= 0.
    u_out : (4,) float64
        Receives the effective open fractions (0..1) of a_in, a_out, b_in, b_out.

    Returns
    -------
    int
        The case, 1..5 (:data:`CASE_NAMES`).
    """
    return clib.pt_eq33_into(q_ld, q_lf, u_out.ctypes)


@njit(cache=True, error_model="numpy")
def pwm_inverse(ratio: float, duty_pts: np.ndarray, ratio_pts: np.ndarray) -> float:
    """Smallest commanded duty whose effective open fraction reaches ``ratio``.

    Parameters
    ----------
    ratio : float
        Wanted effective open fraction (0..1).
    duty_pts, ratio_pts : (m,) float64
        The PWM curve: effective fraction ``ratio_pts`` at duty ``duty_pts``, both
        non-decreasing, starting at (0, 0) (validated by the config loader).

    Returns
    -------
    float
        Duty in [0, 1]: 0 for ``ratio <= 0``; linear interpolation on the first segment that
        reaches ``ratio``; 1 for a ratio at or above the curve's top (module docstring).
    """
    return clib.pt_pwm_inverse(ratio, duty_pts.ctypes, ratio_pts.ctypes, duty_pts.shape[0])


@njit(cache=True, error_model="numpy")
def duties_into(q_ld: float, q_lf: float, n_pts: np.ndarray, duty_pts: np.ndarray,
                ratio_pts: np.ndarray, stride: int, u_work: np.ndarray,
                duties_out: np.ndarray) -> int:
    """Eq. (33) then each valve's PWM inverse: the four commanded duties.

    Parameters
    ----------
    q_ld, q_lf : float
        Desired and fully-open Q_L [N/s].
    n_pts : (4,) float64
        Number of points of each valve's curve.
    duty_pts, ratio_pts : (4 * stride,) float64
        The valves' PWM curves (see :func:`pwm_inverse`), valve ``i``'s from ``i * stride``.
    stride : int
        Distance between two valves' curves in ``duty_pts`` and ``ratio_pts``.
    u_work : (4,) float64
        Receives the effective open fractions of Eq. (33).
    duties_out : (4,) float64
        Receives the commanded duties of a_in, a_out, b_in, b_out (0..1).

    Returns
    -------
    int
        The Eq. (33) case, 1..5.
    """
    return clib.pt_duties_into(q_ld, q_lf, n_pts.ctypes, duty_pts.ctypes, ratio_pts.ctypes,
                               stride, u_work.ctypes, duties_out.ctypes)


def dead_zone_knee(duty_pts: np.ndarray, ratio_pts: np.ndarray) -> tuple[float, float]:
    """The top ``(d_k, r_k)`` of the PWM curve's dead-zone rise, or ``(0, 0)`` if it has none.

    The rise is the steepest segment ending at or below half the curve's top ratio (a vertical
    step, as in a curve computed from the valves, or the steep segment of a curve identified on
    a duty grid), extended over the steep segments that follow it; "steep" is
    :data:`KNEE_STEEPNESS` times the chord slope. Below ``r_k`` the valve cannot pass a steady
    fraction in every period (module docstring).

    Parameters
    ----------
    duty_pts, ratio_pts : (m,) array_like
        The PWM curve (non-decreasing, from (0, 0)).

    Returns
    -------
    d_k : float
        Duty at the knee (0..1).
    r_k : float
        Effective open fraction at the knee (0..1); 0 when the curve has no steep rise.
    """
    d = np.asarray(duty_pts, dtype=np.float64)
    r = np.asarray(ratio_pts, dtype=np.float64)
    top = float(r[-1])
    top_duty = float(d[np.argmax(r >= top)])
    if not top > 0.0 or not top_duty > 0.0:
        return 0.0, 0.0
    chord = top / top_duty
    dd = np.diff(d)
    dr = np.diff(r)
    slope = np.where(dr > 0.0, np.inf, 0.0)  # a vertical step is infinitely steep
    np.divide(dr, dd, out=slope, where=dd > 0.0)
    low = r[1:] <= 0.5 * top
    if not low.any():
        return 0.0, 0.0
    steep = slope >= KNEE_STEEPNESS * chord
    cand = np.where(low & steep, slope, -1.0)
    j = int(np.argmax(cand))
    if cand[j] < 0.0:
        return 0.0, 0.0
    while j + 1 < len(steep) and steep[j + 1] and low[j + 1]:
        j += 1
    return float(d[j + 1]), float(r[j + 1])


@njit(cache=True, error_model="numpy")
def dither_into(u: np.ndarray, duties: np.ndarray, t: float, Ts: float, period: float,
                d_k: np.ndarray, r_k: np.ndarray, acc: np.ndarray, pulse: np.ndarray,
                last: np.ndarray) -> None:
    """Dead-zone dithering (module docstring): overwrite the duties of valves with 0 < u < r_k.

    Parameters
    ----------
    u : (4,) float64
        Wanted effective open fractions of Eq. (33).
    duties : (4,) float64
        The duties from :func:`duties_into`; those of valves in the dead zone are replaced by
        ``d_k`` or 0.
    t : float
        Time of this sample [s]; its duties hold over ``[t, t + Ts)``.
    Ts : float
        Control period [s].
    period : float
        PWM carrier period [s].
    d_k, r_k : (4,) float64
        Each valve's dead-zone knee (:func:`dead_zone_knee`); ``r_k <= 0`` leaves that valve's
        duty unchanged.
    acc : (4,) float64
        Sigma-delta accumulators [open fraction x periods], updated in place.
    pulse : (4,) float64
        1 if the valve has its pulse in the current carrier period, else 0; updated.
    last : (1,) float64
        Index of the last carrier period decided; updated. Before the first, -1 and every
        accumulator at ``r_k / 2`` (:func:`pneutune.control.law.darc.init_state`).
    """
    clib.pt_dither_into(u.ctypes, duties.ctypes, t, Ts, period, d_k.ctypes, r_k.ctypes,
                        acc.ctypes, pulse.ctypes, last.ctypes)
