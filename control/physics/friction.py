"""Friction models of the paper, once: scalar forms compiled with numba (the plant and the
control law), vectorised numpy forms beside them (identification), tested to agree.

* :func:`stribeck_force` / :func:`stribeck` - Eq. (2), the friction while sliding
  (:func:`stribeck_level`: its Coulomb-plus-Stribeck part; :func:`stribeck_flat_ratio`: the
  speed ratio from which that part is F_C to the last bit).
* :func:`smooth_sign` / :func:`smooth_sign_array` - S_f of Eq. (4), ``(2/pi) arctan(1000 v)``.
* :func:`smooth_friction` - Eqs. (3)-(4), the controller's smooth approximation
  ``b_v v + A_f S_f(v)``.
* :func:`stribeck_stiffness` - the largest |dF_f/dv| of Eq. (2) at speeds of at least u: what
  limits the plant's integration step while sliding (:func:`stribeck_peak`: where it peaks).

At v = 0 the direction of sliding is not v's sign: the scalar form takes it as an argument
(the plant passes the sign of the applied force at a break-away); the vectorised form takes
``sign(v)`` unless a direction is given, so a sample exactly at rest gets no Coulomb term.

Sticking (Eq. 2's ``F_e`` branch) is not a force law but a state of the plant: while the piston
is stuck, friction equals the applied force as long as that force is at most ``F_S`` in
magnitude; see :mod:`pneutune.control.plant.dynamics`.
"""

from __future__ import annotations

import math

import numpy as np

from pneutune.control.numba_cache import njit

#: Slope of the arctan in S_f of Eq. (4) [s/m].
SF_SLOPE: float = 1000.0
#: exp(-q) is exactly 0.0 in double precision for q above 745.13; from here on
#: :func:`exp_neg` returns that 0.0 without calling ``exp``, whose underflow path (errno,
#: the error handler) costs several times a normal call. The Stribeck term underflows on
#: every step of fast sliding on a law with small v_s.
EXP_UNDERFLOW: float = 746.0
#: Above this ``alpha log(|v|/v_s)`` the Stribeck term ``exp(-(|v|/v_s)^alpha)`` underflows to
#: 0.0 (``exp(6.62)`` > :data:`EXP_UNDERFLOW`), so the power need not be computed.
LOG_EXP_UNDERFLOW: float = 6.62


@njit(cache=True, inline="always")
def exp_neg(q: float) -> float:
    """``exp(-q)``, bit for bit, without the slow underflow path of libm for large ``q``."""
    if q > EXP_UNDERFLOW:
        return 0.0
    return math.exp(-q)


def stribeck_flat_ratio(F_S: float, F_C: float, alpha: float) -> float:
    """The speed ratio ``|v|/v_s`` from which Eq. (2)'s level is ``F_C`` to the last bit [-].

    In double precision ``F_C + (F_S - F_C) exp(-(|v|/v_s)^alpha)`` rounds to ``F_C`` once the
    Stribeck term is below half a unit in the last place of ``F_C``. This returns a ratio from
    which the computed term is below a tenth of that unit (margins for the rounding of the
    power, ``exp`` and the product), so :func:`stribeck_level` may return ``F_C`` there without
    the logarithm and the two exponentials, and return the same bits. The plant computes it
    once per parameter set (``plant.params.set_step_limits``).

    Parameters
    ----------
    F_S, F_C : float
        Stiction and Coulomb levels [N].
    alpha : float
        Stribeck exponent [-].

    Returns
    -------
    float
        >= 0; ``inf`` when no speed gives ``F_C`` exactly (F_C <= 0, F_S < F_C, alpha <= 0 or
        a non-finite parameter).
    """
    dF = F_S - F_C
    if not (math.isfinite(F_S) and math.isfinite(F_C) and math.isfinite(alpha)) \
            or F_C <= 0.0 or dF < 0.0 or alpha <= 0.0:
        return math.inf
    if dF == 0.0:
        return 0.0
    g_max = 0.25 * math.ulp(F_C) / dF  # the term (F_S - F_C) g stays below a quarter ulp
    q_min = 1.0 - math.log(g_max)  # exp(-q) <= g_max / e: a margin for exp's rounding
    if q_min <= 0.0:
        return 0.0
    return math.exp(math.log(q_min) / alpha) * (1.0 + 1.0e-9)


@njit(cache=True)
def stribeck_level(av: float, F_S: float, F_C: float, v_s: float, alpha: float,
                   r_flat: float = math.inf) -> float:
    """The Coulomb-plus-Stribeck level ``F_C + (F_S - F_C) exp(-(|v|/v_s)^alpha)`` of Eq. (2) at
    speed ``av = |v|`` [N]: the sliding friction without its viscous term (also the LuGre
    model's g(v), which makes its steady sliding Eq. (2)). ``r_flat``
    (:func:`stribeck_flat_ratio`) lets it return ``F_C`` from that speed ratio on without
    computing the term, with the same result."""
    if av > 0.0:
        ratio = av / v_s
        if ratio >= r_flat:
            return F_C
        if alpha == 2.0:
            g = exp_neg(ratio * ratio)
        elif alpha == 1.0:
            g = exp_neg(ratio)
        else:
            la = alpha * math.log(ratio)
            g = 0.0 if la > LOG_EXP_UNDERFLOW else exp_neg(math.exp(la))
    else:
        g = 1.0
    return F_C + (F_S - F_C) * g


@njit(cache=True)
def stribeck_force(v: float, direction: float, F_S: float, F_C: float, v_s: float,
                   alpha: float, b_v: float, r_flat: float = math.inf) -> float:
    """Sliding friction of Eq. (2) [N].

    Parameters
    ----------
    v : float
        Piston velocity [m/s].
    direction : float
        Sign of the motion, +1 or -1. Equal to sgn(v) for v != 0; at v = 0 while breaking
        away it is the sign of the applied force, so that friction starts at F_S.
    F_S, F_C : float
        Stiction and Coulomb levels [N].
    v_s : float
        Stribeck velocity [m/s].
    alpha : float
        Stribeck exponent [-].
    b_v : float
        Viscous coefficient [N s/m].
    r_flat : float, optional
        :func:`stribeck_flat_ratio` of F_S, F_C and alpha (the same result, sooner).
    """
    return stribeck_level(abs(v), F_S, F_C, v_s, alpha, r_flat) * direction + b_v * v


#: Lowest speed, as a fraction of v_s, at which the Stribeck slope is evaluated: for alpha < 1 the
#: slope grows without bound as v -> 0.
STRIBECK_FLOOR: float = 1.0e-3


@njit(cache=True)
def stribeck_peak(alpha: float) -> float:
    """Where the Stribeck slope of Eq. (2) peaks, as r = |v|/v_s [-].

    The slope ``s(r) = alpha/v_s r^(alpha-1) exp(-r^alpha)`` of g = exp(-r^alpha) rises to its
    peak at ``r* = ((alpha-1)/alpha)^(1/alpha)`` for alpha > 1 and falls beyond it; for
    alpha <= 1 it falls from r = 0 (without bound as r -> 0 for alpha < 1). Returns
    ``max(r*, STRIBECK_FLOOR)``.
    """
    r_peak = math.exp(math.log((alpha - 1.0) / alpha) / alpha) if alpha > 1.0 else 0.0
    return max(r_peak, STRIBECK_FLOOR)


@njit(cache=True)
def stribeck_stiffness(u: float, F_S: float, F_C: float, v_s: float, alpha: float,
                       b_v: float, r_peak: float) -> float:
    """Largest |dF_f/dv| of Eq. (2) over all sliding speeds |v| >= ``u`` [N s/m].

    dF_f/dv = b_v - (F_S - F_C) s(|v|) with the Stribeck slope s of :func:`stribeck_peak`,
    whose maximum over r >= u/v_s is at ``max(u/v_s, r_peak)``. The result is
    ``max(b_v, (F_S - F_C) s - b_v)``: the viscous mode (eigenvalue -b_v/M) or the unstable
    mode on the falling branch.

    Parameters
    ----------
    u : float
        Lowest speed considered [m/s], >= 0.
    F_S, F_C, v_s, alpha, b_v : float
        Eq. (2)'s parameters [N, N, m/s, -, N s/m].
    r_peak : float
        ``stribeck_peak(alpha)`` (passed in: the plant computes it once).

    Returns
    -------
    float
        [N s/m], at least 1e-9.
    """
    r = max(u / v_s, r_peak)
    ra = r * r if alpha == 2.0 else math.exp(alpha * math.log(r))
    slope = (F_S - F_C) * alpha / v_s * (ra / r) * exp_neg(ra)
    return max(b_v, slope - b_v, 1.0e-9)


@njit(cache=True)
def smooth_sign(v: float) -> float:
    """S_f of Eq. (4): (2/pi) arctan(1000 v), dimensionless, v in m/s."""
    return (2.0 / math.pi) * math.atan(SF_SLOPE * v)


@njit(cache=True)
def smooth_sign_derivative(v: float) -> float:
    """dS_f/dv of Eq. (4) [s/m]."""
    z = SF_SLOPE * v
    return (2.0 / math.pi) * SF_SLOPE / (1.0 + z * z)


@njit(cache=True)
def smooth_friction(v: float, b_v: float, A_f: float) -> float:
    """The smooth friction model of Eq. (3), ``b_v v + A_f S_f(v)`` [N]."""
    return b_v * v + A_f * smooth_sign(v)


def smooth_sign_array(v: np.ndarray) -> np.ndarray:
    """S_f of Eq. (4), vectorised: (2/π) arctan(SF_SLOPE v) [-], v in m/s."""
    return (2.0 / np.pi) * np.arctan(SF_SLOPE * np.asarray(v, dtype=np.float64))


def stribeck(v: np.ndarray, F_S: float, F_C: float, v_s: float, alpha: float, b_v: float,
             direction: np.ndarray | None = None) -> np.ndarray:
    """Sliding friction of Eq. (2), vectorised [N] (:func:`stribeck_force` per element).

    Parameters
    ----------
    v : array
        Velocity [m/s].
    F_S, F_C, v_s, alpha, b_v : float
        Stiction and Coulomb levels [N], Stribeck velocity [m/s] and exponent [-], viscous
        coefficient [N s/m].
    direction : array, optional
        Direction of sliding (+1/-1); default ``sign(v)``, 0 at v = 0.
    """
    v = np.asarray(v, dtype=np.float64)
    d = np.sign(v) if direction is None else np.asarray(direction, dtype=np.float64)
    return d * (F_C + (F_S - F_C) * np.exp(-((np.abs(v) / v_s) ** alpha))) + b_v * v
