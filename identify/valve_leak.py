"""The seal leak and the constant terms D_a, D_b, from stretches with a chamber's valves shut.

Wherever a chamber's two valves stay shut (for at least a window, and for a PWM period before
it), Eq. (5) holds no valve flow: the pressure less the volume term changes at
``D - g φ_leak C_leak`` (chamber A; ``+`` for B), with φ_leak the leak flow per unit
conductance (ISO 6358 with b = 0) and g = n R T0 / V. A straight line through each such stretch
gives its slope (far more precisely than window increments), and a weighted linear least
squares over all stretches of both chambers separates D_a, D_b and C_leak when the stretches see
different pressure differences across the seal (a chamber held at supply with the other vented,
and both at ambient, as the identification run has). The valve fit
(:class:`~pneutune.identify.valves.ValveIdentifier`) holds what this finds fixed in its least
squares.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .dataset import true_runs

#: Scale of the leak conductance's column in the least squares [m^3/(s Pa)] (the unit the
#: valve fit solves for the leak in).
LEAK_SCALE = 1e-10


def closed_stretches(u: np.ndarray, usable: np.ndarray, lookback: int, window: int, Ts: float,
                     nRT: float, chambers: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                     leak_flow: np.ndarray
                     ) -> tuple[list[float | None], list[float], float | None, float]:
    """D_a, D_b [Pa/s], the leak conductance and standard errors, from shut valves.

    Parameters
    ----------
    u : ndarray (N-1, 4)
        Duty per sample of a_in, a_out, b_in, b_out.
    usable : ndarray of bool (N-1,)
        Samples the fit may use.
    lookback : int
        Samples the valves must have been shut before a stretch counts (a PWM period and the
        valve delays).
    window : int
        Shortest stretch [samples].
    Ts : float
        Sampling period [s].
    nRT : float
        n R T0 [J/kg].
    chambers : sequence of (ndarray, ndarray, ndarray)
        Per chamber (A, B): the volume over each sample [m^3], the pressure change per sample
        from the volume change [Pa], and the measured pressure per sample (N,) [Pa].
    leak_flow : ndarray (N-1,)
        Leak flow from A to B per unit conductance over each sample [kg/(s m^3/(s Pa))].

    Returns
    -------
    (list, list, float or None, float)
        D_a, D_b (None where a chamber never has such a stretch) and their standard errors
        (nan there); the leak conductance [m^3/(s Pa)] and its standard error, or None and nan
        where the stretches do not separate it (or it comes out negative).
    """
    w = window
    rows, rhs, var = [], [], []
    for ch, ((V, vol, p), sgn) in enumerate(zip(chambers, (-1.0, 1.0), strict=True)):
        uc = u[:, 2 * ch:2 * ch + 2]
        shut = np.all(uc <= 0.0, axis=1) & usable
        ok = shut.copy()
        for k in range(1, lookback + 1):
            ok[k:] &= shut[:-k]
        ok[:lookback] = False
        cs = np.concatenate([[0.0], np.cumsum(vol)])
        y = p[: len(cs)] - cs
        leak_rate = sgn * nRT / V * leak_flow  # dp/dt per unit leak conductance
        for a, b in true_runs(ok):
            if b - a < w:
                continue
            tt = np.arange(a, b + 1) * Ts
            yy = y[a:b + 1]
            A = np.column_stack([tt - tt.mean(), np.ones_like(tt)])
            coef, *_ = np.linalg.lstsq(A, yy, rcond=None)
            s2 = float(np.sum((yy - A @ coef) ** 2)) / max(1, len(tt) - 2)
            # a stretch that fits exactly (a noise-free log, a pressure held within one
            # quantum) has no residual; its variance is then that of the data's rounding, not
            # zero, so that its weight stays finite
            s2 = max(s2, (np.finfo(float).eps * float(np.max(np.abs(yy)))) ** 2)
            row = [0.0, 0.0, float(np.mean(leak_rate[a:b])) * LEAK_SCALE]
            row[ch] = 1.0
            rows.append(row)
            rhs.append(coef[0])
            var.append(s2 / float(np.sum((tt - tt.mean()) ** 2)))
    D: list[float | None] = [None, None]
    D_std = [np.nan, np.nan]
    if not rows:
        return D, D_std, None, np.nan
    A = np.asarray(rows)
    y = np.asarray(rhs)
    wts = 1.0 / np.sqrt(np.asarray(var))
    have = [bool(np.any(A[:, ch] > 0)) for ch in range(2)]
    # the leak is separable only if the stretches see different seal flows
    leak_ok = np.ptp(A[:, 2]) > 0.0 and len(rows) >= sum(have) + 1
    cols = [ch for ch in range(2) if have[ch]] + ([2] if leak_ok else [])
    Aw = A[:, cols] * wts[:, None]
    sol, *_ = np.linalg.lstsq(Aw, y * wts, rcond=None)
    if leak_ok and sol[-1] < 0.0:  # a leak cannot be negative: refit without it
        cols = cols[:-1]
        leak_ok = False
        Aw = A[:, cols] * wts[:, None]
        sol, *_ = np.linalg.lstsq(Aw, y * wts, rcond=None)
    dof = max(1, len(y) - len(cols))
    chi2 = float(np.sum((Aw @ sol - y * wts) ** 2)) / dof
    # columns scaled to unit norm before the pseudo-inverse: the weights of an exact stretch
    # and a noisy one can differ by many decades, and pinv's cut-off (relative to the largest
    # singular value) would otherwise drop the noisy chamber's column and report its error as 0
    norm = np.linalg.norm(Aw, axis=0)
    norm[norm == 0.0] = 1.0
    As = Aw / norm
    cov = np.linalg.pinv(As.T @ As) / np.outer(norm, norm) * max(1.0, chi2)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    for j, c in enumerate(cols):
        if c < 2:
            D[c] = float(sol[j])
            D_std[c] = float(sd[j])
    if leak_ok:
        return D, D_std, float(sol[-1]) * LEAK_SCALE, float(sd[-1]) * LEAK_SCALE
    return D, D_std, None, np.nan
