"""ISO 6358 valve flow, the paper's Eq. (7), compiled with numba.

    mdot = C rho0 p_u sqrt(T_ref / T_u)                                p_d / p_u <= b  (choked)
    mdot = C rho0 p_u sqrt(T_ref / T_u) sqrt(1 - ((p_d/p_u - b)/(1 - b))^2)   b < p_d / p_u <= 1

C is the sonic conductance [m^3/(s Pa)], b the critical pressure ratio, rho0 = 1.185 kg/m^3 the
density at the ISO 6358 reference temperature T_ref = 293.15 K, T_u the upstream temperature.

The infinite slope at p_d -> p_u
--------------------------------
d(mdot)/d(p_d) of Eq. (7) tends to -infinity as p_d -> p_u, so a chamber filling towards the
supply pressure obeys an ODE that is not Lipschitz there and an explicit integrator overshoots
and chatters between forward and reverse flow. Over the last ``LIN_WIDTH`` of pressure ratio
(1 - LIN_WIDTH < p_d/p_u <= 1) the flow is therefore taken as the straight line from the Eq. (7)
value at ``1 - LIN_WIDTH`` down to zero at ``p_d = p_u``: continuous, monotone and with a finite
slope. With LIN_WIDTH = 1e-3 the flows replaced are below 5 % of the choked flow and act only
within 0.1 % of the supply pressure (0.6 kPa at 6 bar); the effect on the trajectories is far
below the sensor noise (see tests/test_physics.py::test_flow_regularisation_is_small).

Reverse flow: :func:`signed_flow` returns the flow from port 1 to port 2, negative when the
pressure difference reverses, using the same equation with the roles of the ports swapped.
"""

from __future__ import annotations

import functools
import math
from typing import Any

from numba import vectorize

from pneutune.control.constants import RHO0, T_REF
from pneutune.control.numba_cache import njit

#: Width, in pressure ratio, of the linear segment that replaces Eq. (7) as p_d -> p_u.
LIN_WIDTH: float = 1.0e-3


@njit(cache=True)
def iso6358_flow(C: float, b: float, p_u: float, p_d: float, T_u: float) -> float:
    """Mass flow through a valve from the upstream port to the downstream port, Eq. (7).

    Parameters
    ----------
    C : float
        Sonic conductance [m^3/(s Pa)].
    b : float
        Critical pressure ratio [-], 0 <= b < 1 - LIN_WIDTH.
    p_u, p_d : float
        Upstream and downstream absolute pressures [Pa]; ``p_u >= p_d`` is expected, and a
        non-positive result is returned as 0 when it does not hold.
    T_u : float
        Upstream gas temperature [K].

    Returns
    -------
    float
        Mass flow [kg/s], >= 0.
    """
    return iso6358_flow_k(C, b, p_u, p_d, math.sqrt(T_REF / T_u))


@njit(cache=True)
def iso6358_flow_k(C: float, b: float, p_u: float, p_d: float, k_T: float) -> float:
    """:func:`iso6358_flow` with its temperature factor ``k_T = sqrt(T_ref / T_u)`` given (a
    caller with many flows at one temperature computes it once; the result is the same to the
    last bit)."""
    if p_u <= 0.0 or p_d >= p_u:
        return 0.0
    choked = C * RHO0 * p_u * k_T
    r = p_d / p_u
    if r <= b:
        return choked
    one_b = 1.0 - b
    if r <= 1.0 - LIN_WIDTH:
        s = (r - b) / one_b
        return choked * math.sqrt(1.0 - s * s)
    s_lin = (1.0 - LIN_WIDTH - b) / one_b
    return choked * math.sqrt(1.0 - s_lin * s_lin) * (1.0 - r) / LIN_WIDTH


@njit(cache=True)
def signed_flow(C: float, b: float, p_1: float, p_2: float, T: float) -> float:
    """Mass flow from port 1 to port 2 [kg/s]; negative when the flow reverses.

    Both ports are at gas temperature ``T`` [K] (the paper's isothermal-supply assumption,
    T_i = T0), so the upstream temperature is ``T`` whichever way the air flows.
    """
    return signed_flow_k(C, b, p_1, p_2, math.sqrt(T_REF / T))


@njit(cache=True)
def signed_flow_k(C: float, b: float, p_1: float, p_2: float, k_T: float) -> float:
    """:func:`signed_flow` with the temperature factor ``k_T = sqrt(T_ref / T)`` given."""
    if p_1 >= p_2:
        return iso6358_flow_k(C, b, p_1, p_2, k_T)
    return -iso6358_flow_k(C, b, p_2, p_1, k_T)


@njit(cache=True)
def signed_flow_t(C: float, b: float, p_1: float, p_2: float, T_1: float, T_2: float) -> float:
    """Mass flow from port 1 to port 2 [kg/s], negative when it reverses, with each port's own
    gas temperature ``T_1``, ``T_2`` [K]: the upstream one sets the flow (for chambers whose
    temperature is a state)."""
    if p_1 >= p_2:
        return iso6358_flow(C, b, p_1, p_2, T_1)
    return -iso6358_flow(C, b, p_2, p_1, T_2)


def _signed_flow_scalar(C: float, b: float, p_1: float, p_2: float, T: float) -> float:
    return signed_flow(C, b, p_1, p_2, T)


@functools.cache
def _signed_flow_ufunc() -> Any:
    """The ufunc of :func:`signed_flow_array`, made on first use: building it loads or compiles
    it at once (about 0.3 s), which ``tune`` and ``simulate``, which never call it, need not
    pay when they import this module."""
    return vectorize(["float64(float64, float64, float64, float64, float64)"],
                     cache=True)(_signed_flow_scalar)


def signed_flow_array(C: Any, b: Any, p_1: Any, p_2: Any, T: Any) -> Any:
    """:func:`signed_flow` as a numpy ufunc (broadcasts over arrays), for the identifiers.

    Parameters
    ----------
    C, b, p_1, p_2, T : float or array
        As :func:`signed_flow`'s, broadcast against each other.

    Returns
    -------
    float or ndarray
        Mass flow from port 1 to port 2 [kg/s].
    """
    return _signed_flow_ufunc()(C, b, p_1, p_2, T)
