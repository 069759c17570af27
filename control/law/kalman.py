"""Kalman filters of Sec. 4: the C core (``control/law/c/ptlaw.c``) and the models around it.

Model (Eq. 34)::

    X[k+1] = A_d X[k] + W_d w[k],     z[k] = H_d X[k] + v[k],
    E[w^2] = Q,  E[v^2] = R.

* Motion filter (3 states: x [m], v [m/s], a [m/s^2]; constant acceleration between samples):
  ``A_d = [[1, Ts, Ts^2/2], [0, 1, Ts], [0, 0, 1]]``, ``W_d = [Ts^2/2, Ts, 1]``,
  ``H_d = [1, 0, 0]``. w is an acceleration [m/s^2], so Q is in m^2/s^4 and R in m^2.
* Force filter (2 states: F_pd [N], dF_pd/dt [N/s]):
  ``A_d = [[1, Ts], [0, 1]]``, ``W_d = [Ts^2/2, Ts]``, ``H_d = [1, 0]``.
  w is a second derivative of force [N/s^2], so Q is in N^2/s^4 and R in N^2.

Time update, Eq. (35): ``x <- A x``, ``P <- A P A^T + W Q W^T``.
Measurement update, Eq. (36), in Joseph form::

    K = P H^T / (H P H^T + R),   x <- x + K (z - H x),
    P <- (I - K H) P (I - K H)^T + K R K^T.

Both filters of Sec. 4 measure one scalar, so the core handles a scalar measurement (``H`` a row
vector, ``R`` a float). The Joseph form keeps P symmetric positive semi-definite in floating
point; with the paper's Q/R (docs/controller.md) the plain form ``(I - K H) P`` loses symmetry.

Layout of the core: the in-place kernels :func:`kf_predict_into` and :func:`kf_update_into` take
the state mean ``x`` (n) and the covariance ``P`` *flattened row-major* (n*n) plus a scratch
buffer, so that the DARC step can run them on slices of its flat state vector without allocating.
:func:`kf_predict` and :func:`kf_update` are the pure (allocating) forms with a 2-D ``P``;
:class:`KalmanFilter` is a thin class over them. The in-place kernels call ``pt_kf_predict_into``
and ``pt_kf_update_into`` of ``ptlaw.c`` (:mod:`pneutune.control.law.clib`), the only copy of
Eqs. (35)-(36).
"""

from __future__ import annotations

import numpy as np

from pneutune.control.law import clib
from pneutune.control.numba_cache import njit


def work_size(n: int) -> int:
    """Length of the scratch buffer the in-place kernels need for ``n`` states (2 n^2 + n)."""
    return 2 * n * n + n


@njit(cache=True, error_model="numpy")
def kf_predict_into(x: np.ndarray, Pf: np.ndarray, A: np.ndarray, WQWt: np.ndarray,
                    work: np.ndarray) -> None:
    """Time update of Eq. (35), in place.

    Parameters
    ----------
    x : (n,) float64
        State mean, overwritten with ``A x``.
    Pf : (n*n,) float64
        Covariance flattened row-major, overwritten with ``A P A^T + W Q W^T``.
    A : (n, n) float64
        Transition matrix A_d.
    WQWt : (n, n) float64
        Process-noise covariance ``W_d Q W_d^T``.
    work : (>= n*n + n,) float64
        Scratch; its content on return is meaningless.
    """
    clib.pt_kf_predict_into(x.ctypes, Pf.ctypes, A.ctypes, WQWt.ctypes, work.ctypes,
                            x.shape[0])


@njit(cache=True, error_model="numpy")
def kf_update_into(x: np.ndarray, Pf: np.ndarray, z: float, H: np.ndarray, R: float,
                   work: np.ndarray) -> None:
    """Measurement update of Eq. (36) in Joseph form, in place, for a scalar measurement.

    Parameters
    ----------
    x : (n,) float64
        A priori mean, overwritten with the a posteriori mean.
    Pf : (n*n,) float64
        A priori covariance flattened row-major, overwritten with the a posteriori one.
    z : float
        Measurement (unit of ``H x``).
    H : (n,) float64
        Measurement row H_d.
    R : float
        Measurement-noise variance R_d (unit of z squared).
    work : (>= 2 n^2 + n,) float64
        Scratch. On return ``work[:n]`` holds the Kalman gain K of this update.
    """
    clib.pt_kf_update_into(x.ctypes, Pf.ctypes, z, H.ctypes, R, work.ctypes, x.shape[0])


@njit(cache=True, error_model="numpy")
def kf_predict(x: np.ndarray, P: np.ndarray, A: np.ndarray,
               WQWt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Time update of Eq. (35) (pure: returns new arrays).

    Parameters
    ----------
    x : (n,) float64
        A posteriori mean at k-1.
    P : (n, n) float64
        A posteriori covariance at k-1.
    A, WQWt : (n, n) float64
        A_d and ``W_d Q W_d^T``.

    Returns
    -------
    x, P : (n,), (n, n) float64
        A priori mean and covariance at k.
    """
    n = x.shape[0]
    xo = x.copy()
    Pf = np.ascontiguousarray(P).copy().reshape(n * n)
    work = np.empty(2 * n * n + n)
    kf_predict_into(xo, Pf, A, WQWt, work)
    return xo, Pf.reshape((n, n))


@njit(cache=True, error_model="numpy")
def kf_update(x: np.ndarray, P: np.ndarray, z: float, H: np.ndarray,
              R: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measurement update of Eq. (36), Joseph form (pure: returns new arrays).

    Parameters
    ----------
    x : (n,) float64
        A priori mean.
    P : (n, n) float64
        A priori covariance.
    z : float
        Measurement.
    H : (n,) float64
        Measurement row H_d.
    R : float
        Measurement-noise variance.

    Returns
    -------
    x, P, K : (n,), (n, n), (n,) float64
        A posteriori mean and covariance, and the Kalman gain used.
    """
    n = x.shape[0]
    xo = x.copy()
    Pf = np.ascontiguousarray(P).copy().reshape(n * n)
    work = np.empty(2 * n * n + n)
    kf_update_into(xo, Pf, z, H, R, work)
    return xo, Pf.reshape((n, n)), work[:n].copy()


def motion_model(Ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. (34), motion states [x, v, a]: constant acceleration between samples.

    Parameters
    ----------
    Ts : float
        Sampling period [s].

    Returns
    -------
    A, W, H : (3, 3), (3,), (3,) float64
        A_d, W_d and H_d.
    """
    A = np.array([[1.0, Ts, 0.5 * Ts * Ts], [0.0, 1.0, Ts], [0.0, 0.0, 1.0]])
    W = np.array([0.5 * Ts * Ts, Ts, 1.0])
    H = np.array([1.0, 0.0, 0.0])
    return A, W, H


def force_model(Ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. (34), intermediate-control-law states [F_pd, dF_pd/dt].

    Parameters
    ----------
    Ts : float
        Sampling period [s].

    Returns
    -------
    A, W, H : (2, 2), (2,), (2,) float64
        A_d, W_d and H_d.
    """
    A = np.array([[1.0, Ts], [0.0, 1.0]])
    W = np.array([0.5 * Ts * Ts, Ts])
    H = np.array([1.0, 0.0])
    return A, W, H


def process_cov(W: np.ndarray, Q: float) -> np.ndarray:
    """``W_d Q W_d^T`` of Eq. (35) for a scalar process noise of variance ``Q``."""
    W = np.asarray(W, dtype=np.float64)
    return float(Q) * np.outer(W, W)


def steady_state_gain(A: np.ndarray, WQWt: np.ndarray, H: np.ndarray, R: float) -> np.ndarray:
    """Steady-state Kalman gain from the discrete algebraic Riccati equation (scipy).

    The a priori covariance P of the converged filter solves
    ``P = A P A^T - A P H^T (H P H^T + R)^-1 H P A^T + W Q W^T``, which is
    ``scipy.linalg.solve_discrete_are(A^T, H^T, W Q W^T, R)``; then ``K = P H^T / (H P H^T + R)``.
    """
    from scipy.linalg import solve_discrete_are

    Hm = np.asarray(H, dtype=np.float64).reshape(1, -1)
    P = solve_discrete_are(np.asarray(A).T, Hm.T, np.asarray(WQWt), np.array([[float(R)]]))
    return (P @ Hm.T / (Hm @ P @ Hm.T + R)).ravel()


class KalmanFilter:
    """A scalar-measurement Kalman filter (Eqs. 35-36) over the pure functions.

    Parameters
    ----------
    A : (n, n) array
        Transition matrix A_d.
    W : (n,) array
        Noise input W_d.
    H : (n,) array
        Measurement row H_d.
    Q : float
        Process-noise variance (unit: w squared).
    R : float
        Measurement-noise variance (unit: z squared).
    x0 : (n,) array
        Initial mean.
    P0 : (n, n) array
        Initial covariance.

    Attributes
    ----------
    x, P : arrays
        Current mean and covariance.
    K : (n,) array
        Gain of the last update (zeros before the first).
    """

    def __init__(self, A: np.ndarray, W: np.ndarray, H: np.ndarray, Q: float, R: float,
                 x0: np.ndarray, P0: np.ndarray) -> None:
        self.A = np.ascontiguousarray(A, dtype=np.float64)
        self.H = np.ascontiguousarray(H, dtype=np.float64)
        self.WQWt = process_cov(W, Q)
        self.R = float(R)
        self.x = np.array(x0, dtype=np.float64)
        self.P = np.array(P0, dtype=np.float64)
        self.K = np.zeros_like(self.x)

    @classmethod
    def motion(cls, Ts: float, Q: float, R: float, x0: np.ndarray,
               P0: np.ndarray) -> KalmanFilter:
        """The 3-state motion filter of Sec. 4 (Q [m^2/s^4], R [m^2], Ts [s])."""
        A, W, H = motion_model(Ts)
        return cls(A, W, H, Q, R, x0, P0)

    @classmethod
    def force(cls, Ts: float, Q: float, R: float, x0: np.ndarray,
              P0: np.ndarray) -> KalmanFilter:
        """The 2-state F_pd filter of Sec. 4 (Q [N^2/s^4], R [N^2], Ts [s])."""
        A, W, H = force_model(Ts)
        return cls(A, W, H, Q, R, x0, P0)

    def predict(self) -> None:
        """Time update, Eq. (35)."""
        self.x, self.P = kf_predict(self.x, self.P, self.A, self.WQWt)

    def update(self, z: float) -> None:
        """Measurement update, Eq. (36), Joseph form."""
        self.x, self.P, self.K = kf_update(self.x, self.P, float(z), self.H, self.R)

    def step(self, z: float) -> np.ndarray:
        """Predict then update with ``z``; returns the a posteriori mean."""
        self.predict()
        self.update(z)
        return self.x
