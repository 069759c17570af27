"""Kalman filters of Sec. 4 (Eqs. 34-36): class vs pure functions, steady state vs scipy DARE."""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.control.law.kalman import (
    KalmanFilter,
    force_model,
    kf_predict,
    kf_predict_into,
    kf_update,
    kf_update_into,
    motion_model,
    process_cov,
    steady_state_gain,
    work_size,
)

TS = 0.004  # Sec. 5.1: sampling period 4 ms
# Sec. 5.1 Q = 3100, R = 0.0001 read in mm (docs/controller.md), converted to SI:
Q_MOTION = 3100.0e-6  # m^2/s^4
R_MOTION = 1.0e-4 * 1.0e-6  # m^2
# data/controller-paper.yaml: the force filter in N (same Q/R ratio as the paper's numbers)
Q_FORCE = 3100.0  # N^2/s^4
R_FORCE = 1.0e-4  # N^2


def _filters(which: str, rng: np.random.Generator):
    if which == "motion":
        A, W, H = motion_model(TS)
        Q, R = Q_MOTION, R_MOTION
        x0 = np.array([0.01, 0.0, 0.0])
        P0 = np.diag([1e-8, 1e-2, 1.0])
    else:
        A, W, H = force_model(TS)
        Q, R = Q_FORCE, R_FORCE
        x0 = np.array([10.0, 0.0])
        P0 = np.diag([1.0, 1e6])
    kf = KalmanFilter(A, W, H, Q, R, x0, P0)
    return kf, A, W, H, Q, R, x0, P0


def test_models_are_eq34() -> None:
    """A_d, W_d, H_d of Eq. (34) for both filters."""
    A, W, H = motion_model(TS)
    np.testing.assert_allclose(A, [[1, TS, TS**2 / 2], [0, 1, TS], [0, 0, 1]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(W, [TS**2 / 2, TS, 1], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(H, [1, 0, 0])
    A, W, H = force_model(TS)
    np.testing.assert_allclose(A, [[1, TS], [0, 1]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(W, [TS**2 / 2, TS], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(H, [1, 0])


@pytest.mark.parametrize("which", ["motion", "force"])
def test_class_matches_pure_functions(which: str) -> None:
    """Class and pure functions agree to 1e-12 (as FilterPy's procedure-form test)."""
    rng = np.random.default_rng(20140416)
    kf, A, W, H, Q, R, x, P = _filters(which, rng)
    WQWt = process_cov(W, Q)
    for k in range(300):
        z = float(x[0] + rng.normal(0.0, np.sqrt(R)) + 0.001 * np.sin(0.05 * k))
        kf.predict()
        kf.update(z)
        x, P = kf_predict(x, P, A, WQWt)
        x, P, _ = kf_update(x, P, z, H, R)
        scale_x = np.maximum(np.abs(x), 1.0)
        np.testing.assert_allclose(kf.x / scale_x, x / scale_x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(kf.P, P, rtol=1e-12, atol=1e-12 * np.abs(P).max())


@pytest.mark.parametrize("which", ["motion", "force"])
def test_inplace_flat_kernels_match_pure(which: str) -> None:
    """The flat in-place kernels the DARC step uses are the same equations (to 1e-12)."""
    rng = np.random.default_rng(7)
    _, A, W, H, Q, R, x, P = _filters(which, rng)
    n = x.shape[0]
    WQWt = process_cov(W, Q)
    xf, Pf, work = x.copy(), P.ravel().copy(), np.empty(work_size(n))
    for _ in range(50):
        z = float(rng.normal(x[0], 10 * np.sqrt(R)))
        x, P = kf_predict(x, P, A, WQWt)
        x, P, K = kf_update(x, P, z, H, R)
        kf_predict_into(xf, Pf, A, WQWt, work)
        kf_update_into(xf, Pf, z, H, R, work)
        np.testing.assert_allclose(xf, x, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(Pf.reshape(n, n), P, rtol=1e-12, atol=1e-12 * np.abs(P).max())
        np.testing.assert_allclose(work[:n], K, rtol=1e-12, atol=0)


@pytest.mark.parametrize("which", ["motion", "force"])
def test_steady_state_gain_matches_dare(which: str) -> None:
    """Iterating Eqs. (35)-(36) converges to the gain of the discrete algebraic Riccati equation
    P = A P A^T - A P H^T (H P H^T + R)^-1 H P A^T + W Q W^T (scipy.linalg.solve_discrete_are)."""
    rng = np.random.default_rng(3)
    kf, A, W, H, Q, R, _, _ = _filters(which, rng)
    for _ in range(5000):
        kf.predict()
        kf.update(float(kf.x[0]))
    K_dare = steady_state_gain(A, process_cov(W, Q), H, R)
    np.testing.assert_allclose(kf.K, K_dare, rtol=1e-6)


def test_joseph_form_keeps_p_symmetric_psd() -> None:
    """Eq. (36) Joseph form: P stays symmetric positive definite after many updates."""
    rng = np.random.default_rng(11)
    kf, *_ = _filters("motion", rng)
    for _ in range(2000):
        kf.predict()
        kf.update(float(rng.normal(0.0, 1e-5)))
    np.testing.assert_allclose(kf.P, kf.P.T, rtol=0, atol=1e-12 * np.abs(kf.P).max())
    assert np.all(np.linalg.eigvalsh(kf.P) > 0.0)


def test_motion_filter_tracks_a_sine() -> None:
    """With the paper's Q/R the motion filter recovers v and a of 17.5 sin(pi t) mm (Sec. 5.2)
    from 5 um-noise samples within 5 mm/s and 0.2 m/s^2 after the transient."""
    rng = np.random.default_rng(5)
    kf = KalmanFilter.motion(TS, Q_MOTION, R_MOTION, np.zeros(3), np.diag([1e-8, 1e-2, 1.0]))
    t = np.arange(0, 4.0, TS)
    x = 0.0175 * np.sin(np.pi * t)
    v = 0.0175 * np.pi * np.cos(np.pi * t)
    a = -0.0175 * np.pi**2 * np.sin(np.pi * t)
    est = np.array([kf.step(float(xi + rng.normal(0, 5e-6))).copy() for xi in x])
    late = t > 1.0
    assert np.max(np.abs(est[late, 1] - v[late])) < 5e-3
    assert np.max(np.abs(est[late, 2] - a[late])) < 0.2
