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
the update mode, delays and the minimum pulse; DESIGN.md), given three numbers per valve
(``delay_on``, ``delay_off``, ``min_pulse``) and the carrier phase at the log's first sample.
Those are found by search (:func:`coordinate_search`, :func:`phase_search`) on the chamber
equations, whose fit is very sensitive to them: on a closed-loop log of a simulated rig, 0.3 ms
off in one delay triples the residual, and a wrong carrier phase multiplies it by 15-1000.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pneutune.control.contracts.plant import PlantConfig, RigConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import P_DOFF, P_DON, P_MINP, pack_plant
from pneutune.control.plant.valves import open_fractions

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
        self._p = pack_plant(PlantConfig(rig=rig)).vec.copy()
        self._out = np.zeros_like(self.duties)

    def __call__(self, timings: Sequence[Timing], phase: float) -> np.ndarray:
        """(N, 4) open fractions, valve order a_in, a_out, b_in, b_out.

        Parameters
        ----------
        timings : sequence of 4 Timing
        phase : float
            Carrier time at the first sample, in [0, 1/pwm_hz) [s].
        """
        p = self._p
        for i, tm in enumerate(timings):
            p[P_DON + i] = tm.delay_on
            p[P_DOFF + i] = tm.delay_off
            p[P_MINP + i] = min(tm.min_pulse, tm.delay_on)
        s = plant.initial_state(p, 0.5 * (self.rig.x_min + self.rig.x_max), self.rig.p0,
                                self.rig.p0)
        open_fractions(p, s, self.duties, float(phase), self.Ts, self._out)
        return self._out.copy()


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


__all__ = ["MAX_DELAY_PERIODS", "PHASE_TOLERANCE", "OpenFractions", "Timing",
           "coordinate_search", "phase_search", "timing_bounds"]
