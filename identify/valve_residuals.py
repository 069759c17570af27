"""Window sums of the valve fit in compiled passes (numba), the floats of their numpy forms.

:class:`~pneutune.identify.valves.ValveIdentifier` evaluates a chamber's window residuals a few
hundred times per fit (every least-squares step and every column of its Jacobian), and the
window sums of its PWM-curve regressors (a column per duty knot) at every QP. Written with
numpy they take temporary arrays as large as the log (times the knots) and a running sum;
:func:`chamber_window_residuals` and :func:`knot_window_sums` compute the same floats (the same
operations in the same order) without them.
"""

from __future__ import annotations

import numpy as np

from pneutune.control.numba_cache import njit


@njit(cache=True)
def chamber_window_residuals(scale: float, V: np.ndarray, r_in: np.ndarray,
                             phi_in: np.ndarray, r_out: np.ndarray, phi_out: np.ndarray,
                             sgn: float, leak: np.ndarray, vol: np.ndarray, drift: float,
                             k0: np.ndarray, k1: np.ndarray, dp: np.ndarray,
                             weights: np.ndarray, out: np.ndarray) -> None:
    """Weighted window residuals of a chamber's pressure increments [kPa].

    Per sample j, the modelled pressure change is
    ``(scale / V[j]) * ((r_in[j] phi_in[j] + r_out[j] (-phi_out[j])) + sgn leak[j]) + vol[j]
    + drift``; over window w, from sample ``k0[w]`` to before ``k1[w]``, its sum (a running
    sum, as numpy's cumsum) less the measured increment ``dp[w]``, times ``weights[w]``, over
    1e3: ``out[w]``. The floats of the numpy expression
    ``(window_sum(scale / V * (r_in * phi_in + r_out * -phi_out + sgn * leak) + vol + drift)
    - dp) * weights / 1e3``.

    Parameters
    ----------
    scale : float
        ``Ts n R T0`` [Pa m^3/kg].
    V : ndarray, (N,)
        Chamber volume per sample [m^3].
    r_in, r_out : ndarray, (N,)
        Open fraction of the chamber's inlet and outlet valve per sample.
    phi_in, phi_out : ndarray, (N,)
        Their fully open flows [kg/s]: into the chamber through the inlet, out of it through
        the outlet.
    sgn : float
        Sign of the seal leak for this chamber (-1 for A, +1 for B).
    leak : ndarray, (N,)
        Seal leak flow from A to B [kg/s] (zeros for none).
    vol : ndarray, (N,)
        Pressure change from the volume change per sample [Pa].
    drift : float
        ``Ts D`` [Pa].
    k0, k1 : ndarray of int, (W,)
        First sample of each window and the sample after its last.
    dp : ndarray, (W,)
        Measured pressure increment over each window [Pa].
    weights : ndarray, (W,)
        Window weights.
    out : ndarray, (W,)
        The residuals [kPa].
    """
    n = V.shape[0]
    c = np.empty(n + 1)
    c[0] = 0.0
    for j in range(n):
        term = (scale / V[j]) * ((r_in[j] * phi_in[j] + r_out[j] * -phi_out[j])
                                 + sgn * leak[j]) + vol[j] + drift
        c[j + 1] = term if j == 0 else c[j] + term
    for w in range(k0.shape[0]):
        out[w] = (c[k1[w]] - c[k0[w]] - dp[w]) * weights[w] / 1e3


@njit(cache=True)
def knot_window_sums(gain: np.ndarray, weights: np.ndarray, k0: np.ndarray, k1: np.ndarray,
                     out: np.ndarray) -> None:
    """Window sums of ``gain[j] * weights[j, q]`` per column q.

    The floats of the numpy form ``c = cumsum(gain[:, None] * weights, axis=0)`` with a row of
    zeros prepended, ``out = c[k1] - c[k0]``; the running sums are kept for the current sample
    only, not for the whole log.

    Parameters
    ----------
    gain : ndarray, (N,)
        Per sample factor (pressure change per unit open fraction).
    weights : ndarray, (N, K)
        Per sample and knot, the interpolation weight of the knot's open fraction.
    k0, k1 : ndarray of int, (W,)
        First sample of each window and the sample after its last, both non-decreasing.
    out : ndarray, (W, K)
        The window sums.
    """
    n, m = weights.shape
    n_win = k0.shape[0]
    run = np.zeros(m)
    a = 0
    b = 0
    for j in range(n + 1):
        while a < n_win and k0[a] == j:  # a window starts: keep the sums before it
            for q in range(m):
                out[a, q] = run[q]
            a += 1
        while b < n_win and k1[b] == j:  # a window ends
            for q in range(m):
                out[b, q] = run[q] - out[b, q]
            b += 1
        if j < n:
            for q in range(m):
                term = gain[j] * weights[j, q]
                run[q] = term if j == 0 else run[q] + term


__all__ = ["chamber_window_residuals", "knot_window_sums"]
