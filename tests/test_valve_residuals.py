"""The valve fit's compiled window residuals (identify/valve_residuals.py) are the floats of the
numpy expression they replace."""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.identify.valve_residuals import chamber_window_residuals, knot_window_sums


@pytest.mark.parametrize("with_leak", [True, False])
def test_compiled_residuals_are_the_numpy_expression(with_leak):
    """Random chamber terms and overlapping windows: the same floats as the numpy form (the
    leak as zeros where there is none, which the numpy form adds as a signed 0.0)."""
    rng = np.random.default_rng(4)
    n = 3000
    V = rng.uniform(2e-5, 4e-4, n)
    ratios = rng.uniform(0.0, 1.0, (n, 4))
    phi_in, phi_out = rng.normal(0.0, 3e-3, n), rng.normal(0.0, 3e-3, n)
    leak = rng.normal(0.0, 1e-5, n) if with_leak else None
    vol = rng.normal(0.0, 50.0, n)
    k0 = np.arange(0, n - 30, 2)
    k1 = k0 + 30
    dp = rng.normal(0.0, 1e4, k0.size)
    weights = rng.choice([0.1, 0.3, 1.0], k0.size)
    scale, sgn, drift = 0.004 * 1.2 * 287.0 * 293.15, -1.0, 0.004 * 123.4

    L = leak if with_leak else 0.0
    g = scale / V * (ratios[:, 0] * phi_in + ratios[:, 1] * -phi_out + sgn * L)
    c = np.concatenate([[0.0], np.cumsum(g + vol + drift)])
    expected = (c[k1] - c[k0] - dp) * weights / 1e3

    out = np.empty(k0.size)
    chamber_window_residuals(scale, V, ratios[:, 0], phi_in, ratios[:, 1], phi_out, sgn,
                             leak if with_leak else np.zeros(n), vol, drift, k0, k1, dp,
                             weights, out)
    assert np.array_equal(out, expected)


def test_knot_window_sums_are_the_numpy_expression():
    """Per-knot window sums of sparse interpolation weights (zeros of both signs in the terms):
    the same floats as the cumulative sum along the samples."""
    from pneutune.identify.valve_curves import default_knots, interp_weights

    rng = np.random.default_rng(6)
    n = 2000
    knots = default_knots()
    weights = interp_weights(rng.uniform(0.0, 1.0, n), knots)
    gain = rng.normal(0.0, 1e8, n)
    k0 = np.arange(0, n - 25, 2)
    k1 = k0 + 25
    c = np.cumsum(gain[:, None] * weights, axis=0)
    c = np.concatenate([np.zeros((1, knots.size)), c])
    expected = c[k1] - c[k0]
    out = np.empty((k0.size, knots.size))
    knot_window_sums(gain, weights, k0, k1, out)
    assert np.array_equal(out, expected)
    assert np.array_equal(np.signbit(out), np.signbit(expected))


def test_window_sandwich_is_white_without_lags_and_sees_correlated_residuals():
    """The Newey-West sandwich of the valve fit (identify/valves.py, window_sandwich_sd) on a
    straight-line fit y = a + b t with 20,000 rows: with independent equal errors and no lag it
    is the Gauss-Newton standard error (within 3 %, the sampling error of 20,000 squares); when
    each error repeats over 4 consecutive rows (what overlapping windows make), its lag-8
    estimate is the no-lag one times sqrt(1 + 2 sum_l w_l (4 - l) / 4) = 1.856, the Bartlett
    weights w_l = 1 - l / 9 applied to the repeats' autocorrelation, to within 5 %."""
    from pneutune.identify.valves import window_sandwich_sd

    rng = np.random.default_rng(11)
    n = 20000
    t = np.linspace(0.0, 1.0, n)
    J = np.column_stack([np.ones(n), t])
    A = np.linalg.inv(J.T @ J)
    r = rng.normal(0.0, 0.5, n)
    gn = np.sqrt(np.diag(A) * np.sum(r**2) / (n - 2))
    assert window_sandwich_sd(J, r, A, (n // 2, n), 0) == pytest.approx(gn, rel=0.03)
    r4 = np.repeat(rng.normal(0.0, 0.5, n // 4), 4)
    no_lag = window_sandwich_sd(J, r4, A, (n // 2, n), 0)
    lagged = window_sandwich_sd(J, r4, A, (n // 2, n), 8)
    # lag-l autocovariance (4 - l) / 4 for l < 4, Bartlett weights 1 - l / 9
    expected = np.sqrt(1.0 + 2.0 * sum((1.0 - lg / 9.0) * (4 - lg) / 4.0 for lg in (1, 2, 3)))
    assert expected == pytest.approx(1.856, abs=1e-3)
    assert lagged / no_lag == pytest.approx(expected, rel=0.05)
