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
from numba import njit

from pneutune.control.contracts.plant import PlantConfig, RigConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import P_DOFF, P_DON, P_MINP, pack_plant
from pneutune.control.plant.valves import open_fractions, valve_open_fractions

#: Longest delay searched, in PWM periods (the plant allows up to 4).
MAX_DELAY_PERIODS = 0.5
#: Relative cost advantage another carrier phase needs over phase 0 (:func:`phase_search`).
PHASE_TOLERANCE = 0.1


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


def timing_bounds(period: float) -> tuple[float, float]:
    """Search range of a delay [s]: 0 to :data:`MAX_DELAY_PERIODS` PWM periods."""
    return 0.0, MAX_DELAY_PERIODS * period


__all__ = ["MAX_DELAY_PERIODS", "PHASE_TOLERANCE", "OpenFractions", "Timing", "TimingCost",
           "coordinate_search", "phase_search", "timing_bounds"]
