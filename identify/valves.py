"""Valve conductances C, critical ratios b and the PWM duty curves, from chamber pressures.

The chamber equations (5)-(6) of the paper, integrated over windows of whole PWM periods:

    p(t_k1) - p(t_k0) = sum_k [ Ts n R T0 / V_k (r_in(u_in,k) Φ_in,k - r_out(u_out,k) Φ_out,k ∓ L_k)
                                - n p_k (V_k+1 - V_k) / V_k ] + Ts (k1 - k0) D

with Φ the ISO 6358 flow of Eq. (7) (:func:`pneutune.control.physics.flow.signed_flow_array`,
reverse
flow included), L the seal leak (ISO 6358 with b = 0), r(u) the effective open fraction of a
valve at commanded duty u (the PWM curve) and midpoint values p_k, V_k over each sample. Windows
of whole PWM periods make the on/off ripple of the valves cancel at the window ends. Position
increments replace dV/dt, so nothing is differentiated.

D_a, D_b and the leak come first from the stretches with a chamber's valves shut, where the log
has them (:mod:`.valve_leak`), and are held there. Then two alternating solves (block
coordinate descent):

1. curves fixed: nonlinear least squares (``scipy.optimize.least_squares``, bounded, its
   Jacobian from :mod:`.valve_jacobian`) for C, b of the four valves, the leak conductance and
   the constant terms D_a, D_b, with a weak prior on b (:data:`B_PRIOR` ± :data:`B_PRIOR_SD`,
   weighted like one window) that decides b only where the log cannot;
2. C, b fixed: the equations are linear in the curve values at the knots, so each chamber's two
   curves come from a QP (:func:`~.valve_curves.chamber_curves`): monotone, 0 <= r <= 1,
   r(0) = 0, r(1) = 1 (which fixes the scale between C and r), with a small curvature penalty
   where the data say little.

Then the timing stage (:mod:`.valve_timing`): r(u) is exact only while the duties are steady
over a PWM period. With the valves' delays, minimum pulses and the carrier phase searched, the
opening of every valve in every sample is computed as the rig switches it, and C, b, D are
refitted on it. On closed-loop logs this took C from 15-50 % off to within 3 %
(benchmarks/fleet.py); on the identification run it changes C by 0.3 % and gives the delays to
about 0.1 ms. The PWM curves then follow from the timings
(:func:`~pneutune.control.physics.pwm.effective_open_fraction`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_filter
from threadpoolctl import threadpool_limits

from pneutune.control.constants import VALVES
from pneutune.control.physics.pwm import effective_open_fraction
from pneutune.control.sim.model_box import MIN_PULSE_SPAN

from .base import Identifier
from .dataset import Dataset, IdentificationError, true_runs
from .valve_curves import chamber_curves, curve_switching, default_knots, interp_weights
from .valve_flows import A_IN, A_OUT, B_IN, B_OUT, LEAK, PortFlows
from .valve_jacobian import grouped_jacobian, valve_fit_groups
from .valve_leak import closed_stretches
from .valve_onsets import Onset, step_onsets
from .valve_residuals import chamber_window_residuals, knot_window_sums
from .valve_timing import LOOP_DELAY_TOLERANCE as LOOP_DELAY_TOLERANCE  # re-exported
from .valve_timing import (
    MIN_PULSE_STEP,
    OpenFractions,
    Timing,
    TimingCost,
    min_pulse_range,
    search_timings,
    timing_bounds,
)
from .valve_timing import ONSET_MARGIN as ONSET_MARGIN  # re-exported

#: Parameter scaling for the solver: C in 1e-9 m^3/(s Pa), leak in 1e-10, D in 1e3 Pa/s.
_C_UNIT, _LEAK_UNIT, _D_UNIT = 1e-9, 1e-10, 1e3
#: Prior of the critical pressure ratio b: mean and standard deviation. ISO 6358 b of small
#: solenoid valves lies around 0.15-0.4 (the paper's 0.186). It decides b only where the log does
#: not: a valve that never chokes, or is never fully open, leaves b and C trading off, and
#: unregularised b ran to 0 with C 12 % high on a closed-loop log (benchmarks/fleet.py).
B_PRIOR, B_PRIOR_SD = 0.25, 0.1
#: Duty below which a sample does not count as "the valve was commanded open".
_OPEN_DUTY = 1e-6
#: A valve counts as fully open for its C and b only if the log holds it at duty 1 for this long
#: at a stretch [s]: a whole charge or vent (the identification run's last 1.5 s and more). A
#: closed-loop log has every valve at duty 1 in bursts of 0.01-0.28 s (benchmarks/fleet.py,
#: kind c), which left C and b ranges that missed the truth on 7 of 12 fleet plants.
FULL_OPEN_PIN_S = 0.5


@contextlib.contextmanager
def single_blas_thread() -> Iterator[None]:
    """Run the block with the BLAS libraries on one thread (threadpoolctl); restore after.

    The valve fit's linear algebra is on tall matrices of a dozen columns (the trust-region
    SVD of the Jacobian, about 18k x 11 on an identification run): a few milliseconds on one
    core. With a second BLAS thread on a shared 2-core machine, each call waited up to 90 ms
    for a busy core, which made the valve fit take 9 s instead of 3 s. On data/run.mcap the
    fit gives the same floats on one thread as on two (benchmarks/identify_speed.py). The
    thread count is process-wide: other threads doing BLAS meanwhile run single-threaded too.

    Yields
    ------
    None
    """
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def pwm_window(Ts: float, pwm_hz: float, lo: int = 8, hi: int = 60) -> int:
    """Window length (samples) closest to a whole number of PWM periods, within [lo, hi]."""
    period = 1.0 / pwm_hz
    best, best_err = lo, np.inf
    for w in range(lo, hi + 1):
        cycles = w * Ts / period
        err = abs(cycles - round(cycles)) / max(cycles, 1.0)
        if err < best_err - 1e-12:
            best, best_err = w, err
    return best


def longest_run(flags: np.ndarray) -> int:
    """Length of the longest run of True in ``flags``.

    Parameters
    ----------
    flags : ndarray of bool
        The samples.

    Returns
    -------
    int
        The most consecutive True samples (0 for none).
    """
    return max((b - a for a, b in true_runs(flags)), default=0)


def window_sandwich_sd(J: np.ndarray, r: np.ndarray, JtJ_inv: np.ndarray,
                       blocks: tuple[int, int], lag: int) -> np.ndarray:
    """Standard errors of a least-squares fit whose residuals are correlated in time and
    unequal in size: the Newey-West sandwich ``A S A``, ``A = (J^T J)^-1``, ``S`` the
    Bartlett-weighted sum of the score products ``J_t r_t r_s J_s^T`` for ``|t - s| <= lag``.

    Parameters
    ----------
    J : (n, k) array
        Jacobian of the residuals at the solution.
    r : (n,) array
        Residuals at the solution.
    JtJ_inv : (k, k) array
        ``(J^T J)^-1`` (or its pseudo-inverse).
    blocks : (int, int)
        Ends of the time-ordered runs of rows: rows ``[0, blocks[0])`` are one (chamber A's
        windows), ``[blocks[0], blocks[1])`` another (chamber B's); rows from ``blocks[1]`` on
        are independent (priors).
    lag : int
        Longest lag with weight (Bartlett: ``1 - l / (lag + 1)``).

    Returns
    -------
    (k,) array
        The standard errors.
    """
    J = np.asarray(J, dtype=float)
    g = J * np.asarray(r, dtype=float)[:, None]
    S = g.T @ g
    for lo, hi in ((0, blocks[0]), (blocks[0], blocks[1])):
        gb = g[lo:hi]
        for lg in range(1, min(lag + 1, hi - lo)):
            G = gb[lg:].T @ gb[:-lg]
            S += (1.0 - lg / (lag + 1.0)) * (G + G.T)
    cov = JtJ_inv @ S @ JtJ_inv
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


class ValveIdentifier(Identifier):
    """C and b per valve, the leak, D_a, D_b and the PWM curves (one per valve).

    Parameters
    ----------
    knots : array, optional
        Duty knots of the curves (default :func:`~.valve_curves.default_knots`).
    iterations : int
        Alternations between the NLS and the QP.
    smooth : float
        Weight of the curvature penalty of the QP, relative to the data.
    stride : int
        Window start every ``stride`` samples (windows overlap).
    smooth_window : int
        Savitzky-Golay window (samples) of the pressures inside the flow terms.
    equilibrium_band : float
        Windows where an open valve has less than this across it are left out [Pa].
    varying_weight, partial_weight : float
        Weights of windows whose duties change inside the window, and of windows at a steady
        partial duty, relative to windows with the chamber's valves fully open or shut (see
        ``_prepare``).
    loss, f_scale : str, float
        Robust loss of the NLS and its scale [kPa] (``scipy.optimize.least_squares``): windows
        spoiled by what the averaged model lacks (valve delays at duty steps) weigh less.
    timing : bool
        Run the timing stage (module docstring); it is adopted only if it fits better.
    allow_unopened : bool
        Fit the other valves when one is never commanded open (a protocol run cut short),
        instead of raising; that valve's C and b are then not identified (``unopened_``).

    Attributes
    ----------
    C_, b_ : ndarray (4,)
        [m^3/(s Pa)], [-] of a_in, a_out, b_in, b_out.
    C_std_, b_std_ : ndarray (4,)
        Standard errors (Gauss-Newton, inflated by the window overlap).
    leak_C_ : float
        Seal leak conductance [m^3/(s Pa)].
    D_, D_std_ : ndarray (2,)
        Constant pressure-rate terms D_a, D_b [Pa/s] (θ5, θ6 of the paper) and their standard
        errors, from windows with the chamber's valves shut where the log has them.
    knots_, curves_ : ndarray
        Duty knots (K,) and the effective open fraction of each valve at them (4, K).
    curve_ : ndarray (K,)
        The mean curve (contract 3's top-level ``pwm``; each valve's is ``valves.<v>.pwm``).
    residual_std_ : ndarray (2,)
        RMS window residual of chambers A and B [Pa].
    D_closed_ : (bool, bool)
        Whether D_a, D_b came from stretches with the chamber's valves shut (else from the NLS,
        where they absorb flow-model error too).
    D_max_ : ndarray (2,)
        Largest |window residual| / window time, a bound on the fast-changing terms [Pa/s].
    window_ : int
        Window length [samples].
    max_duty_ : ndarray (4,)
        Highest duty each valve was commanded in the fitted part.
    full_open_s_ : ndarray (4,)
        Longest stretch of consecutive fitted samples each valve was commanded duty 1 [s]
        (compared with :data:`FULL_OPEN_PIN_S`).
    ratios_ : ndarray (N-1, 4)
        Open fraction of each valve in each sample used by the final fit (the PWM curves', or
        the exact opening of the timing stage).
    timing_ : tuple of Timing or None
        Delays and minimum pulse per valve from the timing stage (None: not adopted).
    min_pulse_range_ : list of (float, float) or None
        Per valve, the minimum pulses the timing stage cannot tell apart
        (:func:`~.valve_timing.min_pulse_range`) [s]; None without the timing stage.
    phase_ : float
        Carrier time at the log's first sample found by the timing stage [s].
    timing_rss_ : (float, float)
        Weighted residual sum of squares of the timing stage and of the averaged model
        [kPa^2].
    unopened_ : ndarray of bool (4,)
        Valves never commanded open in the fitted part (only with ``allow_unopened``).
    onsets_ : list of Onset or None
        Per valve, the delay from a full-opening command to the chamber pressure's response in
        the fast logs given to :meth:`fit` (:func:`~.valve_onsets.step_onsets`): the timing
        stage holds each valve's opening delay plus the loop delay inside its range. None
        where the logs have no such edges.
    """

    def __init__(self, knots: np.ndarray | None = None, iterations: int = 3,
                 smooth: float = 1e-4, stride: int = 2, smooth_window: int = 9,
                 equilibrium_band: float = 3.0e3, loss: str = "linear",
                 f_scale: float = 1.0, varying_weight: float = 0.1,
                 partial_weight: float = 0.3, timing: bool = True,
                 allow_unopened: bool = False) -> None:
        self.knots = knots
        self.iterations = iterations
        self.smooth = smooth
        self.stride = stride
        self.smooth_window = smooth_window
        self.equilibrium_band = equilibrium_band
        self.loss = loss
        self.f_scale = f_scale
        self.varying_weight = varying_weight
        self.partial_weight = partial_weight
        self.timing = timing
        self.allow_unopened = allow_unopened

    # -- per-sample terms ----------------------------------------------------------------------
    def _prepare(self, d: Dataset, mask: np.ndarray) -> None:
        r = d.rig
        self._nRT = r.n * r.R * r.T0
        self._u = d.u[:-1]
        self._mask_samples = mask[:-1] & mask[1:]
        Va, Vb = d.volumes()
        pa, pb, ps = d.p_a, d.p_b, d.p_s
        self._pa_raw, self._pb_raw = pa, pb
        # Eq. (7) is steep near p_d = p_u: measured pressures would turn sensor noise into large
        # spurious flows there, so the flow terms use smoothed pressures (Savitzky-Golay, no
        # lag); the window increments on the left-hand side stay raw.
        sa = savgol_filter(pa, self.smooth_window, 2)
        sb = savgol_filter(pb, self.smooth_window, 2)
        ss = savgol_filter(ps, 4 * self.smooth_window + 1, 1)
        self._pa = 0.5 * (sa[1:] + sa[:-1])
        self._pb = 0.5 * (sb[1:] + sb[:-1])
        self._ps = 0.5 * (ss[1:] + ss[:-1])
        self._Va = 0.5 * (Va[1:] + Va[:-1])
        self._Vb = 0.5 * (Vb[1:] + Vb[:-1])
        self._vol_a = -r.n * self._pa * np.diff(Va) / self._Va
        self._vol_b = -r.n * self._pb * np.diff(Vb) / self._Vb
        self._p0 = r.p0
        self._T0 = r.T0
        self._flow = PortFlows([(self._ps, self._pa), (self._pa, r.p0), (self._ps, self._pb),
                                (self._pb, r.p0), (self._pa, self._pb)], r.T0)
        self._no_leak = np.zeros_like(self._pa)
        self._Ts = d.Ts
        w = pwm_window(d.Ts, r.pwm_hz)
        #: samples a duty change can take to act fully (a PWM period plus the valve delays)
        self._lookback = int(np.ceil((1.0 / r.pwm_hz + 0.01) / d.Ts))
        starts = np.arange(0, d.n - 1 - w, self.stride)
        # windows where an open valve is near equilibrium (|p_u - p_d| < equilibrium_band)
        # carry sensor noise, not information on C and b
        band = self.equilibrium_band
        u = self._u
        near_a = ((u[:, 0] > 0) & (np.abs(self._ps - self._pa) < band)) \
            | ((u[:, 1] > 0) & (np.abs(self._pa - r.p0) < band))
        near_b = ((u[:, 2] > 0) & (np.abs(self._ps - self._pb) < band)) \
            | ((u[:, 3] > 0) & (np.abs(self._pb - r.p0) < band))
        self._k0, self._k1, self._dp, self._wt = [], [], [], []
        for ch, (near, p) in enumerate(((near_a, pa), (near_b, pb))):
            bad = np.concatenate([[0], np.cumsum(near | ~mask[:-1])])
            k0 = starts[(bad[starts + w] - bad[starts]) == 0]
            # The averaged model r(u) is exact while a chamber's duties are steady over the
            # window; where they change from sample to sample the pulses depend on the carrier
            # phase, which a 4 ms log does not show. Such windows weigh ``varying_weight``.
            # (a duty step into the window's first sample counts too: the valves answer it
            # with their delays, inside that sample)
            # ... and so does one within a PWM period before it: in latched mode a new duty
            # acts only from the next period start)
            uc = u[:, 2 * ch:2 * ch + 2]
            chg = np.any(np.abs(np.diff(uc, axis=0)) > 1e-9, axis=1)
            cum = np.concatenate([[0], np.cumsum(chg)])
            first = np.maximum(k0 - self._lookback, 0)
            steady = (cum[k0 + w - 1] - cum[first]) == 0
            # windows with the valves fully open or shut need no curve at all (r(0) = 0 and
            # r(1) = 1): they pin C and b; steady partial duties weigh ``partial_weight``
            full = np.all((uc[k0] < 1e-9) | (uc[k0] > 1.0 - 1e-9), axis=1)
            self._k0.append(k0)
            self._k1.append(k0 + w)
            self._dp.append(p[k0 + w] - p[k0])
            self._wt.append(np.where(steady, np.where(full, 1.0, self.partial_weight),
                                     self.varying_weight))
        self.window_ = w
        K = len(self.knots_)
        # windowed interpolation weights: sum over a window of coef_k * W(u_k)
        self._Wu = [interp_weights(self._u[:, i], self.knots_) for i in range(4)]
        self._K = K

    def _flows(self, C: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
        """Fully-open flows of each valve per sample, signed into its chamber [kg/s]."""
        flow = self._flow
        return [flow(A_IN, C[0], b[0]), -flow(A_OUT, C[1], b[1]), flow(B_IN, C[2], b[2]),
                -flow(B_OUT, C[3], b[3])]

    def _window_sum(self, term: np.ndarray, chamber: int) -> np.ndarray:
        c = np.cumsum(term, axis=0)
        c = np.concatenate([np.zeros((1, *c.shape[1:])), c])
        return c[self._k1[chamber]] - c[self._k0[chamber]]

    def _knot_window_sum(self, gain: np.ndarray, weights: np.ndarray, chamber: int
                         ) -> np.ndarray:
        """``_window_sum(gain[:, None] * weights, chamber)``, the same floats
        (:func:`~.valve_residuals.knot_window_sums`)."""
        out = np.empty((len(self._k0[chamber]), weights.shape[1]))
        knot_window_sums(np.ascontiguousarray(gain, dtype=float), weights, self._k0[chamber],
                         self._k1[chamber], out)
        return out

    def _ratios(self, curves: np.ndarray) -> np.ndarray:
        """Open fraction per sample and valve from the PWM curves, (N-1, 4)."""
        return np.column_stack([np.interp(self._u[:, i], self.knots_, curves[i])
                                for i in range(4)])

    def _chamber_residuals(self, ch: int, C: np.ndarray, b: np.ndarray, leak: float,
                           D: float, ratios: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Window residuals of chamber ``ch`` [kPa] for the valves' C, b (that chamber's two),
        the leak, D and the open fraction per sample."""
        i = 2 * ch
        phi_in = self._flow(2 * ch, C[0], b[0])  # A_IN or B_IN
        phi_out = self._flow(2 * ch + 1, C[1], b[1])  # A_OUT or B_OUT, out of the chamber
        if ch == 0:
            V, vol, sgn = self._Va, self._vol_a, -1.0
        else:
            V, vol, sgn = self._Vb, self._vol_b, 1.0
        L = self._flow(LEAK, leak, 0.0) if leak > 0 else self._no_leak
        out = np.empty(len(self._k0[ch]))
        chamber_window_residuals(self._Ts * self._nRT, V, ratios[:, i], phi_in, ratios[:, i + 1],
                                 phi_out, sgn, L, vol, self._Ts * D, self._k0[ch],
                                 self._k1[ch], self._dp[ch], np.asarray(weights, dtype=float),
                                 out)
        return out

    def _residuals(self, theta: np.ndarray, ratios: np.ndarray,
                   weights: Sequence[np.ndarray] | None = None) -> np.ndarray:
        C = theta[0:8:2] * _C_UNIT
        b = theta[1:8:2]
        leak = theta[8] * _LEAK_UNIT
        wt = self._wt if weights is None else weights
        res = np.concatenate([
            *(self._chamber_residuals(ch, C[2 * ch:2 * ch + 2], b[2 * ch:2 * ch + 2], leak,
                                      theta[9 + ch] * _D_UNIT, ratios, wt[ch])
              for ch in range(2)),
            self._b_scale * (b - B_PRIOR) / B_PRIOR_SD])
        self._last_eval = (theta.copy(), ratios, weights, self._b_scale, res)
        return res

    def _residuals_at(self, theta: np.ndarray, ratios: np.ndarray,
                      weights: Sequence[np.ndarray] | None = None) -> np.ndarray:
        """:meth:`_residuals` at ``theta``: those of the evaluation just made there, if it
        was (same ratios, weights and b-prior scale), else evaluated."""
        last = getattr(self, "_last_eval", None)
        if (last is not None and last[1] is ratios and last[2] is weights
                and last[3] == self._b_scale and np.array_equal(last[0], theta)):
            return last[4]
        return self._residuals(theta, ratios, weights)

    def _jacobian(self, lo: np.ndarray, hi: np.ndarray) -> Callable[..., np.ndarray] | str:
        """The Jacobian of :meth:`_residuals` for ``least_squares`` with these bounds: the
        numbers of its ``jac='2-point'``, the two chambers' parameters perturbed together
        (:func:`~.valve_jacobian.grouped_jacobian`), the residuals at the point from the
        evaluation ``least_squares`` just made there."""
        groups = valve_fit_groups(len(self._k0[0]), len(self._k0[1]))
        return grouped_jacobian(self._residuals, self._residuals_at, groups, lo, hi)

    def _least_squares(self, theta: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                       ratios: np.ndarray, weights: Sequence[np.ndarray] | None = None,
                       **kw: Any) -> Any:
        """``least_squares`` of :meth:`_residuals` (bounded trf, ``x_scale='jac'``) with the
        Jacobian of :meth:`_jacobian`; ``kw`` go to ``least_squares``."""
        self._last_eval = None
        try:
            return least_squares(self._residuals, theta, jac=self._jacobian(lo, hi),
                                 bounds=(lo, hi), args=(ratios, weights), x_scale="jac",
                                 method="trf", **kw)
        finally:
            self._last_eval = None

    def _fit_curves(self, C: np.ndarray, b: np.ndarray, leak: float, D: np.ndarray) -> np.ndarray:
        phi = self._flows(C, b)
        L = self._flow(LEAK, leak, 0.0) if leak > 0 else 0.0
        curves = np.zeros((4, self._K))
        for ch, (i, j, V, vol, Dc, sgn) in enumerate((
                (0, 1, self._Va, self._vol_a, D[0], -1.0),
                (2, 3, self._Vb, self._vol_b, D[1], 1.0))):
            dp = self._dp[ch]
            g = self._Ts * self._nRT / V
            known = self._window_sum(vol + self._Ts * Dc + g * sgn * L, ch)
            Ai = self._knot_window_sum(g * phi[i], self._Wu[i], ch)
            Aj = self._knot_window_sum(g * phi[j], self._Wu[j], ch)
            curves[i], curves[j] = chamber_curves(Ai, Aj, dp - known, self._wt[ch], self.smooth,
                                                  self._path, "AB"[ch])
        return curves

    def _closed_stretches(self) -> tuple[list[float | None], list[float], float | None, float]:
        """D_a, D_b [Pa/s], the leak conductance and standard errors, from shut valves
        (:func:`~.valve_leak.closed_stretches`)."""
        return closed_stretches(self._u, self._mask_samples, self._lookback, self.window_,
                                self._Ts, self._nRT,
                                ((self._Va, self._vol_a, self._pa_raw),
                                 (self._Vb, self._vol_b, self._pb_raw)),
                                self._flow(LEAK, 1.0, 0.0))

    @staticmethod
    def _fix(theta: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             fixed: dict[int, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hold parameters (index -> scaled value) within a negligible bound of a value."""
        theta, lo, hi = theta.copy(), lo.copy(), hi.copy()
        for i, value in fixed.items():
            theta[i] = value
            lo[i] = value - 1e-6
            hi[i] = value + 1e-6
        return theta, lo, hi

    def fit(self, data: Dataset, mask: np.ndarray | None = None,
            fast: Sequence[Dataset] = ()) -> ValveIdentifier:
        """Fit on the samples where ``mask`` is True (default: all).

        ``fast``: logs of the same rig at their own sampling period, several samples per PWM
        period (an identification run's 0.5 ms), whose full-opening edges bound each valve's
        opening delay in the timing stage (``onsets_``).

        Raises
        ------
        IdentificationError
            A valve is never commanded open, so its C and b are not identifiable.

        Notes
        -----
        Runs with the BLAS on one thread (:func:`single_blas_thread`).
        """
        with single_blas_thread():
            return self._fit(data, mask, fast)

    def _fit(self, data: Dataset, mask: np.ndarray | None,
             fast: Sequence[Dataset] = ()) -> ValveIdentifier:
        """:meth:`fit`, with the BLAS threads as the caller set them."""
        self._path = data.path
        self._fast = list(fast)
        self.onsets_: list[Onset | None] = [None] * 4
        mask = np.ones(data.n, dtype=bool) if mask is None else mask
        self.unopened_ = np.array([not np.any(data.u[mask, i] > _OPEN_DUTY) for i in range(4)])
        if self.allow_unopened and self.unopened_.all():
            raise IdentificationError(
                data.path, "no valve is ever commanded open in the fitted part of the log: "
                "there is nothing to identify the valves from" + data.stop_note)
        for i, name in enumerate(VALVES):
            u = data.u[mask, i]
            if self.unopened_[i] and self.allow_unopened:
                self.notes_ = [*getattr(self, "notes_", []),
                               f"valve {name} is never commanded open: its C and b are not "
                               f"identified"]
                continue
            if not np.any(u > _OPEN_DUTY):
                raise IdentificationError(
                    data.path, f"valve {name} is never commanded open in the fitted part of the "
                    f"log: its C and b are not identifiable; record an identification run "
                    f"(simulate --experiment identification, or the same protocol on the rig)")
            if not np.any(u >= 0.999):
                self.notes_ = [*getattr(self, "notes_", []),
                               f"valve {name} never runs at full duty: its C and the top of its "
                               f"PWM curve are only separable through the curve's shape"]
        self.notes_ = list(getattr(self, "notes_", []))
        self.max_duty_ = np.array([float(np.max(data.u[mask, i])) for i in range(4)])
        self.full_open_s_ = np.array([longest_run(mask & (data.u[:, i] >= 0.999)) * data.Ts
                                      for i in range(4)])
        self.knots_ = default_knots() if self.knots is None else np.asarray(self.knots, float)
        self._prepare(data, mask)
        for chamber, k0 in zip("AB", self._k0, strict=True):
            if len(k0) == 0:
                raise IdentificationError(
                    data.path, f"chamber {chamber} has no window of whole PWM periods in the "
                    f"fitted part of the log: its valves cannot be identified; record its valve "
                    f"tests (record --experiment identification --segments "
                    f"valves:{chamber.lower()}) and identify both logs")
        curves = np.tile(self.knots_, (4, 1))  # start: r(u) = u
        theta = np.array([8.0, 0.3, 8.0, 0.3, 8.0, 0.3, 8.0, 0.3, 0.0, 0.0, 0.0])
        lo = np.array([0.01, 0.0, 0.01, 0.0, 0.01, 0.0, 0.01, 0.0, 0.0, -1e4, -1e4])
        hi = np.array([1000.0, 0.9, 1000.0, 0.9, 1000.0, 0.9, 1000.0, 0.9, 1000.0, 1e4, 1e4])
        sol = None
        D, D_sd, leak, leak_sd = self._closed_stretches()
        fixed = {9 + ch: D[ch] / _D_UNIT for ch in range(2) if D[ch] is not None}
        if leak is not None:
            fixed[8] = max(leak, 0.0) / _LEAK_UNIT
        theta, lo, hi = self._fix(theta, lo, hi, fixed)
        # the b prior weighs like one window residual of typical size (updated after a solve)
        self._b_scale = 1.0
        for _ in range(max(1, self.iterations)):
            sol = self._least_squares(theta, lo, hi, self._ratios(curves), loss=self.loss,
                                      f_scale=self.f_scale)
            theta = sol.x
            self._b_scale = float(np.sqrt(np.mean(sol.fun[:-4] ** 2)))
            C = theta[0:8:2] * _C_UNIT
            b = theta[1:8:2]
            curves = self._fit_curves(C, b, theta[8] * _LEAK_UNIT,
                                      np.array([theta[9], theta[10]]) * _D_UNIT)
        sol = self._least_squares(theta, lo, hi, self._ratios(curves), loss=self.loss,
                                  f_scale=self.f_scale)
        theta = sol.x
        self.timing_ = None
        self.min_pulse_range_: list[tuple[float, float]] | None = None
        #: the loop delay (every duty acting this long after its sample) and its range [s];
        #: None without the timing stage
        self.loop_delay_: float | None = None
        self.loop_delay_range_: tuple[float, float] | None = None
        self.ratios_ = self._ratios(curves)
        if self.timing:
            exact = self._fit_timing(data, theta, lo, hi, curves)
            if exact is not None:
                sol, curves, self.ratios_ = exact
                theta = sol.x
        self.theta_ = theta
        self.C_ = theta[0:8:2] * _C_UNIT
        self.b_ = theta[1:8:2]
        self.leak_C_ = max(float(theta[8] * _LEAK_UNIT), 0.0)  # bound slack can leave -1e-17
        self.D_ = np.array([theta[9], theta[10]]) * _D_UNIT
        self.D_std_ = np.array(D_sd, dtype=float)
        self.D_closed_ = tuple(d is not None for d in D)
        self.leak_std_ = leak_sd
        self.curves_ = curves
        self.curve_ = np.maximum.accumulate(curves.mean(axis=0))
        res = sol.fun[:-4] * 1e3  # the windows (the last four are the b prior)
        na = len(self._k0[0])
        self.residual_std_ = np.array([np.sqrt(np.mean(res[:na] ** 2)),
                                       np.sqrt(np.mean(res[na:] ** 2))])
        wt = self.window_ * data.Ts
        self.D_max_ = np.array([np.max(np.abs(res[:na])), np.max(np.abs(res[na:]))]) / wt
        # Gauss-Newton standard errors; overlapping windows share samples, so inflate by
        # sqrt(window / stride) (the number of windows each sample appears in). The windows'
        # residuals are not alike, though: where the averaged flow model misses most (a valve's
        # charges through a bent curve) they are larger and correlated over more than the
        # overlap, and there the Gauss-Newton error is too small. A valve's C and b errors are
        # the larger of it and the Newey-West sandwich's (window_sandwich_sd), unless the fit
        # put its b at a bound: that estimate is no normal variate, and its C and b describe
        # the valve with what bends its curve in series (the note below), whose fitted ranges
        # tune does better with (docs/identification.md, "Standard errors").
        J = sol.jac
        dof = max(1, len(res) - len(theta))
        s2 = float(np.sum(sol.fun**2)) / dof
        try:
            JtJ_inv = np.linalg.pinv(J.T @ J)
            cov = JtJ_inv * s2 * (self.window_ / self.stride)
        except np.linalg.LinAlgError:  # pragma: no cover
            JtJ_inv = None
            cov = np.full((len(theta), len(theta)), np.nan)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        sd_hw = np.zeros_like(sd)
        if JtJ_inv is not None and len(sol.fun) == na + len(self._k0[1]) + 4:
            lag = 2 * int(np.ceil(self.window_ / self.stride))
            sd_hw = window_sandwich_sd(J, sol.fun, JtJ_inv, (na, na + len(self._k0[1])), lag)
        for ch in range(2):
            if not np.isfinite(self.D_std_[ch]):  # no closed-valve stretch: D from the NLS,
                # where it also absorbs what the flow model misses; its error is at least |D|
                self.D_std_[ch] = max(sd[9 + ch] * _D_UNIT, abs(self.D_[ch]))
                self.notes_.append(
                    f"D_{'ab'[ch]}n: chamber {'AB'[ch]}'s valves are never all shut for a "
                    f"whole window, so its constant term is not separated from flow-model "
                    f"error; its bound is widened to cover zero")
        self.C_std_ = sd[0:8:2] * _C_UNIT
        self.b_std_ = sd[1:8:2]
        for i, name in enumerate(VALVES):
            at_bound = self.b_[i] < 1e-3 or self.b_[i] > lo[1] + hi[1] - 1e-3
            if not at_bound:
                self.C_std_[i] = max(self.C_std_[i], sd_hw[2 * i] * _C_UNIT)
                self.b_std_[i] = max(self.b_std_[i], sd_hw[2 * i + 1])
            if at_bound and self.full_open_s_[i] >= FULL_OPEN_PIN_S:
                self.notes_.append(
                    f"valve {name}: the fit put b at its bound ({self.b_[i]:.3g}) although the "
                    f"valve was held fully open for {self.full_open_s_[i]:.2g} s: those charges "
                    f"or vents follow ISO 6358's curve for no b, as when a line, fitting or "
                    f"filter in series with the valve, or a lagging pressure transmitter, bends "
                    f"them; model.yaml keeps the fitted C and b, which then describe the valve "
                    f"and what is in series with it together")
            elif at_bound or self.b_std_[i] > 0.1:
                self.notes_.append(
                    f"valve {name}: b is not identifiable from this log (estimate "
                    f"{self.b_[i]:.3g} ± {self.b_std_[i]:.2g}); it needs charges or vents "
                    f"through the fully open valve over a wide pressure range")
        self.fitted_ = True
        return self

    def _fit_timing(self, data: Dataset, theta: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    curves: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray] | None:
        """Refit C, b (and free D) with the exact opening of every valve in every sample.

        The valve timings, the carrier phase and a loop delay are searched
        (:func:`~.valve_timing.search_timings`), starting from the switching behaviour of the
        PWM curves just fitted, each valve's opening delay within its step onset's range where
        the fast logs show one (``onsets_``). Adopted when its residual (the windows weighted
        as for the averaged model, which favours the clean full-duty and steady windows where
        they exist) is below the averaged model's; then returns the final least-squares
        solution, the PWM curves of the timings found and the open fractions per sample, else
        None.
        """
        period = 1.0 / data.rig.pwm_hz
        wt = self._wt
        base = self._least_squares(theta, lo, hi, self._ratios(curves), wt)
        rss_avg = float(np.sum(base.fun**2))
        frac = OpenFractions(data.rig, data.u, data.Ts)
        start = []
        for i in range(4):
            sw = curve_switching(self.knots_, curves[i], period)
            start.append(Timing(sw["delay_on"], sw["delay_off"], sw["min_pulse"]))
        if self._fast:
            self._find_onsets(theta, timing_bounds(period)[1])
        leak = theta[8] * _LEAK_UNIT
        free_D = [hi[9 + ch] - lo[9 + ch] > 1e-3 for ch in range(2)]

        def cost_for(held: np.ndarray, b: np.ndarray) -> TimingCost:
            return self._timing_cost(frac, held, b, leak, free_D)

        def refit(x: np.ndarray, timings: Sequence[Timing], phase: float
                  ) -> tuple[np.ndarray, np.ndarray]:
            x = self._least_squares(x, lo, hi, frac(timings, phase)[:-1], wt).x
            return x, x[1:8:2].copy()

        found = search_timings(frac, start, self.onsets_, theta, theta[1:8:2].copy(), cost_for,
                               refit)
        self._phase_costs = found.phase_costs
        self.loop_delay_costs_ = found.loop_delay_costs
        ratios = frac(found.timings, found.phase)[:-1]
        sol = self._least_squares(found.theta, lo, hi, ratios, wt)
        rss = float(np.sum(sol.fun**2))
        self.timing_rss_ = (rss, rss_avg)
        self.timing_tried_ = (found.timings, found.phase)
        if not rss < rss_avg:
            self.notes_.append(
                f"valves: the exact valve opening per sample (timings searched) fits the "
                f"chamber pressures no better than the averaged PWM curve (residual "
                f"{rss:.3g} vs {rss_avg:.3g} kPa²); the averaged model is kept")
            return None
        self.timing_ = found.timings
        self.min_pulse_range_ = self._min_pulse_ranges(
            cost_for(found.theta, found.theta[1:8:2].copy()), found.timings, found.phase, period)
        self.phase_ = found.phase
        self.loop_delay_ = found.loop_delay
        self.loop_delay_range_ = found.loop_delay_range
        new_curves = np.array([effective_open_fraction(self.knots_, period, t.delay_on,
                                                       t.delay_off, t.min_pulse)
                               for t in found.timings])
        return sol, new_curves, ratios

    def _min_pulse_ranges(self, cost: TimingCost, timings: Sequence[Timing], phase: float,
                          period: float) -> list[tuple[float, float]]:
        """Per valve, the minimum pulses the chamber fit cannot tell from the one found
        (:func:`~.valve_timing.min_pulse_range`), with a note where that range is wide enough
        for tune to draw (:data:`~pneutune.control.sim.model_box.MIN_PULSE_SPAN`).

        Inside the range the log does not say whether a pulse opens the valve: model.yaml
        keeps the minimum pulse found (the PWM curve's dead-zone step, which the controller
        carries) and writes the range, and ``tune`` draws plants across it, so a controller is
        scored both where its smallest pulses open the valve and where they do not.
        """
        step = MIN_PULSE_STEP * period
        ranges = []
        for i, tm in enumerate(timings):
            lo, hi = min_pulse_range(cost, timings, phase, i, step)
            ranges.append((lo, hi))
            if hi - lo > MIN_PULSE_SPAN:
                self.notes_.append(
                    f"valve {VALVES[i]}: the chamber fit cannot tell a minimum pulse of "
                    f"{lo * 1e3:.2f} ms from one of {hi * 1e3:.2f} ms (the log has few or no "
                    f"pulses of a length between, or lags blur where they stop opening the "
                    f"valve); the model keeps {tm.min_pulse * 1e3:.2f} ms and tune draws "
                    f"plants across the range")
        return ranges

    def _find_onsets(self, theta: np.ndarray, max_delay: float) -> None:
        """``onsets_`` from the fast logs at the averaged model's C and b, and a note."""
        self.onsets_ = step_onsets(self._fast, theta[0:8:2] * _C_UNIT, theta[1:8:2], max_delay)
        seen = [f"{VALVES[i]} {on.delay * 1e3:.2f} ms ({on.low * 1e3:.2f}-"
                f"{on.high * 1e3:.2f}, {on.edges} edges)"
                for i, on in enumerate(self.onsets_) if on is not None]
        if seen:
            self.notes_.append(
                f"valves: the chamber pressure follows a full-opening command after "
                f"{'; '.join(seen)}: the loop delay plus the valve's opening delay, "
                f"armature and line lags and the transmitter's lag; the timing search "
                f"keeps each valve's opening delay plus the loop delay in that range")

    def _timing_cost(self, frac: OpenFractions, theta: np.ndarray, b: np.ndarray, leak: float,
                     free_D: Sequence[bool]) -> TimingCost:
        """The timing search's chamber cost for fixed b: C (and a free D) by linear least
        squares, since the window sums are linear in them (:class:`.valve_timing.TimingCost`:
        each valve switched alone, its window sums kept, repeated candidates looked up). The
        leak [m^3/(s Pa)] and, where not ``free_D``, D from ``theta`` enter as known terms."""
        wt = self._wt
        unit = self._flows(np.ones(4), b)
        L = self._flow(LEAK, leak, 0.0) if leak > 0 else 0.0
        gains, targets, extra = [], [], []
        for ch, (V, vol, sgn) in enumerate(((self._Va, self._vol_a, -1.0),
                                            (self._Vb, self._vol_b, 1.0))):
            g = self._Ts * self._nRT / V
            known = vol + g * sgn * L
            cols = []
            if free_D[ch]:
                cols.append(self._window_sum(np.full_like(vol, self._Ts), ch) * wt[ch])
            else:
                known = known + self._Ts * theta[9 + ch] * _D_UNIT
            gains.append(g)
            targets.append((self._dp[ch] - self._window_sum(known, ch)) * wt[ch])
            extra.append(cols)
        return TimingCost(frac, list(zip(self._k0, self._k1, strict=True)), gains, unit,
                          targets, wt, extra)

    def window_increments(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per chamber: the measured and the modelled pressure increments over the fit's
        windows [Pa], and the windows' weights."""
        self._require_fitted()
        res = self._residuals(self.theta_, self.ratios_, [np.ones_like(w) for w in self._wt])
        res = res[:-4]  # the b prior
        na = len(self._k0[0])
        out = []
        for ch, part in enumerate((res[:na], res[na:])):
            out.append((self._dp[ch], self._dp[ch] + part * 1e3, self._wt[ch]))
        return out

    def ratio(self, duty: np.ndarray | float, valve: int | None = None) -> np.ndarray:
        """Effective open fraction at ``duty`` (one valve's curve, or the mean curve)."""
        self._require_fitted()
        curve = self.curve_ if valve is None else self.curves_[valve]
        return np.interp(duty, self.knots_, curve)

    def switching(self, period: float, valve: int | None = None) -> dict[str, float]:
        """Switching behaviour of a valve (or equivalent to the mean curve).

        With the timing stage adopted (``timing_``), a valve's searched delays and minimum pulse.
        Otherwise from the PWM curve (:func:`~.valve_curves.curve_switching`).
        """
        self._require_fitted()
        if getattr(self, "timing_", None) is not None and valve is not None:
            t = self.timing_[valve]
            return {**t.as_dict(), "offset": (t.delay_off - t.delay_on) / period,
                    "dead_zone": t.min_pulse / period}
        return curve_switching(self.knots_, self.curve_ if valve is None
                               else self.curves_[valve], period)

