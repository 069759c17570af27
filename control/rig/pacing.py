"""The deploy loop's clock: realtime pacing and the timing of every iteration.

Without ``realtime`` the loop (:func:`~pneutune.control.rig.runtime.run_loop`) runs as fast as
the rig allows (a simulated rig: about 40 µs a sample). With ``realtime`` iteration k is due at
wall time ``t_0 + k Ts`` (``time.perf_counter_ns``): the loop sleeps until ``spin_s`` before it,
then spins. A late iteration is never followed by a burst of catch-up iterations: when one
starts more than a period late, the schedule shifts to now (the lost time is reported as
``slipped_s``). Jitter is the start lateness of each iteration; an overrun is an iteration
whose work (read to advance) ended after the next one was due. The first overrun is logged as
a ``deadline_overrun`` warning.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from pneutune.control.rig.supervisor import Event


@dataclass(frozen=True)
class TimingStats:
    """Timing of one run, in seconds.

    Attributes
    ----------
    samples : int
        Iterations timed.
    step_p50, step_p99, step_max : float
        Latency of the control step alone (:func:`~pneutune.control.law.darc.step_into`).
    loop_p50, loop_p99, loop_max : float
        Latency from the start of ``read`` to the end of ``write`` (sensor to valve).
    iteration_p50, iteration_p99 : float
        Whole iteration (read to the end of ``advance``, without the realtime wait).
    realtime : bool
        Whether the loop was paced to wall time; the fields below are 0 otherwise.
    overruns : int
        Iterations that ended after the next one was due.
    jitter_p50, jitter_p99, jitter_max : float
        Start lateness of the iterations against their schedule.
    slipped_s : float
        Schedule shifts after iterations that started more than a period late.
    wall_s : float
        Wall time of the loop.
    """

    samples: int
    step_p50: float
    step_p99: float
    step_max: float
    loop_p50: float
    loop_p99: float
    loop_max: float
    iteration_p50: float
    iteration_p99: float
    realtime: bool
    overruns: int
    jitter_p50: float
    jitter_p99: float
    jitter_max: float
    slipped_s: float
    wall_s: float

    def as_dict(self) -> dict[str, Any]:
        """Plain dict: the latencies and jitter in µs (keys ``*_us``), counts, ``wall_s``."""
        us = ("step_p50", "step_p99", "step_max", "loop_p50", "loop_p99", "loop_max",
              "iteration_p50", "iteration_p99", "jitter_p50", "jitter_p99", "jitter_max")
        out: dict[str, Any] = {f"{k}_us": getattr(self, k) * 1e6 for k in us}
        out.update(samples=self.samples, realtime=self.realtime, overruns=self.overruns,
                   slipped_s=self.slipped_s, wall_s=self.wall_s)
        return out


def _stats(step_ns: np.ndarray, loop_ns: np.ndarray, iter_ns: np.ndarray, late_ns: np.ndarray,
           realtime: bool, overruns: int, slipped_ns: int, wall_ns: int) -> TimingStats:
    def q(a: np.ndarray, p: float) -> float:
        return float(np.percentile(a, p)) * 1e-9 if a.size else math.nan

    def mx(a: np.ndarray) -> float:
        return float(a.max()) * 1e-9 if a.size else math.nan

    rt = realtime and late_ns.size > 0
    return TimingStats(
        samples=int(step_ns.size), step_p50=q(step_ns, 50), step_p99=q(step_ns, 99),
        step_max=mx(step_ns), loop_p50=q(loop_ns, 50), loop_p99=q(loop_ns, 99),
        loop_max=mx(loop_ns), iteration_p50=q(iter_ns, 50), iteration_p99=q(iter_ns, 99),
        realtime=realtime, overruns=overruns,
        jitter_p50=q(late_ns, 50) if rt else 0.0, jitter_p99=q(late_ns, 99) if rt else 0.0,
        jitter_max=mx(late_ns) if rt else 0.0, slipped_s=slipped_ns * 1e-9,
        wall_s=wall_ns * 1e-9)

def _wait_until(deadline_ns: int, spin_ns: int) -> int:
    """Sleep until ``spin_ns`` before the deadline, then spin; return the time of arrival."""
    while True:
        now = time.perf_counter_ns()
        remaining = deadline_ns - now
        if remaining <= 0:
            return now
        if remaining > spin_ns:
            time.sleep((remaining - spin_ns) * 1e-9)


class Pacer:
    """The loop's clock: the realtime schedule (module docstring) and every iteration's timing.

    Parameters
    ----------
    n : int
        Iterations of the loop.
    Ts : float
        The rig's sample period [s].
    realtime : bool
        Pace the iterations to wall time.
    spin_s : float
        Busy-wait this long before each due time instead of sleeping [s].
    """

    def __init__(self, n: int, Ts: float, realtime: bool, spin_s: float) -> None:
        self.Ts = Ts
        self.realtime = realtime
        self.period_ns = round(Ts * 1e9)
        self.spin_ns = round(spin_s * 1e9)
        self.step_ns = np.zeros(n, dtype=np.int64)
        self.loop_ns = np.zeros(n, dtype=np.int64)
        self.iter_ns = np.zeros(n, dtype=np.int64)
        self.late_ns = np.zeros(n if realtime else 0, dtype=np.int64)
        self.overruns = 0
        self.slipped = 0
        self.n_timed = 0
        self.wall0 = 0
        self.origin = 0

    def start(self) -> None:
        """Start the wall clock and the schedule: iteration 0 is due now."""
        self.wall0 = time.perf_counter_ns()
        self.origin = self.wall0

    def begin(self, k: int) -> int:
        """Wait for iteration ``k``'s due time (when paced).

        Parameters
        ----------
        k : int
            The iteration.

        Returns
        -------
        int
            The time it starts (``time.perf_counter_ns``) [ns].
        """
        if not self.realtime:
            return time.perf_counter_ns()
        due = self.origin + k * self.period_ns
        start = _wait_until(due, self.spin_ns)
        late = start - due
        self.late_ns[k] = late
        if late > self.period_ns:  # shift the schedule: no burst of catch-up iterations
            self.origin += late
            self.slipped += late
        return start

    def timed(self, k: int, t: float, start: int, step_ns: int, written: int,
              end: int) -> Event | None:
        """Keep iteration ``k``'s latencies.

        Parameters
        ----------
        k : int
            The iteration.
        t : float
            Its rig time [s], for the warning.
        start : int
            When it started (:meth:`begin`) [ns].
        step_ns : int
            Duration of the control step [ns].
        written : int
            When the duties were written [ns].
        end : int
            When the iteration's work ended [ns].

        Returns
        -------
        Event or None
            The ``deadline_overrun`` warning of the first paced iteration that ended after the
            next one was due.
        """
        self.step_ns[k] = step_ns
        self.loop_ns[k] = written - start
        self.iter_ns[k] = end - start
        self.n_timed = k + 1
        next_due = self.origin + (k + 1) * self.period_ns
        if not (self.realtime and end > next_due):
            return None
        self.overruns += 1
        if self.overruns > 1:
            return None
        over_us = (end - next_due) / 1e3
        return Event(t, "warning", "deadline_overrun",
                     f"iteration at t={t:.4f} s took {(end - start) / 1e3:.0f} µs and ended "
                     f"{over_us:.0f} µs after the next sample was due (Ts = {self.Ts * 1e3:g} ms)")

    def finish(self, completed: bool) -> TimingStats:
        """The run's timing.

        A paced run that ``completed`` first waits out its last period (a loop that follows
        starts its own schedule on the tick).

        Parameters
        ----------
        completed : bool
            Every iteration ran.

        Returns
        -------
        TimingStats
        """
        if self.realtime and completed:
            _wait_until(self.origin + self.step_ns.size * self.period_ns, self.spin_ns)
        wall = time.perf_counter_ns() - self.wall0
        m = self.n_timed
        return _stats(self.step_ns[:m], self.loop_ns[:m], self.iter_ns[:m], self.late_ns[:m],
                      self.realtime, self.overruns, self.slipped, wall)


__all__ = [
    "Pacer",
    "TimingStats",
]
