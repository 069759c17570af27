"""Friction models of the paper, compiled with numba.

* :func:`stribeck_force` - Eq. (2), the plant's friction while sliding.
* :func:`smooth_friction` - Eqs. (3)-(4), the controller's smooth approximation
  ``b_v v + A_f S_f(v)`` with ``S_f(v) = (2/pi) arctan(1000 v)``.

Sticking (Eq. 2's ``F_e`` branch) is not a force law but a state of the plant: while the piston
is stuck, friction equals the applied force as long as that force is at most ``F_S`` in
magnitude; see :mod:`pneutune.control.plant`.
"""

from __future__ import annotations

import math

from numba import njit

#: Slope of the arctan in S_f of Eq. (4) [s/m].
SF_SLOPE: float = 1000.0


@njit(cache=True)
def stribeck_force(v: float, direction: float, F_S: float, F_C: float, v_s: float,
                   alpha: float, b_v: float) -> float:
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
    """
    av = abs(v)
    if av > 0.0:
        ratio = av / v_s
        if alpha == 2.0:
            g = math.exp(-ratio * ratio)
        elif alpha == 1.0:
            g = math.exp(-ratio)
        else:
            g = math.exp(-math.exp(alpha * math.log(ratio)))
    else:
        g = 1.0
    return (F_C + (F_S - F_C) * g) * direction + b_v * v


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
