"""Rate-limited discontinuous projection, Eqs. (9)-(11), and its discrete-time update (the C
of ``control/law/c/ptlaw.c``, called through :mod:`pneutune.control.law.clib`).

Continuous time (the paper)::

    dθ̂/dt = sat_θ̇M( Proj_θ̂( Γ τ ) )                                              (9)
    Proj_θ̂i(•i) = 0 if θ̂i = θi,max and •i > 0, or θ̂i = θi,min and •i < 0; else •i   (10)
    sat_θ̇M(•)i = •i if |•i| <= θ̇Mi, else θ̇Mi sgn(•i)                             (11)

Discrete time (the controller runs every Ts; the paper is silent)
    1. Eq. (10) is applied with ``>=`` / ``<=`` instead of ``=``: a component at or beyond its
       bound is not pushed further out. In exact arithmetic the estimate never lies beyond the
       bound, so this is Eq. (10); in floating point it is robust to a bound met by rounding.
    2. Explicit Euler ``θ̂ <- θ̂ + Ts θ̂̇`` followed by clipping to [θ_min, θ_max]. The Euler
       step can overshoot a bound by up to ``Ts θ̇M``; the clip stops it exactly at the bound,
       where (1) then holds the component until τ changes sign.
    3. The *effective* rate ``(θ̂_new - θ̂)/Ts`` has the sign of the rate of (9) and a magnitude
       no larger, so the three properties of Eq. (12) hold for the discrete update as well:
       θ̂ stays in Ω_θ, θ̃^T [Γ^-1 Proj(Γτ) - τ] <= 0, and |effective rate_i| <= θ̇Mi.
       tests/test_projection.py checks them with hypothesis.

All functions write into caller-provided arrays: no allocation (they run in the DARC step).
"""

from __future__ import annotations

import numpy as np

from pneutune.control.law import clib
from pneutune.control.numba_cache import njit


@njit(cache=True, error_model="numpy")
def proj_into(theta_hat: np.ndarray, v: np.ndarray, theta_min: np.ndarray,
              theta_max: np.ndarray, out: np.ndarray) -> None:
    """Discontinuous projection of Eq. (10), elementwise.

    Parameters
    ----------
    theta_hat : (n,) float64
        Current estimate (units of θ).
    v : (n,) float64
        Vector to project, usually Γτ (units of θ per second).
    theta_min, theta_max : (n,) float64
        Bounds of Ω_θ.
    out : (n,) float64
        Receives Proj_θ̂(v); may be ``v`` itself.
    """
    clib.pt_proj_into(theta_hat.ctypes, v.ctypes, theta_min.ctypes, theta_max.ctypes,
                      out.ctypes, theta_hat.shape[0])


@njit(cache=True, error_model="numpy")
def sat_into(v: np.ndarray, rate_max: np.ndarray, out: np.ndarray) -> None:
    """Rate saturation of Eq. (11), elementwise: clip ``v_i`` to [-θ̇Mi, θ̇Mi]."""
    clib.pt_sat_into(v.ctypes, rate_max.ctypes, out.ctypes, v.shape[0])


@njit(cache=True, error_model="numpy")
def adaptation_rate_into(theta_hat: np.ndarray, tau: np.ndarray, gamma: np.ndarray,
                         rate_max: np.ndarray, theta_min: np.ndarray, theta_max: np.ndarray,
                         out: np.ndarray) -> None:
    """The adaptation law of Eq. (9): ``out = sat(Proj(Γ τ))`` with Γ = diag(gamma).

    Parameters
    ----------
    theta_hat : (n,) float64
        Current estimate.
    tau : (n,) float64
        Estimation function τ of Eq. (26).
    gamma : (n,) float64
        Diagonal of the adaptation-rate matrix Γ (> 0).
    rate_max : (n,) float64
        Rate limit θ̇M (units of θ per second, > 0).
    theta_min, theta_max : (n,) float64
        Bounds of Ω_θ.
    out : (n,) float64
        Receives dθ̂/dt.
    """
    clib.pt_adaptation_rate_into(theta_hat.ctypes, tau.ctypes, gamma.ctypes, rate_max.ctypes,
                                 theta_min.ctypes, theta_max.ctypes, out.ctypes,
                                 theta_hat.shape[0])


@njit(cache=True, error_model="numpy")
def adapt_step_into(theta_hat: np.ndarray, tau: np.ndarray, gamma: np.ndarray,
                    rate_max: np.ndarray, theta_min: np.ndarray, theta_max: np.ndarray,
                    Ts: float, rate_out: np.ndarray) -> None:
    """One discrete-time adaptation step: θ̂ <- clip(θ̂ + Ts sat(Proj(Γτ)), θ_min, θ_max).

    Parameters
    ----------
    theta_hat : (n,) float64
        Estimate, updated in place; stays within [theta_min, theta_max].
    tau, gamma, rate_max, theta_min, theta_max : (n,) float64
        As in :func:`adaptation_rate_into`.
    Ts : float
        Step [s].
    rate_out : (n,) float64
        Receives the effective rate ``(θ̂_new - θ̂_old) / Ts`` (units of θ per second).
    """
    clib.pt_adapt_step_into(theta_hat.ctypes, tau.ctypes, gamma.ctypes, rate_max.ctypes,
                            theta_min.ctypes, theta_max.ctypes, Ts, rate_out.ctypes,
                            theta_hat.shape[0])


def adaptation_rate(theta_hat: np.ndarray, tau: np.ndarray, gamma: np.ndarray,
                    rate_max: np.ndarray, theta_min: np.ndarray,
                    theta_max: np.ndarray) -> np.ndarray:
    """Allocating convenience form of :func:`adaptation_rate_into` (Eq. 9)."""
    out = np.empty(len(theta_hat))
    adaptation_rate_into(*(np.ascontiguousarray(a, dtype=np.float64) for a in (
        theta_hat, tau, gamma, rate_max, theta_min, theta_max)), out)
    return out


def proj(theta_hat: np.ndarray, v: np.ndarray, theta_min: np.ndarray,
         theta_max: np.ndarray) -> np.ndarray:
    """Allocating convenience form of :func:`proj_into` (Eq. 10)."""
    out = np.empty(len(theta_hat))
    proj_into(*(np.ascontiguousarray(a, dtype=np.float64) for a in (
        theta_hat, v, theta_min, theta_max)), out)
    return out
