"""Valve timing from a log: which part of each sample each valve was open.

A log holds the duty written at each sample, not the valve's opening. Where the duties are
steady over a PWM period the averaged PWM curve r(u) stands in for the opening (what
:class:`~pneutune.identify.valves.ValveIdentifier` does first). Where they change every sample,
as in any closed-loop log, it does not: a duty written 4 ms into a 16.7 ms period acts on what
is left of that period (``rig.pwm_update: immediate``) or from the next period start
(``latched``), so the opening inside each sample depends on the carrier phase, the duties
before and the valve's delays and minimum pulse. A closed-loop log fitted with r(u) gave C off
by 15-50 % (benchmarks/fleet.py).

The opening per sample is computed here exactly as the simulated rig switches its valves
(:func:`pneutune.control.plant.valves.open_fractions`: the edge-aligned PWM carrier at
``rig.pwm_hz``,
the update mode, delays and the minimum pulse), given three numbers per valve
(``delay_on``, ``delay_off``, ``min_pulse``) and the carrier phase at the log's first sample.
Those are found by search (:func:`coordinate_search`, :func:`phase_search`) on the chamber
equations, whose fit is very sensitive to them: on a closed-loop log of a simulated rig, 0.3 ms
off in one delay triples the residual, and a wrong carrier phase multiplies it by 15-1000.

The search evaluates about a thousand candidates, each changing one valve (or the phase). Its
cost (:class:`TimingCost`) therefore switches each valve alone
(:func:`pneutune.control.plant.valves.valve_open_fractions`, the same switching as
:func:`~pneutune.control.plant.valves.open_fractions`, which the valves do not interact in),
keeps each valve's window sums, and looks up repeated candidates (a fifth of them on
data/run.mcap): there, about 0.6 ms per candidate instead of 5 ms for the four valves together,
and the same timings, phase and fit as with the four valves: checked decision by decision on
four logs, a candidate's two costs differ by at most 1e-12 of its value, while no two costs the
search compared came closer than 1e-6.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pneutune.control.contracts.plant import PlantConfig, RigConfig
from pneutune.control.numba_cache import njit
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import P_DOFF, P_DON, P_MINP, pack_plant
from pneutune.control.plant.valves import open_fractions, valve_open_fractions

from .bounds import Z
from .valve_onsets import Onset

#: Longest delay searched, in PWM periods (the plant allows up to 4).
MAX_DELAY_PERIODS = 0.5
#: Relative cost advantage another carrier phase needs over phase 0 (:func:`phase_search`).
PHASE_TOLERANCE = 0.1
#: Loop delays scanned, evenly over [0, Ts] (0.5 ms apart at Ts = 4 ms).
LOOP_DELAY_POINTS = 9
#: Relative cost advantage a loop delay needs over none, and the tolerance of its range.
LOOP_DELAY_TOLERANCE = 0.05
#: Step of the minimum-pulse profile (:func:`min_pulse_range`), in PWM periods (0.042 ms at
#: 60 Hz).
MIN_PULSE_STEP = 1.0 / 400
#: Slack around a valve's step-onset range when it bounds the opening delay [s] (the onset grid
#: step, and the carrier-timed opening of the averaged model, are coarser than the search).
ONSET_MARGIN = 2.5e-4


@dataclass(frozen=True)
class Timing:
    """Switching behaviour of one valve [s] (contract 2's ``delay_on``, ``delay_off``,
    ``min_pulse``)."""

    delay_on: float
    delay_off: float
    min_pulse: float

    def as_dict(self) -> dict[str, float]:
        """The plant.yaml / model.yaml keys."""
        return {"delay_on": self.delay_on, "delay_off": self.delay_off,
                "min_pulse": self.min_pulse}


class OpenFractions:
    """Open fraction of every valve in every sample of a log, for given timings and phase.

    Parameters
    ----------
    rig : RigConfig
        The log's rig (PWM frequency and update mode).
    duties : ndarray, (N, 4)
        Commanded duties per sample.
    Ts : float
        Sampling period of ``duties`` [s].
    """

    def __init__(self, rig: RigConfig, duties: np.ndarray, Ts: float) -> None:
        self.rig = rig
        self.duties = np.ascontiguousarray(duties, dtype=np.float64)
        self.Ts = float(Ts)
        #: every duty acts this long after its sample [s] (a loop delay: IO, not the valves')
        self.write_delay = 0.0
        self._p = pack_plant(PlantConfig(rig=rig)).vec.copy()
        self._out = np.zeros_like(self.duties)
        self._columns = [np.ascontiguousarray(self.duties[:, i]) for i in range(4)]

    def __call__(self, timings: Sequence[Timing], phase: float) -> np.ndarray:
        """(N, 4) open fractions, valve order a_in, a_out, b_in, b_out.

        Parameters
        ----------
        timings : sequence of 4 Timing
        phase : float
            Carrier time at the first sample, in [0, 1/pwm_hz) [s].
        """
        if self.write_delay > 0.0:  # valve by valve (they do not interact)
            return np.column_stack([self.valve(i, [tm], phase)[0]
                                    for i, tm in enumerate(timings)])
        p = self._p
        for i, tm in enumerate(timings):
            p[P_DON + i] = tm.delay_on
            p[P_DOFF + i] = tm.delay_off
            p[P_MINP + i] = min(tm.min_pulse, tm.delay_on)
        s = plant.initial_state(p, 0.5 * (self.rig.x_min + self.rig.x_max), self.rig.p0,
                                self.rig.p0)
        open_fractions(p, s, self.duties, float(phase), self.Ts, self._out)
        return self._out.copy()

    def valve(self, i: int, timings: Sequence[Timing], phase: float) -> np.ndarray:
        """Open fractions of valve ``i`` alone, for several candidate timings, in one call.

        The valve switches as in :meth:`__call__` (the valves do not interact); only the sums
        of each sample's open time round differently there, on the finer grid of all four
        valves' switching events (a few 1e-12 of the fraction on data/run.mcap).

        Parameters
        ----------
        i : int
            Valve index (a_in, a_out, b_in, b_out).
        timings : sequence of Timing
            The candidates (M of them).
        phase : float
            Carrier time at the first sample, in [0, 1/pwm_hz) [s].

        Returns
        -------
        ndarray, (M, N)
            Open fraction of every sample per candidate, 0..1.
        """
        tm = np.array([[t.delay_on, t.delay_off, min(t.min_pulse, t.delay_on)]
                       for t in timings], dtype=np.float64).reshape(-1, 3)
        phases = np.full(tm.shape[0], float(phase))
        out = np.empty((tm.shape[0], self.duties.shape[0]))
        valve_open_fractions(self._p, self._columns[i], tm, phases, self.Ts, out,
                             self.write_delay)
        return out


class TimingCost:
    """The timing search's cost of a chamber, evaluated valve by valve.

    For valve openings r_i per sample (:meth:`OpenFractions.valve`), chamber ``ch``'s window
    equations are linear in its two conductances and, where free, its constant term: the cost
    is the residual sum of squares [kPa^2] of the weighted windows after those are solved by
    linear least squares (the column of valve i holds the sums of ``gain * r_i * flow_i`` over
    the chamber's windows, times the window weights). A step of the search changes one valve,
    so each valve's column is kept per (valve, timing, phase) and only the changed one is
    recomputed; a candidate evaluated before is looked up.

    Parameters
    ----------
    frac : OpenFractions
        The log's duties, rig and sampling period.
    windows : sequence of 2 (ndarray, ndarray)
        Per chamber, the first sample of each window and the sample after its last (indices
        into the N-1 sample intervals, as integers).
    gains : sequence of 2 ndarray, (N-1,)
        Per chamber, pressure change per unit mass flow over one sample [Pa s/kg].
    flows : sequence of 4 ndarray, (N-1,)
        Per valve, its fully open flow for unit conductance, signed into its chamber.
    targets : sequence of 2 ndarray
        Per chamber, the weighted window increments less the known terms [Pa].
    weights : sequence of 2 ndarray
        Per chamber, the window weights.
    extra : sequence of 2 lists of ndarray
        Per chamber, further weighted columns solved for with the conductances (a free
        constant term), after them.
    keep : int
        Valve columns kept (least recently used dropped).
    """

    def __init__(self, frac: OpenFractions, windows: Sequence[tuple[np.ndarray, np.ndarray]],
                 gains: Sequence[np.ndarray], flows: Sequence[np.ndarray],
                 targets: Sequence[np.ndarray], weights: Sequence[np.ndarray],
                 extra: Sequence[Sequence[np.ndarray]], keep: int = 64) -> None:
        self.frac = frac
        self._windows = [(np.ascontiguousarray(k0, dtype=np.int64),
                          np.ascontiguousarray(k1, dtype=np.int64)) for k0, k1 in windows]
        self._gains = [np.ascontiguousarray(g, dtype=np.float64) for g in gains]
        self._flows = [np.array(f, dtype=np.float64) for f in flows]  # writable copies
        self._targets, self._weights = list(targets), list(weights)
        self._extra = [list(cols) for cols in extra]
        self._keep = keep
        self._columns: OrderedDict[tuple[float, ...], np.ndarray] = OrderedDict()
        self._costs: dict[tuple[float, ...], float] = {}
        #: candidates evaluated, and those of them looked up
        self.evaluations = 0
        self.repeats = 0

    @staticmethod
    def _key(tm: Timing) -> tuple[float, float, float]:
        """What the switching depends on (the minimum pulse is capped at the opening delay)."""
        return float(tm.delay_on), float(tm.delay_off), float(min(tm.min_pulse, tm.delay_on))

    def windows(self, ch: int) -> int:
        """Number of chamber ``ch``'s windows that carry weight."""
        return int(np.count_nonzero(self._weights[ch]))

    def _column(self, i: int, tm: Timing, phase: float) -> np.ndarray:
        key = (i, *self._key(tm), phase, self.frac.write_delay)
        col = self._columns.get(key)
        if col is not None:
            self._columns.move_to_end(key)
            return col
        ch = i // 2
        r = self.frac.valve(i, [tm], phase)[0]
        k0, k1 = self._windows[ch]
        col = np.empty(k0.shape[0])
        _window_column(self._gains[ch], r, self._flows[i], k0, k1, self._weights[ch], col)
        self._columns[key] = col
        if len(self._columns) > self._keep:
            self._columns.popitem(last=False)
        return col

    def __call__(self, ch: int, timings: Sequence[Timing], phase: float) -> float:
        """Cost of chamber ``ch`` [kPa^2] for the valves' ``timings`` and the carrier phase.

        Parameters
        ----------
        ch : int
            Chamber (0: A, 1: B); only its valves' timings are read.
        timings : sequence of 4 Timing
        phase : float
            Carrier time at the first sample [s].
        """
        phase = float(phase)
        self.evaluations += 1
        key = (ch, *self._key(timings[2 * ch]), *self._key(timings[2 * ch + 1]), phase,
               self.frac.write_delay)
        cost = self._costs.get(key)
        if cost is not None:
            self.repeats += 1
            return cost
        A = np.column_stack([self._column(2 * ch + j, timings[2 * ch + j], phase)
                             for j in range(2)] + self._extra[ch])
        y = self._targets[ch]
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        cost = float(np.sum((A @ coef - y) ** 2)) / 1e6
        self._costs[key] = cost
        return cost


@njit(cache=True)
def _window_column(gain: np.ndarray, r: np.ndarray, flow: np.ndarray, k0: np.ndarray,
                   k1: np.ndarray, weight: np.ndarray, out: np.ndarray) -> None:
    """``out[k] = weight[k] * sum(gain[j] r[j] flow[j], k0[k] <= j < k1[k])``, summed as a
    running sum (numpy's cumsum: the same floating-point operations in the same order)."""
    n = gain.shape[0]
    c = np.empty(n + 1)
    c[0] = 0.0
    for j in range(n):
        term = gain[j] * r[j] * flow[j]
        c[j + 1] = term if j == 0 else c[j] + term
    for k in range(k0.shape[0]):
        out[k] = (c[k1[k]] - c[k0[k]]) * weight[k]


def coordinate_search(cost: Callable[[np.ndarray], float], x0: np.ndarray, lo: np.ndarray,
                      hi: np.ndarray, steps: np.ndarray, levels: int = 3, points: int = 3,
                      sweeps: int = 2) -> tuple[np.ndarray, float]:
    """Minimise ``cost`` one coordinate at a time on shrinking grids (no derivatives).

    The costs here are piecewise smooth with kinks (a minimum pulse switches whole pulses on and
    off), so a grid is more robust than a gradient. At each level every coordinate is tried at
    ``x ± k step`` (k = 1..points) within [lo, hi], ``sweeps`` times; then the steps shrink by 3.

    Parameters
    ----------
    cost : callable
        ``cost(x) -> float``.
    x0, lo, hi, steps : ndarray
        Start, bounds and first step per coordinate.
    levels, points, sweeps : int
        Grid refinements, points either side, sweeps per level.

    Returns
    -------
    (ndarray, float)
        The best point and its cost.
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    best = cost(x)
    step = np.asarray(steps, dtype=float).copy()
    for _ in range(levels):
        for _ in range(sweeps):
            moved = False
            for j in range(x.size):
                for k in (*range(-points, 0), *range(1, points + 1)):
                    cand = x.copy()
                    cand[j] = min(hi[j], max(lo[j], x[j] + k * step[j]))
                    if cand[j] == x[j]:
                        continue
                    c = cost(cand)
                    if c < best:
                        best, x, moved = c, cand, True
            if not moved:
                break
        step /= 3.0
    return x, best


def phase_search(cost: Callable[[float], float], period: float, coarse: int = 24,
                 tolerance: float = PHASE_TOLERANCE) -> tuple[float, float, np.ndarray]:
    """The carrier phase minimising ``cost``: a grid of ``coarse`` phases, then a finer one.

    A phase shift and a common shift of the valve delays explain the data almost alike (with
    the delays still being searched, the phases next to the truth cost within 5-10 % of
    it on the simulated rigs), so phase 0 (a carrier started with the log) is kept unless
    another phase costs less than ``1 / (1 + tolerance)`` of it: only a log that shows another
    phase moves it.

    Returns
    -------
    (float, float, ndarray)
        The phase [s] in [0, period), its cost and the costs of the coarse grid.
    """
    grid = np.arange(coarse) * period / coarse
    costs = np.array([cost(float(ph)) for ph in grid])
    if costs[0] <= (1.0 + tolerance) * float(np.min(costs)):
        return 0.0, float(costs[0]), costs
    k = int(np.argmin(costs))
    best_ph, best = float(grid[k]), float(costs[k])
    h = period / coarse
    for ph in best_ph + np.linspace(-h, h, 9):
        ph = float(np.mod(ph, period))
        c = cost(ph)
        if c < best:
            best_ph, best = ph, c
    return best_ph, best, costs


def min_pulse_range(cost: TimingCost, timings: Sequence[Timing], phase: float, i: int,
                    step: float) -> tuple[float, float]:
    """The minimum pulses of valve ``i`` the log cannot tell from the one found.

    A minimum pulse only decides whether a command pulse opens the valve at all, so the cost is
    flat between the lengths of the pulses the log holds: a closed loop whose controller never
    commands a pulse shorter than 1.5 ms (its PWM curve steps over the dead zone) leaves every
    minimum pulse up to 1.5 ms alike. The range is the profile-likelihood interval at the level
    of the other ranges (±:data:`~pneutune.identify.bounds.Z` s.e.): from the minimum pulse
    found, in steps of ``step`` each way, while the chamber's cost stays within a factor
    ``1 + Z^2 / n`` of its cost there (n: the chamber's windows), and never above the opening
    delay (contract 2's ``min_pulse <= delay_on``).

    Parameters
    ----------
    cost : TimingCost
        The chamber cost at the fitted conductances and pressure ratios.
    timings : sequence of 4 Timing
        The timings found; valve ``i``'s minimum pulse is varied, the others held.
    phase : float
        Carrier time at the log's first sample [s].
    i : int
        Valve index (a_in, a_out, b_in, b_out).
    step : float
        Scan step [s].

    Returns
    -------
    (float, float)
        Lowest and highest minimum pulse within the interval [s].
    """
    ch = i // 2
    tm = timings[i]
    limit = cost(ch, timings, phase) * (1.0 + Z**2 / max(cost.windows(ch), 1))

    def fits(mp: float) -> bool:
        cand = Timing(tm.delay_on, tm.delay_off, mp)
        return cost(ch, [*timings[:i], cand, *timings[i + 1:]], phase) <= limit

    found = min(tm.min_pulse, tm.delay_on)
    lo = hi = found
    while lo > 0.0 and fits(max(0.0, lo - step)):
        lo = max(0.0, lo - step)
    while hi < tm.delay_on and fits(min(tm.delay_on, hi + step)):
        hi = min(tm.delay_on, hi + step)
    return lo, hi


def timing_bounds(period: float) -> tuple[float, float]:
    """Search range of a delay [s]: 0 to :data:`MAX_DELAY_PERIODS` PWM periods."""
    return 0.0, MAX_DELAY_PERIODS * period


def opening_bounds(onset: Onset | None, write_delay: float, period: float
                   ) -> tuple[float, float]:
    """Search range of a valve's opening delay [s].

    A valve's step onset (:func:`~.valve_onsets.step_onsets`) holds its opening delay plus
    the loop delay: the range is the onset's, widened by :data:`ONSET_MARGIN`, less the loop
    delay, within :func:`timing_bounds`. Without an onset, :func:`timing_bounds`.

    Parameters
    ----------
    onset : Onset or None
        The valve's delay from a full-opening command to the chamber pressure's response.
    write_delay : float
        The loop delay [s] (:attr:`OpenFractions.write_delay`).
    period : float
        PWM period [s].

    Returns
    -------
    (float, float)
        Lowest and highest opening delay [s].
    """
    t_lo, t_hi = timing_bounds(period)
    if onset is None:
        return t_lo, t_hi
    hi_on = min(t_hi, max(t_lo, onset.high + ONSET_MARGIN - write_delay))
    return min(hi_on, max(t_lo, onset.low - ONSET_MARGIN - write_delay)), hi_on


#: ``cost_for(held, b)``: the chamber cost for the critical pressure ratios ``b`` of the four
#: valves, with the terms it does not solve for (the constant terms held) from the parameters
#: ``held`` (:class:`TimingCost`).
CostFor = Callable[[np.ndarray, np.ndarray], TimingCost]
#: ``refit(theta, timings, phase)``: the chamber fit's parameters refitted, starting from
#: ``theta``, on the valve openings of these timings and carrier phase; and their critical
#: pressure ratios b.
Refit = Callable[[np.ndarray, Sequence[Timing], float], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class TimingSearch:
    """The valve timings, carrier phase and loop delay found by :func:`search_timings`.

    Attributes
    ----------
    timings : tuple of 4 Timing
        Delays and minimum pulse per valve (a_in, a_out, b_in, b_out).
    phase : float
        Carrier time at the log's first sample [s].
    theta : ndarray
        The chamber fit's parameters from the last refit.
    phase_costs : ndarray
        Costs of the coarse phase grid (:func:`phase_search`) [kPa^2].
    loop_delay : float
        Every duty acts this long after its sample [s] (0: no loop delay found).
    loop_delay_range : (float, float)
        The loop delays scanned whose cost is within :data:`LOOP_DELAY_TOLERANCE` of the
        best, widened by half a grid step [s].
    loop_delay_costs : (ndarray, ndarray)
        The loop delays scanned [s] and their costs [kPa^2].
    """

    timings: tuple[Timing, ...]
    phase: float
    theta: np.ndarray
    phase_costs: np.ndarray
    loop_delay: float
    loop_delay_range: tuple[float, float]
    loop_delay_costs: tuple[np.ndarray, np.ndarray]


class _Search:
    """The timings being searched (a list of 4, replaced in place) and the steps of
    :func:`search_timings`."""

    def __init__(self, frac: OpenFractions, timings: Sequence[Timing],
                 onsets: Sequence[Onset | None], cost_for: CostFor, period: float) -> None:
        self.frac = frac
        self.timings = list(timings)
        self.onsets = list(onsets)
        self.cost_for = cost_for
        self.period = period
        self.t_lo, self.t_hi = timing_bounds(period)

    def bounds(self, i: int) -> tuple[float, float]:
        """Range of valve i's opening delay at the current loop delay."""
        return opening_bounds(self.onsets[i], self.frac.write_delay, self.period)

    def coarse(self, held: np.ndarray, b: np.ndarray) -> None:
        """A grid of (opening delay, pulse lengthening) per valve, the others held, at phase
        0: the curve's timings are a poor start where its duties were not steady. A valve with
        an onset starts with its opening delay moved into the onset's range."""
        cost = self.cost_for(held, b)
        timings, t_lo, t_hi = self.timings, self.t_lo, self.t_hi
        for i in range(4):
            t = timings[i]
            on_lo, on_hi = self.bounds(i)
            if self.onsets[i] is not None:
                on0 = float(np.clip(t.delay_on, on_lo, on_hi))
                t = Timing(on0, max(0.0, t.delay_off + on0 - t.delay_on), min(t.min_pulse, on0))
                timings[i] = t
            best = (cost(i // 2, timings, 0.0), t)
            grid_on = (np.linspace(on_lo, on_hi, 9) if self.onsets[i] is not None
                       else np.linspace(t_lo, 0.8 * t_hi, 9))
            for on in grid_on:
                for dl in np.linspace(-0.3 * t_hi, 0.5 * t_hi, 9):
                    cand = Timing(on, max(0.0, on + dl), min(t.min_pulse, on))
                    c = cost(i // 2, [*timings[:i], cand, *timings[i + 1:]], 0.0)
                    if c < best[0]:
                        best = (c, cand)
            timings[i] = best[1]

    def pairs(self, held: np.ndarray, b: np.ndarray, phase: float, step: float,
              levels: int) -> None:
        """Coordinate search of each chamber's two valves over (delay_on, delay_off -
        delay_on, min_pulse): the first moves both delays together, along the valley where
        the pulse widths stay and only their timing changes."""
        chamber_cost = self.cost_for(held, b)
        timings, t_lo, t_hi = self.timings, self.t_lo, self.t_hi

        def unpack(x: np.ndarray, j: int) -> Timing:
            on = x[3 * j]
            return Timing(on, max(0.0, on + x[3 * j + 1]), min(x[3 * j + 2], on))

        for ch in range(2):
            pair = (2 * ch, 2 * ch + 1)

            def cost(x: np.ndarray, ch: int = ch, pair: tuple[int, int] = pair) -> float:
                tms = list(timings)
                for j, i in enumerate(pair):
                    tms[i] = unpack(x, j)
                return chamber_cost(ch, tms, phase)

            x0 = np.array([v for i in pair for v in (
                timings[i].delay_on, timings[i].delay_off - timings[i].delay_on,
                timings[i].min_pulse)])
            lo_x = np.tile([t_lo, -t_hi, t_lo], 2)
            hi_x = np.tile([t_hi, t_hi, t_hi], 2)
            for j, i in enumerate(pair):
                lo_x[3 * j], hi_x[3 * j] = self.bounds(i)
            x0 = np.clip(x0, lo_x, hi_x)
            x, _ = coordinate_search(cost, x0, lo_x, hi_x, np.full(6, step), levels=levels)
            for j, i in enumerate(pair):
                timings[i] = unpack(x, j)

    def shifted(self, d: float) -> list[Timing]:
        """The timings with ``d`` taken off the opening delays an onset holds."""
        out = list(self.timings)
        for i, tm in enumerate(self.timings):
            if self.onsets[i] is None:
                continue
            on = float(np.clip(tm.delay_on - d, *self.bounds(i)))
            out[i] = Timing(on, max(0.0, tm.delay_off - d), min(tm.min_pulse, on))
        return out

    def loop_delay(self, theta: np.ndarray, b: np.ndarray, phase: float, refit: Refit
                   ) -> tuple[np.ndarray, tuple[float, float], tuple[np.ndarray, np.ndarray]]:
        """The loop-delay scan of :func:`search_timings`; sets ``frac.write_delay``.

        Returns the refitted parameters (``theta`` where no loop delay is adopted), the loop
        delay range and the scan's delays and costs.
        """
        frac = self.frac
        cost = self.cost_for(theta, b)
        grid = np.linspace(0.0, frac.Ts, LOOP_DELAY_POINTS)
        costs = []
        for d in grid:
            frac.write_delay = float(d)
            costs.append(sum(cost(ch, self.shifted(float(d)), phase) for ch in range(2)))
        frac.write_delay = 0.0
        c = np.asarray(costs)
        k = int(np.argmin(c))
        fitted = theta
        if k > 0 and c[k] * (1.0 + LOOP_DELAY_TOLERANCE) < c[0]:
            frac.write_delay = float(grid[k])
            self.timings[:] = self.shifted(float(grid[k]))
            for step in (0.03, 0.01):
                self.pairs(theta, b, phase, step * self.period, levels=2)
                fitted, b = refit(theta, self.timings, phase)
        near = grid[c <= c.min() * (1.0 + LOOP_DELAY_TOLERANCE)]
        h = 0.5 * (grid[1] - grid[0])
        return fitted, (max(0.0, float(near.min()) - h), float(near.max()) + h), (grid, c)


def search_timings(frac: OpenFractions, timings: Sequence[Timing],
                   onsets: Sequence[Onset | None], theta: np.ndarray, b: np.ndarray,
                   cost_for: CostFor, refit: Refit) -> TimingSearch:
    """Search the valves' timings, the carrier phase and a loop delay on a chamber fit.

    Timings first for fixed b at phase 0 (a carrier started with the log): a coarse grid per
    valve, then :func:`coordinate_search` of each chamber's two valves; then C and b for those
    timings (``refit``); then the phase (:func:`phase_search`), searched with these timings
    (the search sees the phase far better with timings near the truth than with the curve's);
    then finer timings, each step refitted.

    Last, a loop delay: every duty acting ``d`` after its sample (an IO delay). A common shift
    of the valves' own delays explains a loop delay where the duties change every sample (a
    closed loop), but not where they are steady for whole PWM periods (the valve tests), since
    the carrier, not the write, times the pulses there. So a log with both shows it, and a
    closed-loop log alone leaves it in the valves' delays (its cost is flat or rises with d).
    ``d`` is scanned over [0, Ts] (:data:`LOOP_DELAY_POINTS`) with the timings held; where a
    delay beats none by more than :data:`LOOP_DELAY_TOLERANCE`, the timings are searched again
    with it, with the costs' held terms and each refit's start the parameters before the
    scan. The range holds every scanned delay within that tolerance of the best, widened by
    half a grid step.

    Where a valve's step onset holds the sum of its opening delay and the loop delay, its
    opening delay is searched within :func:`opening_bounds`, and a candidate ``d`` takes ``d``
    off that valve's opening and closing delays: edges timed by a write (the full-opening
    steps) keep their times, pulses timed by the carrier (steady duties) move ``d`` earlier.
    On an identification run the costs stay flat all the same, since the carrier's phase is
    searched too (docs/identification.md, "The loop delay").

    Parameters
    ----------
    frac : OpenFractions
        The log's openings per sample; its ``write_delay`` is left at the loop delay found.
    timings : sequence of 4 Timing
        Starting timings (those of the averaged model's PWM curves).
    onsets : sequence of 4 (Onset or None)
        Per valve, its step onset where the logs show one.
    theta, b : ndarray
        The chamber fit's starting parameters and its critical pressure ratios of the four
        valves.
    cost_for : callable
        ``cost_for(held, b)``: the chamber cost (:data:`CostFor`).
    refit : callable
        ``refit(theta, timings, phase)``: the chamber fit's refit (:data:`Refit`).

    Returns
    -------
    TimingSearch
    """
    period = 1.0 / frac.rig.pwm_hz
    s = _Search(frac, timings, onsets, cost_for, period)
    s.coarse(theta, b)
    s.pairs(theta, b, 0.0, 0.1 * period, levels=3)
    theta, b = refit(theta, s.timings, 0.0)
    cost = cost_for(theta, b)
    phase, _, phase_costs = phase_search(
        lambda ph: sum(cost(ch, s.timings, ph) for ch in range(2)), period)
    if phase != 0.0:
        s.pairs(theta, b, phase, 0.1 * period, levels=3)
    for step in (0.03, 0.01):
        s.pairs(theta, b, phase, step * period, levels=2)
        theta, b = refit(theta, s.timings, phase)
    theta, span, scan = s.loop_delay(theta, b, phase, refit)
    return TimingSearch(timings=tuple(s.timings), phase=phase, theta=theta,
                        phase_costs=phase_costs, loop_delay=frac.write_delay,
                        loop_delay_range=span, loop_delay_costs=scan)


__all__ = ["LOOP_DELAY_POINTS", "LOOP_DELAY_TOLERANCE", "MAX_DELAY_PERIODS", "MIN_PULSE_STEP",
           "ONSET_MARGIN", "PHASE_TOLERANCE", "CostFor", "OpenFractions", "Refit", "Timing",
           "TimingCost", "TimingSearch", "coordinate_search", "min_pulse_range",
           "opening_bounds", "phase_search", "search_timings", "timing_bounds"]
