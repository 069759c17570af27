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
