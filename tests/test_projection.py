"""Rate-limited discontinuous projection, Eqs. (9)-(11): the three properties of Eq. (12)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pneutune.control.law.projection import (
    adapt_step_into,
    adaptation_rate,
    adaptation_rate_into,
    proj,
)

# Sec. 5.1 bounds, Γ and θ̇M (θ = [M, F_n, b_v, A_f, D_an, D_bn]).
THETA_MIN = np.array([0.5, -10.0, 2000.0, -50.0, -20.0, -20.0])
THETA_MAX = np.array([5.0, 10.0, 5000.0, 200.0, 20.0, 20.0])
GAMMA = np.array([0.2, 300.0, 2000.0, 500.0, 100.0, 100.0])
RATE_MAX = np.array([50.0, 500.0, 2000.0, 100.0, 50.0, 50.0])
TS = 0.004

unit = st.floats(0.0, 1.0, allow_nan=False)
taus = st.lists(st.floats(-1e6, 1e6, allow_nan=False, allow_subnormal=False),
                min_size=6, max_size=6).map(np.array)
fractions = st.lists(unit, min_size=6, max_size=6).map(np.array)
# Estimates inside Ω, with the bounds themselves drawn often (where Eq. 10 acts).
edge_fractions = st.lists(st.one_of(unit, st.sampled_from([0.0, 1.0])), min_size=6,
                          max_size=6).map(np.array)


def _in_box(f: np.ndarray) -> np.ndarray:
    return THETA_MIN + f * (THETA_MAX - THETA_MIN)


@settings(max_examples=300, deadline=None)
@given(edge_fractions, fractions, taus)
def test_eq12_property2_projection_dissipative(fh: np.ndarray, ft: np.ndarray,
                                               tau: np.ndarray) -> None:
    """Eq. (12) line 2: θ̃^T [Γ^-1 Proj_θ̂(Γτ) - τ] <= 0 for all τ, θ̂, θ in Ω_θ."""
    theta_hat, theta = _in_box(fh), _in_box(ft)
    p = proj(theta_hat, GAMMA * tau, THETA_MIN, THETA_MAX)
    value = float((theta_hat - theta) @ (p / GAMMA - tau))
    assert value <= 1e-12 * (1.0 + float(np.abs((theta_hat - theta) * tau).sum()))


@settings(max_examples=100, deadline=None)
@given(edge_fractions, st.lists(taus, min_size=1, max_size=60))
def test_eq12_properties_1_and_3_discrete_update(fh: np.ndarray, tau_seq: list) -> None:
    """Eq. (12) lines 1 and 3 for the discrete update: θ̂ stays in Ω_θ and every effective
    rate (θ̂_new - θ̂_old)/Ts is bounded by θ̇M, for any sequence of τ."""
    theta_hat = _in_box(fh)
    rate = np.empty(6)
    for tau in tau_seq:
        old = theta_hat.copy()
        adapt_step_into(theta_hat, tau, GAMMA, RATE_MAX, THETA_MIN, THETA_MAX, TS, rate)
        assert np.all(theta_hat >= THETA_MIN) and np.all(theta_hat <= THETA_MAX)
        assert np.all(np.abs(rate) <= RATE_MAX * (1 + 1e-12))
        np.testing.assert_allclose(rate * TS, theta_hat - old, rtol=1e-12, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(edge_fractions, taus)
def test_eq12_property3_continuous_rate(fh: np.ndarray, tau: np.ndarray) -> None:
    """Eq. (12) line 3: |dθ̂_i/dt| <= θ̇Mi for the rate of Eq. (9); same sign as Proj(Γτ)."""
    theta_hat = _in_box(fh)
    r = adaptation_rate(theta_hat, tau, GAMMA, RATE_MAX, THETA_MIN, THETA_MAX)
    p = proj(theta_hat, GAMMA * tau, THETA_MIN, THETA_MAX)
    assert np.all(np.abs(r) <= RATE_MAX)
    assert np.all(r * p >= 0.0)


def test_eq10_eq11_cases() -> None:
    """Eq. (10): zero only at a bound and pointing out; Eq. (11): clip to ±θ̇M."""
    th = np.array([5.0, -10.0, 3000.0, 200.0, -20.0, 0.0])  # at max, at min, inside, ...
    v = np.array([1.0, -1.0, 1e9, -1.0, 1.0, -1e9])
    np.testing.assert_array_equal(proj(th, v, THETA_MIN, THETA_MAX),
                                  [0.0, 0.0, 1e9, -1.0, 1.0, -1e9])
    out = np.empty(6)
    adaptation_rate_into(th, v / GAMMA, GAMMA, RATE_MAX, THETA_MIN, THETA_MAX, out)
    np.testing.assert_allclose(out, [0.0, 0.0, 2000.0, -1.0, 1.0, -50.0], rtol=1e-12)


def test_discrete_step_stops_at_the_bound() -> None:
    """An Euler step that would overshoot θ_max ends exactly on it (clip), then holds."""
    th = np.array([4.99, 0.0, 3500.0, 100.0, 0.0, 0.0])
    tau = np.array([1e6, 0.0, 0.0, 0.0, 0.0, 0.0])
    rate = np.empty(6)
    adapt_step_into(th, tau, GAMMA, RATE_MAX, THETA_MIN, THETA_MAX, TS, rate)
    assert th[0] == 5.0
    np.testing.assert_allclose(rate[0], 0.01 / TS, rtol=1e-9)
    adapt_step_into(th, tau, GAMMA, RATE_MAX, THETA_MIN, THETA_MAX, TS, rate)
    assert th[0] == 5.0 and rate[0] == 0.0
