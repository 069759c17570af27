"""The moving mass from the lag of the motion behind the pressure force (fast logs).

While the piston slides, Eq. (1) with the friction of Eq. (2) reads

    M dv/dt + b_v v = g(t),   g = F_p - F_C sgn v - (F_S - F_C) e^{-(|v|/v_s)^alpha} sgn v + F_n.

Integrated once, ``b_v x + M v = G + c`` with ``G = ∫ g dt``, so that

    x(t) = lag_tau(G)(t) / b_v + c,   tau = M / b_v,

where ``lag_tau`` is the first-order lag ``1 / (1 + s tau)``. The position is the integrated
pressure force, delayed by the mechanical time constant. On the paper's rig tau is about
0.3 ms: invisible at the controller's 4 ms, but it shows in a log sampled every 0.5 ms
(identification_run.IDENT_SAMPLE_PERIOD), provided the pressures are sampled densely enough
for ``G`` to be integrated from them (the PWM switching makes the force kink between samples).

For a given tau the model is linear in ``1/b_v``, ``F_C/b_v``, ``F_n/b_v`` and one constant per
window, so tau is found by a one-dimensional search over exact linear least-squares fits. The
Stribeck excess uses the shape fitted by :class:`~pneutune.identify.motion.FrictionIdentifier`
(it is small above the 20 mm/s used here). No valve model and no valve timing enter: the
force comes from the measured pressures, sampled together with the position.

Two things set the interval:

* a moving-window bootstrap (windows resampled, tau re-minimised on a grid), and
* the discretisation error of the trapezoid force integral, taken as the change of the estimate
  when every other sample is dropped (a Richardson-style check; the integral's error is of
  second order in the sample period, so the change is about three times the error itself).

Several fast logs of one rig pool their windows (:class:`_StackedLagProblem`): each log keeps
its own signals, filters and windows, and one tau and one set of coefficients fit them all.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.optimize import minimize_scalar
from scipy.signal import savgol_filter

from pneutune.control.errors import LogError
from pneutune.control.numba_cache import njit
from pneutune.control.physics.friction import stribeck

from .base import Identifier
from .dataset import Dataset, IdentificationError
from .motion import FrictionIdentifier

#: Sliding speed above which windows are used [m/s] (as the Coulomb stage of the friction fit).
V_LAG = 0.02
#: Window length [s] (each window has its own position constant).
LAG_WINDOW = 0.05
#: Samples trimmed from both ends of a sliding stretch, as time [s].
LAG_MARGIN = 0.01
#: Least samples per PWM period for the trapezoid force integral to follow the PWM ripple:
#: at 4 ms (4 per period at 60 Hz) the estimate is 50-90 % low, at 2 ms and below it is
#: within a few per cent (docs/identifiability.md).
MIN_SAMPLES_PER_PWM = 8
#: Fewest windows for an estimate.
MIN_WINDOWS = 20


def samples_per_pwm(data: Dataset) -> float:
    """Logged samples per PWM period (the lag estimate needs MIN_SAMPLES_PER_PWM)."""
    return 1.0 / (data.rig.pwm_hz * data.Ts)


def lag_filter(u: np.ndarray, tau: float, h: float) -> np.ndarray:
    """Exact first-order lag ``1/(1 + s tau)`` of a signal linear between samples.

    Parameters
    ----------
    u : ndarray
        Samples ``h`` apart; the filter starts in steady state at ``u[0]``.
    tau : float
        Time constant [s] (> 0).
    h : float
        Sample period [s].

    Returns
    -------
    ndarray
        The filtered samples.
    """
    phi = np.exp(-h / tau)
    c = tau * (1.0 - phi) / h
    u = np.ascontiguousarray(u, dtype=np.float64)
    out = np.empty_like(u)
    _first_order_filter(u, 1.0 - c, c - phi, -phi, out)
    return out


def lag_filter3(signals: np.ndarray, tau: float, h: float, rows: np.ndarray) -> np.ndarray:
    """:func:`lag_filter` of three signals at once, kept at some samples only.

    Parameters
    ----------
    signals : ndarray, (3, N)
        The signals, samples ``h`` apart.
    tau : float
        Time constant [s] (> 0).
    h : float
        Sample period [s].
    rows : ndarray of int, (R,)
        The samples kept, increasing.

    Returns
    -------
    ndarray, (3, R)
        ``lag_filter(signals[k], tau, h)[rows]`` for each k (the same floats).
    """
    phi = np.exp(-h / tau)
    c = tau * (1.0 - phi) / h
    out = np.empty((3, rows.shape[0]))
    _first_order_filter3(np.ascontiguousarray(signals, dtype=np.float64), 1.0 - c, c - phi,
                         -phi, np.ascontiguousarray(rows, dtype=np.int64), out)
    return out


@njit(cache=True)
def _first_order_filter(u: np.ndarray, b0: float, b1: float, a1: float, out: np.ndarray) -> None:
    """``out = lfilter([b0, b1], [1, a1], u - u[0]) + u[0]`` (scipy.signal), in one pass.

    The transposed direct form II of ``lfilter`` with its floating-point operations in its
    order: ``y = z + b0 x``, then ``z = x b1 - y a1``, from ``z = 0``; so the same floats.
    """
    u0 = u[0]
    z = 0.0
    for i in range(u.shape[0]):
        x = u[i] - u0
        y = z + b0 * x
        z = x * b1 - y * a1
        out[i] = y + u0


@njit(cache=True)
def _first_order_filter3(u: np.ndarray, b0: float, b1: float, a1: float, rows: np.ndarray,
                         out: np.ndarray) -> None:
    """:func:`_first_order_filter` of the three rows of ``u`` side by side (their recursions
    overlap in the processor), stored at the samples ``rows`` only."""
    u0, u1, u2 = u[0, 0], u[1, 0], u[2, 0]
    z0 = z1 = z2 = 0.0
    r = 0
    for i in range(u.shape[1]):
        x0 = u[0, i] - u0
        x1 = u[1, i] - u1
        x2 = u[2, i] - u2
        y0 = z0 + b0 * x0
        y1 = z1 + b0 * x1
        y2 = z2 + b0 * x2
        z0 = x0 * b1 - y0 * a1
        z1 = x1 * b1 - y1 * a1
        z2 = x2 * b1 - y2 * a1
        if r < rows.shape[0] and rows[r] == i:
            out[0, r] = y0 + u0
            out[1, r] = y1 + u1
            out[2, r] = y2 + u2
            r += 1


def sliding_windows(ok: np.ndarray, length: int, trim: int) -> np.ndarray:
    """Window index of every sample (-1: unused): stretches of ``ok`` cut into windows.

    Each stretch of consecutive True loses ``trim`` samples at both ends and is cut into
    windows of ``length`` samples; a remainder of at least half a window is a window too.
    """
    g = np.full(ok.shape[0], -1)
    edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    gid = 0
    for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        s, e = s + trim, e - trim
        while e - s >= max(2, length // 2):
            n = min(length, e - s)
            g[s:s + n] = gid
            gid += 1
            s += n
    return g


class _LagProblem:
    """The linear least-squares problem of one log for any tau."""

    def __init__(self, x: np.ndarray, F_p: np.ndarray, h: float, ok: np.ndarray,
                 friction: FrictionIdentifier) -> None:
        f = friction
        v = savgol_filter(x, max(5, round(0.005 / h) | 1), 3, deriv=1, delta=h)
        sgn = np.sign(v)
        # the Stribeck excess over the Coulomb level: Eq. (2) with F_C and b_v set to zero
        excess = stribeck(v, f.F_S_ - f.F_C_, 0.0, f.v_s_, f.alpha_, 0.0)
        self.h = h
        self.signals = np.stack([cumulative_trapezoid(F_p - excess, dx=h, initial=0.0),
                                 cumulative_trapezoid(sgn, dx=h, initial=0.0),
                                 np.arange(x.shape[0]) * h])
        group = sliding_windows(ok & (np.abs(v) > V_LAG), max(8, round(LAG_WINDOW / h)),
                                round(LAG_MARGIN / h))
        self.sel = group >= 0
        self._rows = np.flatnonzero(self.sel)
        self.group = group[self.sel]
        self.n_groups = int(self.group.max()) + 1 if self.group.size else 0
        self._count = np.bincount(self.group, minlength=self.n_groups).astype(float)
        self.X = self._demean(x[self.sel])

    def _demean(self, z: np.ndarray) -> np.ndarray:
        return z - (np.bincount(self.group, z, self.n_groups) / self._count)[self.group]

    def design(self, tau: float) -> np.ndarray:
        """Regressors (columns: lagged ∫(F_p - excess), ∫sgn v, t), demeaned per window."""
        lagged = lag_filter3(self.signals, tau, self.h, self._rows)
        return np.column_stack([self._demean(col) for col in lagged])

    def rss(self, tau: float) -> float:
        """Residual sum of squares of the best linear fit at ``tau``."""
        A = self.design(tau)
        coef, *_ = np.linalg.lstsq(A, self.X, rcond=None)
        r = self.X - A @ coef
        return float(r @ r)

    def solve(self, tau_max: float) -> tuple[float, np.ndarray, float]:
        """(tau, coefficients, residual rms) minimising the residual over (0, tau_max]."""
        taus = np.geomspace(self.h / 100.0, tau_max, 60)
        rss = np.array([self.rss(t) for t in taus])
        i = int(np.argmin(rss))
        lo, hi = taus[max(i - 1, 0)], taus[min(i + 1, taus.size - 1)]
        tau = float(minimize_scalar(self.rss, bounds=(lo, hi), method="bounded",
                                    options={"xatol": 1e-3 * lo}).x)
        A = self.design(tau)
        coef, *_ = np.linalg.lstsq(A, self.X, rcond=None)
        r = self.X - A @ coef
        return tau, coef, float(np.sqrt(np.mean(r**2)))

    def group_stats(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-window A'A (G, 3, 3), A'X (G, 3), X'X (G,) at ``tau``."""
        A = self.design(tau)
        G = self.n_groups
        AA = np.zeros((G, 3, 3))
        AX = np.zeros((G, 3))
        for i in range(3):
            AX[:, i] = np.bincount(self.group, A[:, i] * self.X, G)
            for j in range(i, 3):
                AA[:, i, j] = AA[:, j, i] = np.bincount(self.group, A[:, i] * A[:, j], G)
        return AA, AX, np.bincount(self.group, self.X * self.X, G)


class _StackedLagProblem(_LagProblem):
    """The problems of several logs as one: rows stacked, windows numbered on, one tau.

    Each log's regressors are built and demeaned per window in its own problem (its own sample
    period, filters and integrals), so that nothing runs across from one log to the next.
    """

    def __init__(self, problems: Sequence[_LagProblem]) -> None:
        self.problems = tuple(problems)
        self.h = min(p.h for p in self.problems)
        offsets = np.cumsum([0] + [p.n_groups for p in self.problems])
        self.group = np.concatenate([p.group + off for p, off in
                                     zip(self.problems, offsets[:-1], strict=True)])
        self.n_groups = int(offsets[-1])
        self.X = np.concatenate([p.X for p in self.problems])

    def design(self, tau: float) -> np.ndarray:
        """Every log's regressors at ``tau``, stacked."""
        return np.vstack([p.design(tau) for p in self.problems])


def _problem(datasets: Sequence[Dataset], masks: Sequence[np.ndarray], step: int,
             friction: FrictionIdentifier) -> _LagProblem:
    """One problem over every log (every ``step``-th sample), stacked when several."""
    probs = [_LagProblem(d.x[::step], d.F_p[::step], step * d.Ts, m[::step], friction)
             for d, m in zip(datasets, masks, strict=True)]
    return probs[0] if len(probs) == 1 else _StackedLagProblem(probs)


class LagMassIdentifier(Identifier):
    """Moving mass M = tau b_v from the lag of the position behind the integrated force.

    Parameters
    ----------
    friction : FrictionIdentifier
        Fitted friction (its Stribeck shape; F_C, b_v and F_n are refitted here).
    n_boot : int
        Bootstrap replicates (windows resampled).
    seed : int
        Bootstrap seed.

    Attributes
    ----------
    M_ : float
        Estimate [kg].
    tau_, b_v_, F_C_, F_n_ : float
        Mechanical time constant [s] and the friction terms of the same fit.
    ci_ : (float, float)
        99 % interval [kg]: bootstrap quantiles widened by ``discretisation_``.
    bootstrap_ci_ : (float, float)
        The bootstrap quantiles alone [kg].
    M_half_ : float
        The estimate from every other sample [kg].
    discretisation_ : float
        ``|M_ - M_half_|`` [kg].
    residual_std_ : float
        Residual rms of the position [m].
    n_windows_ : int
        Windows used.
    """

    def __init__(self, friction: FrictionIdentifier, n_boot: int = 400, seed: int = 0) -> None:
        self.friction = friction
        self.n_boot = n_boot
        self.seed = seed

    def fit(self, data: Dataset | Sequence[Dataset],
            mask: np.ndarray | Sequence[np.ndarray] | None = None) -> LagMassIdentifier:
        """Fit on the sliding windows inside ``mask`` (full-rate data).

        Parameters
        ----------
        data : Dataset or sequence of Dataset
            One log, or several logs of one rig (their windows pooled, module docstring).
        mask : ndarray of bool, or one per log, optional
            Samples that may be used (default: all).

        Raises
        ------
        IdentificationError
            Samples too sparse for the PWM ripple (fewer than MIN_SAMPLES_PER_PWM per PWM
            period), or fewer than MIN_WINDOWS sliding windows.
        """
        datasets = [data] if isinstance(data, Dataset) else list(data)
        if mask is None:
            masks = [np.ones(d.n, dtype=bool) for d in datasets]
        elif isinstance(data, Dataset):
            masks = [np.asarray(mask)]
        else:
            masks = [np.asarray(m) for m in mask]
        name = ", ".join(d.path for d in datasets)
        for d in datasets:
            per_pwm = samples_per_pwm(d)
            if per_pwm < MIN_SAMPLES_PER_PWM:
                raise IdentificationError(
                    d.path, f"{per_pwm:.1f} samples per PWM period; the lag of the motion "
                    f"behind the pressure force needs at least {MIN_SAMPLES_PER_PWM} (a sample "
                    f"period of {1e3 / (MIN_SAMPLES_PER_PWM * d.rig.pwm_hz):.3g} ms or less)")
        tau_max = 0.05
        prob = _problem(datasets, masks, 1, self.friction)
        if prob.n_groups < MIN_WINDOWS:
            raise IdentificationError(name, f"only {prob.n_groups} sliding windows of "
                                      f"{LAG_WINDOW:g} s faster than {V_LAG * 1e3:g} mm/s")
        tau, coef, rms = prob.solve(tau_max)
        self.tau_ = tau
        self.b_v_ = 1.0 / coef[0]
        self.F_C_ = -coef[1] * self.b_v_
        self.F_n_ = coef[2] * self.b_v_
        self.M_ = tau * self.b_v_
        self.residual_std_ = rms
        self.n_windows_ = prob.n_groups
        self.bootstrap_ci_ = self._bootstrap(prob, tau)
        try:
            half = _problem(datasets, masks, 2, self.friction)
            t2, c2, _ = half.solve(tau_max)
            self.M_half_ = float(t2 / c2[0])
        except (LogError, ValueError, np.linalg.LinAlgError):
            self.M_half_ = float("inf")
        self.discretisation_ = abs(self.M_ - self.M_half_)
        lo, hi = self.bootstrap_ci_
        self.ci_ = (max(lo - self.discretisation_, 0.0), hi + self.discretisation_)
        self.fitted_ = True
        return self

    def _bootstrap(self, prob: _LagProblem, tau: float) -> tuple[float, float]:
        """99 % interval of M over window resamples, tau re-minimised on a log grid."""
        grid = tau * np.exp(np.linspace(-0.7, 0.7, 57))
        stats = [prob.group_stats(t) for t in grid]
        AA = np.stack([s[0] for s in stats])          # (T, G, 3, 3)
        AX = np.stack([s[1] for s in stats])          # (T, G, 3)
        XX = stats[0][2]                              # (G,)
        rng = np.random.default_rng(self.seed)
        G = prob.n_groups
        out = np.empty(self.n_boot)
        for b in range(self.n_boot):
            w = np.bincount(rng.integers(0, G, G), minlength=G).astype(float)
            sAA = np.einsum("g,tgij->tij", w, AA)
            sAX = np.einsum("g,tgi->ti", w, AX)
            coef = np.linalg.solve(sAA, sAX[..., None])[..., 0]
            rss = float(w @ XX) - np.einsum("ti,ti->t", sAX, coef)
            j = int(np.clip(np.argmin(rss), 1, grid.size - 2))
            # parabola through three points in log tau
            y0, y1, y2 = rss[j - 1], rss[j], rss[j + 1]
            den = y0 - 2.0 * y1 + y2
            step = 0.5 * (y0 - y2) / den if den > 0 else 0.0
            dz = np.log(grid[1] / grid[0])
            t_b = grid[j] * np.exp(np.clip(step, -1.0, 1.0) * dz)
            out[b] = t_b / coef[j, 0]
        lo, hi = np.quantile(out, [0.005, 0.995])
        return float(lo), float(hi)
