"""The PWM curves of the valve fit: duty knots, the QP per chamber, the switching they stand for.

A valve's PWM curve r(u) is its effective open fraction at commanded duty u, piecewise linear
between duty knots (:func:`default_knots`, :func:`interp_weights`). With C and b fixed, the
chamber equations of :class:`~pneutune.identify.valves.ValveIdentifier` are linear in the curve
values at the knots, so a chamber's two curves come from one QP (:func:`chamber_curves`):
monotone, 0 <= r <= 1, r(0) = 0, r(1) = 1 (which fixes the scale between C and r), with a small
curvature penalty where the data say little. :func:`curve_switching` reads the delays and the
minimum pulse a curve stands for.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from .dataset import IdentificationError


def default_knots() -> np.ndarray:
    """Duty knots of the curves: 0.0125 apart below 0.2 (dead zone), 0.025 above.

    Returns
    -------
    ndarray
        The knots, from 0 to 1.
    """
    return np.unique(np.round(np.concatenate([np.arange(0.0, 0.2, 0.0125),
                                              np.arange(0.2, 1.0 + 1e-9, 0.025)]), 10))


def interp_weights(u: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Matrix W (len(u), len(knots)) with W @ r = piecewise-linear r at u.

    Parameters
    ----------
    u : ndarray
        Duties (clipped to the knots' span).
    knots : ndarray
        Duty knots, increasing.

    Returns
    -------
    ndarray
        The interpolation weights, two nonzero per row.
    """
    u = np.clip(u, knots[0], knots[-1])
    j = np.clip(np.searchsorted(knots, u, side="right") - 1, 0, len(knots) - 2)
    frac = (u - knots[j]) / (knots[j + 1] - knots[j])
    W = np.zeros((len(u), len(knots)))
    rows = np.arange(len(u))
    W[rows, j] = 1.0 - frac
    W[rows, j + 1] = frac
    return W


def chamber_curves(A_in: np.ndarray, A_out: np.ndarray, y: np.ndarray, weights: np.ndarray,
                   smooth: float, path: str, chamber: str) -> tuple[np.ndarray, np.ndarray]:
    """The PWM curves of a chamber's two valves at the knots, from one QP (cvxpy).

    Minimises the weighted squared window residual ``A_in r_in + A_out r_out - y`` plus
    ``smooth`` times the data's scale times the curves' squared second differences, with each
    curve monotone, in [0, 1], 0 at the first knot and 1 at the last.

    Parameters
    ----------
    A_in, A_out : ndarray (W, K)
        Per window, the change of the chamber pressure per unit open fraction of the inlet and
        the outlet valve at each knot [Pa].
    y : ndarray (W,)
        Per window, the pressure change the valves have to account for [Pa].
    weights : ndarray (W,)
        Window weights.
    smooth : float
        Weight of the curvature penalty, relative to the data.
    path : str
        The log, for the error.
    chamber : str
        ``"A"`` or ``"B"``, for the error.

    Returns
    -------
    (ndarray (K,), ndarray (K,))
        The inlet's and the outlet's curve, clipped to [0, 1] and made nondecreasing.

    Raises
    ------
    IdentificationError
        The solver found no solution.
    """
    K = A_in.shape[1]
    wt = weights[:, None] / 1e3
    A = np.hstack([A_in, A_out]) * wt
    y = y * wt[:, 0]
    r = cp.Variable(2 * K)
    D2 = np.diff(np.eye(K), 2, axis=0)
    lam = smooth * float(np.sum(A * A)) / K
    ri, rj = r[:K], r[K:]
    cons = [ri[0] == 0, rj[0] == 0, ri[-1] == 1, rj[-1] == 1, r >= 0, r <= 1,
            cp.diff(ri) >= 0, cp.diff(rj) >= 0]
    obj = cp.Minimize(cp.sum_squares(A @ r - y)
                      + lam * (cp.sum_squares(D2 @ ri) + cp.sum_squares(D2 @ rj)))
    prob = cp.Problem(obj, cons)
    prob.solve(solver=cp.CLARABEL if "CLARABEL" in cp.installed_solvers() else None)
    if r.value is None:  # pragma: no cover - solver failure
        raise IdentificationError(path, f"the PWM-curve QP of chamber {chamber} failed "
                                  f"({prob.status})")
    vals = np.clip(np.asarray(r.value).ravel(), 0.0, 1.0)
    return np.maximum.accumulate(vals[:K]), np.maximum.accumulate(vals[K:])


def curve_switching(knots: np.ndarray, curve: np.ndarray, period: float) -> dict[str, float]:
    """Switching behaviour equivalent to a PWM curve (delays and minimum pulse [s]).

    Only the minimum pulse (end of the dead zone) and the difference of the delays (the offset
    of the curve above the diagonal) show in a curve; the opening delay is taken equal to the
    minimum pulse (its smallest physical value).

    Parameters
    ----------
    knots, curve : ndarray
        Duties and effective open fractions.
    period : float
        PWM period [s].

    Returns
    -------
    dict
        ``min_pulse``, ``delay_on``, ``delay_off`` [s], ``offset`` and ``dead_zone`` [-].
    """
    k, r = knots, curve
    dead = k[r <= 0.02]
    d0 = float(dead.max()) if dead.size else 0.0
    lin = (k > d0 + 0.05) & (r < 0.98) & (k < 0.95)
    offset = float(np.median(r[lin] - k[lin])) if np.any(lin) else 0.0
    min_pulse = d0 * period
    delay_on = min_pulse
    delay_off = max(0.0, delay_on + offset * period)
    return {"min_pulse": min_pulse, "delay_on": delay_on, "delay_off": delay_off,
            "offset": offset, "dead_zone": d0}
