"""The shut-valve drift fit (``identify/valve_leak.py``): stretches whose residuals differ by
many decades (a chamber held exactly, a noisy one) keep finite weights and honest errors."""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.identify.valve_leak import closed_stretches

N, TS = 401, 1e-3


def _fit(pa: np.ndarray, pb: np.ndarray) -> tuple[list, list]:
    u = np.zeros((N - 1, 4))  # every valve shut throughout: one stretch per chamber
    V, vol = np.full(N - 1, 1e-4), np.zeros(N - 1)
    D, D_sd, leak, _ = closed_stretches(u, np.ones(N - 1, bool), 2, 50, TS, 1.2 * 287.0 * 293.15,
                                        [(V, vol, pa), (V, vol, pb)], np.zeros(N - 1))
    assert leak is None  # one seal flow (none): the leak is not separable
    return D, D_sd


def test_an_exact_chamber_leaves_the_noisy_ones_error_intact() -> None:
    """Chamber A held at one pressure (no residual), chamber B drifting 50 Pa/s under 30 Pa of
    noise: B's drift and standard error are those of its own straight-line fit (the two
    chambers share no column), not 0 as a pseudo-inverse cut at the exact chamber's weight
    gave."""
    rng = np.random.default_rng(1)
    pa = np.full(N, 262144.0)
    pb = 2.0e5 + 50.0 * np.arange(N) * TS + rng.normal(0.0, 30.0, N)
    D, D_sd = _fit(pa, pb)
    # the same stretch by hand: samples lookback (2) to N - 1 against centred time
    t = np.arange(2, N) * TS
    y = pb[2:N]
    A = np.column_stack([t - t.mean(), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    s2 = float(np.sum((y - A @ coef) ** 2)) / (len(t) - 2)
    assert D[1] == pytest.approx(coef[0], rel=1e-9)
    assert D_sd[1] == pytest.approx(np.sqrt(s2 / np.sum((t - t.mean()) ** 2)), rel=1e-6)
    assert abs(D[0]) < 1e-6 and np.isfinite(D_sd[0])


def test_two_exact_chambers_fit_without_error() -> None:
    """A noise-free log: both chambers exactly linear. The fit returns their drifts, finite."""
    t = np.arange(N) * TS
    D, D_sd = _fit(262144.0 + 0.0 * t, 131072.0 + 64.0 * t)
    assert D[0] == pytest.approx(0.0, abs=1e-6)
    assert D[1] == pytest.approx(64.0, rel=1e-9)
    assert np.all(np.isfinite(D_sd))
