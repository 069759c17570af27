"""The deploy runtime: a fixed-rate loop at Ts around the one compiled control step.

Per sample k (rig time t = k Ts), in this order:

1. ``rig.read()`` the sensors ``[x, p_a, p_b, p_s]`` and ``rig.sample_times()`` (None when the
   rig cannot tell; :class:`pneutune.control.rig.protocol.Rig`);
2. the supervisor checks them (:meth:`pneutune.control.rig.supervisor.Supervisor.check_sensors`);
   a fault writes the fail-safe duties *in this sample*, records the event and stops the loop:
   the bad sample never reaches the control law;
3. :func:`pneutune.control.law.darc.step_into`, the same compiled step as the simulator and the
   tuner (the control law exists once), on ``[t, x, p_a, p_b, p_s, x_r, v_r, a_r]``;
4. ``rig.write(duties)``;
5. the supervisor's re-identification warnings on θ̂ and p_s (they never stop the run);
6. ``rig.advance()`` to the next sample, then (``realtime``) wait for its wall-clock time.

Start: the piston must rest where the reference starts (the precondition of
:func:`pneutune.control.sim.closed_loop.simulate_scenario` too): the first reading must lie within
``start_tolerance`` of x_r(0), else the run stops with the fault ``start_position``. The
controller state starts from :func:`pneutune.control.law.darc.init_state` at x_r(0) and the first
measured chamber pressures, exactly as in the simulator, so that on the simulated rig with the
same plant and seed a deploy run reproduces ``simulate --controller`` sample for sample.

Homing (:func:`run_scenario`'s ``home``, ``deploy --home``): before the scenario,
:func:`homing_move` moves the piston from where it rests to x_r(0) under the same controller and
supervisor: a quintic move of :data:`HOME_MOVE_S` from the first reading, then
:data:`HOME_HOLD_S` holding x_r(0). ``auto`` (the default) does so only when the first reading is
more than ``start_tolerance`` away, ``always`` before every scenario, ``off`` never (a distant
piston is then the fault ``start_position``). The first reading is taken once and serves the
decision and the first sample of whichever loop runs next (a simulated rig draws its noise per
reading), so a run that needs no homing is the run without it, sample for sample. After a move
the scenario starts as above, from a fresh controller state and its own t = 0; the rig's clock
runs on (``clock_offset``: the supervisor's staleness rule compares the rig's sample times with
the loop's time shifted by the homing's length; the control law gets the rig's time). A
simulated rig in process holds its timed disturbance during the move and starts it with the
scenario (``set_scenario_start``); for a driver that simulates one on its own clock a warning
says it comes early. The homing samples are not in the scenario's recording: at t = 0 it gets the
move's warnings and an ``info`` event saying where the piston came from and how close it got.

Pacing: without ``realtime`` the loop runs as fast as the rig allows (a simulated rig: about
40 µs a sample). With ``realtime`` iteration k is due at wall time ``t_0 + k Ts``
(``time.perf_counter_ns``): the loop sleeps until ``spin_s`` before it, then spins. A late
iteration is never followed by a burst of catch-up iterations: when one starts more than a
period late, the schedule shifts to now (the lost time is reported as ``slipped_s``). Jitter is
the start lateness of each iteration; an overrun is an iteration whose work (read to advance)
ended after the next one was due. The first overrun is logged as a ``deadline_overrun``
warning.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.constants import HOME_MODES
from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.darc import MEAS_SIZE, S_THETA, init_state, step_into
from pneutune.control.law.layout import pack
from pneutune.control.logs.recording import Recording
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.protocol import Rig, SimulatedRig
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES, Event, Supervisor, SupervisorSettings
from pneutune.control.rig.wire import RigIOError
from pneutune.control.sim.closed_loop import (
    LOG_INDEX,
    ClosedLoopResult,
    Metrics,
    compute_metrics,
    scenario_plant,
)
from pneutune.control.sim.scenarios import Scenario, move_and_hold

#: Status of a run that a supervisor fault stopped (Metrics.status).
STATUS_FAULT = "fault"
#: Largest distance between the first position reading and x_r(0) [m].
START_TOLERANCE = 1.0e-3
#: Homing: the quintic move from the resting position to x_r(0) [s] (a full 50 mm stroke at a
#: peak speed of 31 mm/s, below the Table-1 sines' 55 mm/s).
HOME_MOVE_S = 3.0
#: Homing: time holding x_r(0) after the move, for the pressures to settle [s].
HOME_HOLD_S = 1.0


@dataclass(frozen=True)
class TimingStats:
    """Timing of one run, in seconds.

    Attributes
    ----------
    samples : int
        Iterations timed.
    step_p50, step_p99, step_max : float
        Latency of the control step alone (:func:`darc.step_into`).
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


@dataclass
class LoopResult:
    """What :func:`run_loop` produced.

    Attributes
    ----------
    recording : Recording
        Sensors, duties, reference, ``/control/state`` (and ``/sim/truth``) per sample, the
        events; truncated to the samples recorded.
    n_done : int
        Samples recorded (the fault sample is included when its readings are finite: it shows
        the fail-safe duties).
    fault : Event or None
        The fault that stopped the run.
    events : list of Event
        Every event, in time order (warnings, the fault).
    timing : TimingStats
        Latencies, and jitter/overruns when paced.
    state : ndarray
        The controller state at the end.
    """

    recording: Recording
    n_done: int
    fault: Event | None
    events: list[Event]
    timing: TimingStats
    state: np.ndarray


@dataclass(frozen=True)
class LoopSettings:
    """How :func:`run_loop` runs: the options a deploy run gives every loop it starts.

    Attributes
    ----------
    realtime : bool
        Pace the loop to wall time.
    record_truth : bool
        Record ``rig.truth()`` as ``/sim/truth``; the rig must then be a
        :class:`~pneutune.control.rig.protocol.SimulatedRig`.
    fail_safe : 4 floats
        Duties written on a fault.
    start_tolerance : float
        Largest |x(0) - x_r(0)| [m].
    spin_s : float
        Realtime: busy-wait this long before each deadline instead of sleeping [s].
    law : callable or None
        The control step, with the signature of :func:`~pneutune.control.law.darc.step_into`;
        None: the installed law. Another build of the same C
        (:class:`~pneutune.control.law.cbuild.CLaw`, e.g. in ``float``) runs the loop as a
        target would (software in the loop).
    """

    realtime: bool = False
    record_truth: bool = False
    fail_safe: tuple[float, float, float, float] = FAIL_SAFE_DUTIES
    start_tolerance: float = START_TOLERANCE
    spin_s: float = 5.0e-4
    law: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], int] | None = None


def _wait_until(deadline_ns: int, spin_ns: int) -> int:
    """Sleep until ``spin_ns`` before the deadline, then spin; return the time of arrival."""
    while True:
        now = time.perf_counter_ns()
        remaining = deadline_ns - now
        if remaining <= 0:
            return now
        if remaining > spin_ns:
            time.sleep((remaining - spin_ns) * 1e-9)


def _warm_up(cfg: np.ndarray, ref: np.ndarray,
             law: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], int] = step_into,
             ) -> None:
    """One control step on a scratch state, so that loading the compiled step does not delay
    the first sample of a paced run."""
    if ref.shape[0] == 0:
        return
    scratch = init_state(cfg, float(ref[0, 0]), 2.0e5, 2.0e5)
    meas = np.zeros(MEAS_SIZE)
    meas[1] = ref[0, 0]
    meas[2:5] = (2.0e5, 2.0e5, 6.0e5)
    meas[5:8] = ref[0]
    law(scratch, meas, cfg, np.empty(4))


class _Pacer:
    """The loop's clock: the realtime schedule (module docstring) and every iteration's timing.

    Parameters
    ----------
    n : int
        Iterations of the loop.
    Ts : float
        The rig's sample period [s].
    realtime, spin_s
        As :class:`LoopSettings`.
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
        """Wait for iteration ``k``'s due time (when paced); the time it starts [ns]."""
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
        """Keep iteration ``k``'s latencies (times in ns); the warning of the first overrun."""
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
        """The run's timing; a paced run that ``completed`` first waits out its last period
        (a loop that follows starts its own schedule on the tick)."""
        if self.realtime and completed:
            _wait_until(self.origin + self.step_ns.size * self.period_ns, self.spin_ns)
        wall = time.perf_counter_ns() - self.wall0
        m = self.n_timed
        return _stats(self.step_ns[:m], self.loop_ns[:m], self.iter_ns[:m], self.late_ns[:m],
                      self.realtime, self.overruns, self.slipped, wall)


class _LoopLog:
    """What a loop records per sample: sensors, duties, the logged controller state, the truth.

    Parameters
    ----------
    rig : Rig
        The rig; with ``record_truth`` it must be a
        :class:`~pneutune.control.rig.protocol.SimulatedRig`.
    ref : (N, 3) float64
        The reference, recorded as it is.
    Ts : float
        The sample period [s].
    record_truth : bool
        Record ``rig.truth()`` at every sample.

    Raises
    ------
    TypeError
        ``record_truth`` for a rig that is not a ``SimulatedRig``.
    """

    def __init__(self, rig: Rig, ref: np.ndarray, Ts: float, record_truth: bool) -> None:
        self.truth_fn: Callable[[], np.ndarray] | None = None
        if record_truth:
            if not isinstance(rig, SimulatedRig):
                raise TypeError(f"record_truth needs a SimulatedRig (one with truth()), got "
                                f"{type(rig).__name__}")
            self.truth_fn = rig.truth
        n = ref.shape[0]
        rec = Recording(n, Ts, truth=self.truth_fn is not None, reference=True,
                        control_state=True)
        self.rec = rec
        self.sensors, self.duties, self.truth = rec.sensors_, rec.duties_, rec.truth_
        self.state = rec.state_ if rec.state_ is not None else np.empty((n, LOG_INDEX.shape[0]))
        if rec.reference_ is not None:
            rec.reference_[:] = ref

    def sample(self, k: int, sensors: np.ndarray, duties: np.ndarray,
               state: np.ndarray) -> None:
        """Record sample ``k``: its readings, the duties written and the controller state."""
        self.sensors[k] = sensors
        self.duties[k] = duties
        self.state[k, :] = state[LOG_INDEX]
        if self.truth is not None and self.truth_fn is not None:
            self.truth[k] = self.truth_fn()

    def finish(self, n_done: int, events: list[Event]) -> Recording:
        """The recording of the first ``n_done`` samples, with ``events``."""
        self.rec.truncate(n_done)
        for e in events:
            self.rec.event(e.t, e.level, e.code, e.message)
        return self.rec


class _Stop(Exception):
    """A fault that ends the loop at sample ``k`` (rig time ``t`` on the loop's clock);
    ``sensors`` are that sample's readings, when it has any."""

    def __init__(self, k: int, t: float, fault: Event, sensors: np.ndarray | None = None) -> None:
        super().__init__(fault.message)
        self.k = k
        self.t = t
        self.fault = fault
        self.sensors = sensors

    @classmethod
    def rig_io(cls, k: int, t: float, message: str) -> _Stop:
        """The fault ``rig_io`` at sample ``k`` (time ``t``): a call of the rig failed."""
        return cls(k, t, Event(t, "error", "rig_io", message))


def _read_sample(rig: Rig, k: int, t: float,
                 first: tuple[np.ndarray, np.ndarray | None] | RigIOError | None,
                 clock_offset: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Sample ``k``'s sensors and their sample times shifted to the loop's clock.

    At k = 0, ``first`` (a reading already taken, or the error it raised) stands for the read.

    Raises
    ------
    _Stop
        The read failed: the fault ``rig_io``.
    """
    try:
        if k == 0 and isinstance(first, RigIOError):
            raise first
        if k == 0 and first is not None:
            s, stamps = first
        else:
            s = rig.read()
            stamps = rig.sample_times()
    except RigIOError as exc:
        raise _Stop.rig_io(k, t, f"reading the rig failed at t={t:.4f} s: {exc}") from None
    if stamps is not None and clock_offset:
        stamps = np.asarray(stamps, dtype=np.float64) - clock_offset
    return s, stamps


def _write_duties(rig: Rig, k: int, t: float, duties: np.ndarray) -> None:
    """Write sample ``k``'s duties.

    Raises
    ------
    _Stop
        The write failed: the fault ``rig_io`` at sample ``k``.
    """
    try:
        rig.write(duties)
    except RigIOError as exc:
        raise _Stop.rig_io(k, t, f"writing the duties failed at t={t:.4f} s: {exc}") from None


def _advance(rig: Rig, k: int, t: float, Ts: float) -> None:
    """Move the rig on from sample ``k`` (time ``t``) to the next.

    Raises
    ------
    _Stop
        The advance failed: the fault ``rig_io`` at sample ``k + 1``.
    """
    try:
        rig.advance()
    except RigIOError as exc:
        raise _Stop.rig_io(k + 1, t + Ts,
                           f"advancing the rig failed at t={t:.4f} s: {exc}") from None


def _check_sample(supervisor: Supervisor | None, k: int, t: float, s: np.ndarray,
                  stamps: np.ndarray | None, x_r0: float, start_tolerance: float) -> None:
    """Let sample ``k`` reach the control law only if the supervisor accepts it and, at
    k = 0, the piston lies within ``start_tolerance`` of ``x_r0``.

    Raises
    ------
    _Stop
        The supervisor's fault, or ``start_position``; with the sample's readings.
    """
    fault = supervisor.check_sensors(t, s, stamps) if supervisor is not None else None
    if fault is None and k == 0 and not abs(float(s[0]) - x_r0) <= start_tolerance:
        fault = Event(t, "error", "start_position",
                      f"the piston is at x = {float(s[0]) * 1e3:.3f} mm, not at the start of "
                      f"the reference x_r(0) = {x_r0 * 1e3:.3f} mm (tolerance "
                      f"{start_tolerance * 1e3:g} mm): move it there first (deploy --home "
                      f"auto does, under the controller)")
    if fault is not None:
        raise _Stop(k, t, fault, s)


def _fail_safe(rig: Rig, duties: np.ndarray, fault: Event, t: float) -> Event:
    """Write the fail-safe ``duties`` now; the fault as logged, naming them (and a failed
    write)."""
    try:
        rig.write(duties)
    except RigIOError as exc:
        fault = Event(fault.t, fault.level, fault.code,
                      f"{fault.message}; writing the fail-safe duties failed too ({exc})")
    return Event(fault.t, fault.level, fault.code,
                 f"{fault.message}; fail-safe: valves [a_in, a_out, b_in, b_out] = "
                 f"{duties.tolist()} from t={t:.4f} s")


def run_loop(rig: Rig, cfg_vec: np.ndarray, reference: np.ndarray,
             supervisor: Supervisor | None = None, settings: LoopSettings | None = None, *,
             first: tuple[np.ndarray, np.ndarray | None] | RigIOError | None = None,
             on_sample: Callable[[int], None] | None = None,
             clock_offset: float = 0.0) -> LoopResult:
    """Run the controller against a rig for ``len(reference)`` samples (module docstring).

    Parameters
    ----------
    rig : Rig
        The rig (:class:`pneutune.control.rig.protocol.Rig`). It is not closed here.
    cfg_vec : (CFG_SIZE,) float64
        The packed controller config (:func:`pneutune.control.law.layout.pack`).
    reference : (N, 3) float64
        ``[x_r, v_r, a_r]`` per sample [m, m/s, m/s^2].
    supervisor : Supervisor, optional
        The safety supervisor (reset here); None runs unsupervised (benchmarks only).
    settings : LoopSettings, optional
        Pacing, truth recording, fail-safe duties, start tolerance; default
        ``LoopSettings()``.
    first : (sensors, sample_times) or RigIOError, optional
        The first sample's ``read()`` and ``sample_times()``, already taken (by
        :func:`run_scenario`, to decide on homing), or the error that reading raised: used for
        k = 0 instead of reading again (a rig_io fault for an error).
    on_sample : callable, optional
        Called with k after each sample (progress display).
    clock_offset : float
        Rig time of this loop's first sample [s] (after a homing move): ``sample_times()`` are
        shifted by it before the supervisor compares them with the loop's time, and the control
        law gets the rig's time (its PWM dithering follows the rig's carrier).

    Returns
    -------
    LoopResult

    Raises
    ------
    TypeError
        ``settings.record_truth`` for a rig that is not a ``SimulatedRig``.
    """
    opts = LoopSettings() if settings is None else settings
    ref = np.ascontiguousarray(reference, dtype=np.float64)
    n = ref.shape[0]
    Ts = float(rig.Ts)
    log = _LoopLog(rig, ref, Ts, opts.record_truth)
    cfg = np.ascontiguousarray(cfg_vec, dtype=np.float64)
    if supervisor is not None:
        supervisor.reset()
    fs = np.asarray(opts.fail_safe, dtype=np.float64)
    meas = np.empty(MEAS_SIZE)
    duties = np.empty(4)
    cs = np.empty(0)
    events: list[Event] = []
    fault: Event | None = None
    n_done = 0
    pacer = _Pacer(n, Ts, opts.realtime, opts.spin_s)
    law = step_into if opts.law is None else opts.law
    _warm_up(cfg, ref, law)
    pacer.start()
    clock = time.perf_counter_ns
    try:
        for k in range(n):
            t = k * Ts
            start = pacer.begin(k)
            s, stamps = _read_sample(rig, k, t, first, clock_offset)
            _check_sample(supervisor, k, t, s, stamps, ref[0, 0], opts.start_tolerance)
            if k == 0:
                cs = init_state(cfg, float(ref[0, 0]), float(s[1]), float(s[2]))
            meas[0] = t + clock_offset
            meas[1:5] = s
            meas[5:8] = ref[k]
            t_step = clock()
            law(cs, meas, cfg, duties)
            t_step_end = clock()
            _write_duties(rig, k, t, duties)
            t_written = clock()
            log.sample(k, s, duties, cs)
            if supervisor is not None:
                events.extend(supervisor.check_estimates(t, float(s[3]), cs[S_THETA:S_THETA + 6]))
            n_done = k + 1
            _advance(rig, k, t, Ts)
            overrun = pacer.timed(k, t, start, t_step_end - t_step, t_written, clock())
            if overrun is not None:
                events.append(overrun)
            if on_sample is not None:
                on_sample(k)
    except _Stop as stop:
        fault = _fail_safe(rig, fs, stop.fault, stop.t)
        events.append(fault)
        n_done = stop.k
        sensors = stop.sensors
        if sensors is not None and np.all(np.isfinite(sensors)):  # a loggable fault sample
            state = cs if cs.size else init_state(cfg, float(ref[0, 0]), float(sensors[1]),
                                                  float(sensors[2]))
            log.sample(stop.k, sensors, fs, state)
            n_done = stop.k + 1
    timing = pacer.finish(completed=fault is None and n_done == n)
    events.sort(key=lambda e: e.t)
    return LoopResult(log.finish(n_done, events), n_done, fault, events, timing, cs)


def homing_move(rig: Rig, cfg_vec: np.ndarray, target: float,
                supervisor: Supervisor | None = None, settings: LoopSettings | None = None, *,
                move_s: float = HOME_MOVE_S, hold_s: float = HOME_HOLD_S,
                first: tuple[np.ndarray, np.ndarray | None] | RigIOError | None = None,
                on_sample: Callable[[int], None] | None = None) -> LoopResult:
    """Move the piston from where it rests to ``target`` under the controller (homing).

    The reference is :func:`~pneutune.control.sim.scenarios.move_and_hold` from the first
    position reading to ``target`` in ``move_s``, then ``hold_s`` at ``target``; the controller
    state starts there as in any run (:func:`run_loop`), under the same supervisor.

    Parameters
    ----------
    rig : Rig
    cfg_vec : (CFG_SIZE,) float64
        The packed controller config.
    target : float
        Where the move ends: the scenario's x_r(0) [m].
    supervisor : Supervisor, optional
        As :func:`run_loop` (reset here).
    settings : LoopSettings, optional
        As :func:`run_loop`; its ``start_tolerance`` does not apply (the move starts where
        the piston is).
    move_s, hold_s : float
        Durations of the move and the hold [s].
    first : (sensors, sample_times) or RigIOError, optional
        The first sample's reading, already taken (:func:`run_scenario`), or the error it
        raised; default: read it here.
    on_sample : callable, optional
        As :func:`run_loop`.

    Returns
    -------
    LoopResult
        Its recording holds the homing samples; ``fault`` is set if the supervisor stopped it.
    """
    opts = LoopSettings() if settings is None else settings
    if first is None:
        try:
            first = (rig.read(), rig.sample_times())
        except RigIOError as exc:
            first = exc
    t = np.arange(max(1, round((move_s + hold_s) / float(rig.Ts)))) * float(rig.Ts)
    x0 = math.nan if isinstance(first, RigIOError) else float(first[0][0])
    # a NaN first position is the supervisor's sensor_nan at k = 0: start the move anywhere
    ref = move_and_hold(t, x0 if math.isfinite(x0) else target, target, move_s)
    return run_loop(rig, cfg_vec, ref, supervisor,
                    dataclasses.replace(opts, start_tolerance=math.inf),
                    first=first, on_sample=on_sample)


def _after_homing(rig: Rig, scenario: Scenario, plant: PlantConfig | None,
                  homing: LoopResult | None, offset: float, target: float) -> list[Event]:
    """Start the scenario's clock on the rig after a homing move; the events for its log.

    A rig with ``set_scenario_start`` (the simulated rigs in process) times its plant's force
    steps from the scenario's start; any other rig that simulates timed steps (the plant's, when
    known, else the scenario's) does so on its own clock, which a ``warning`` says. The move's
    warnings follow, at t = 0, then the ``info`` event ``homing``.
    """
    if homing is None:
        return []
    out: list[Event] = []
    timed = bool(plant.disturbance.force_steps if plant is not None
                 else scenario.plant_updates.get("disturbance", {}).get("force_steps"))
    start = getattr(rig, "set_scenario_start", None)
    if callable(start):
        start(offset)
    elif timed:
        out.append(Event(0.0, "warning", "homing_clock",
                         f"the homing move took {offset:.2f} s of the rig's clock: a driver that "
                         f"simulates this scenario's timed disturbance on its own clock applies "
                         f"it {offset:.2f} s early"))
    out += [Event(0.0, e.level, e.code, f"during the homing move (t={e.t:.3f} s): {e.message}")
            for e in homing.events if e.level == "warning"]
    x = homing.recording.sensors_[:, 0]
    out.append(Event(0.0, "info", "homing",
                     f"moved from x = {x[0] * 1e3:.3f} mm to x_r(0) = {target * 1e3:.3f} mm in "
                     f"{homing.n_done * homing.recording.Ts:.2f} s under the controller; "
                     f"|x - x_r(0)| = {abs(x[-1] - target) * 1e3:.3f} mm at its end"))
    return out


# ---------------------------------------------------------------------------------------------
# Scenarios
# ---------------------------------------------------------------------------------------------


@dataclass
class ScenarioResult:
    """One scenario deployed on a rig.

    Attributes
    ----------
    scenario : Scenario
        What was tracked.
    controller : ControllerConfig
        The deployed config.
    loop : LoopResult
        The loop's output (recording, events, timing).
    metrics : Metrics
        The paper's indices over what ran (status ``ok`` or ``fault``).
    rig_meta : dict
        The rig's ``rig`` block (written to the log).
    plant : PlantConfig or None
        The simulated plant (with the scenario's changes), when the rig is simulated.
    seed : int or None
        The simulated rig's noise seed.
    run_meta : dict
        The log's ``run`` metadata.
    homing : LoopResult or None
        The homing move before the scenario, if one ran; when it faulted, :attr:`loop` is that
        move, the scenario did not run and the metrics' E_p and E_rms are NaN.
    """

    scenario: Scenario
    controller: ControllerConfig
    loop: LoopResult
    metrics: Metrics
    rig_meta: dict[str, float | str]
    plant: PlantConfig | None = None
    seed: int | None = None
    run_meta: dict[str, str] = field(default_factory=dict)
    homing: LoopResult | None = None

    @property
    def fault(self) -> Event | None:
        """The fault that stopped the run, if any."""
        return self.loop.fault

    def save_log(self, path: str, run: Mapping[str, str] | None = None) -> None:
        """Write the run as an MCAP log (contract 1), atomically.

        Parameters
        ----------
        path : str
            Destination.
        run : mapping, optional
            Extra ``run`` metadata (merged over :attr:`run_meta`).
        """
        meta = dict(self.run_meta)
        meta.update(run or {})
        self.loop.recording.save(path, rig=self.rig_meta, run=meta)

    def closed_loop_result(self) -> ClosedLoopResult:
        """The run as a :class:`~pneutune.control.sim.closed_loop.ClosedLoopResult` (for plots)."""
        rec = self.loop.recording
        plant = self.plant if self.plant is not None else PlantConfig()
        return ClosedLoopResult(self.scenario, plant, self.controller, self.seed or 0, rec.Ts,
                                rec.reference_, rec.sensors_, rec.duties_, rec.state_,
                                rec.truth_, self.metrics)


def scenario_reference(scenario: Scenario, rig_meta: Mapping[str, float | str]) -> np.ndarray:
    """The scenario's reference at the rig's Ts, centred at the rig's mid-stroke, (N, 3)."""
    x_min, x_max = float(rig_meta["x_min"]), float(rig_meta["x_max"])
    return scenario.reference_array(float(rig_meta["Ts"]), 0.5 * (x_min + x_max))


def run_scenario(controller: ControllerConfig, scenario: Scenario, rig: Rig, *,
                 supervisor: Supervisor | None = None, realtime: bool = False,
                 record_truth: bool = False, cfg_vec: np.ndarray | None = None,
                 fail_safe: tuple[float, float, float, float] = FAIL_SAFE_DUTIES,
                 duration: float | None = None, plant: PlantConfig | None = None,
                 seed: int | None = None,
                 on_sample: Callable[[int], None] | None = None,
                 home: str = "auto",
                 start_tolerance: float = START_TOLERANCE,
                 law: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], int] | None
                 = None) -> ScenarioResult:
    """Deploy ``controller`` on ``rig`` for one scenario and compute the metrics.

    Parameters
    ----------
    controller : ControllerConfig
        The config (already checked against the rig).
    scenario : Scenario
        What to track. Its plant changes (payload, force steps) are the rig's business: a
        simulated rig must have been built with them (:func:`sim_rig_for`).
    rig : Rig
        The rig; its ``rig_metadata()`` sets the reference's timing and centre and goes to the
        log.
    supervisor : Supervisor, optional
        Default: one from the controller's ``limits`` (:meth:`SupervisorSettings.from_controller`).
    realtime, record_truth, fail_safe
        As :class:`LoopSettings`.
    cfg_vec : ndarray, optional
        Pre-packed controller.
    duration : float, optional
        Run only the first ``duration`` seconds of the scenario [s].
    plant, seed : optional
        The simulated plant and seed, kept in the result (logs, plots).
    on_sample : callable, optional
        Progress callback.
    home : {"auto", "always", "off"}
        Move the piston to x_r(0) under the controller first (:func:`homing_move`, module
        docstring): when it rests more than ``start_tolerance`` away, always, or never.
    start_tolerance : float
        Largest |x(0) - x_r(0)| of the scenario's start [m].
    law : callable, optional
        The control step (:attr:`LoopSettings.law`); default the installed law.

    Returns
    -------
    ScenarioResult
    """
    rig_meta = dict(rig.rig_metadata())
    ref = scenario_reference(scenario, rig_meta)
    if duration is not None:
        ref = ref[:max(1, round(duration / float(rig_meta["Ts"])))]
    sup = supervisor if supervisor is not None else Supervisor(
        SupervisorSettings.from_controller(controller))
    cfg = pack(controller) if cfg_vec is None else cfg_vec
    settings = LoopSettings(realtime=realtime, record_truth=record_truth, fail_safe=fail_safe,
                            start_tolerance=start_tolerance, law=law)
    if home not in HOME_MODES:
        raise ValueError(f"home must be one of {HOME_MODES}, got {home!r}")
    homing: LoopResult | None = None
    segment = (scenario.name, "scenario", {"description": scenario.description})
    first: tuple[np.ndarray, np.ndarray | None] | RigIOError | None = None
    if home != "off":
        # before the first reading, which then serves its sample at once
        _warm_up(cfg, ref, step_into if law is None else law)
        try:
            first = (rig.read(), rig.sample_times())
        except RigIOError as exc:
            first = exc  # the scenario's loop records it as the rig_io fault at t = 0
        # a reading the supervisor refuses (NaN, out of range, stale, no supply) is its fault
        # at the scenario's first sample: nothing moves
        sup.reset()
        fit = not isinstance(first, RigIOError) and sup.check_sensors(0.0, *first) is None
        if fit and (home == "always" or abs(float(first[0][0]) - ref[0, 0]) > start_tolerance):
            start = getattr(rig, "set_scenario_start", None)
            if callable(start):
                start(None)  # no timed step fires during the move
            homing = homing_move(rig, cfg, float(ref[0, 0]), sup, settings, first=first)
            first = None
    if homing is not None and homing.fault is not None:  # the scenario does not run
        loop = homing
        ref = homing.recording.reference_
        segment = ("homing", "homing", {"description": f"homing move before {scenario.name}"})
    else:
        offset = homing.n_done * float(rig_meta["Ts"]) if homing is not None else 0.0
        notes = _after_homing(rig, scenario, plant, homing, offset, float(ref[0, 0]))
        loop = run_loop(rig, cfg, ref, sup, settings, first=first, on_sample=on_sample,
                        clock_offset=offset)
        loop.events[:0] = notes
        loop.recording.events_[:0] = [(e.t, e.level, e.code, e.message) for e in notes]
    rec = loop.recording
    a = controller.adaptation
    status = STATUS_FAULT if loop.fault is not None else "ok"
    metrics = compute_metrics(scenario, rec.Ts, ref, rec.sensors_, rec.duties_, rec.state_,
                              np.asarray(a.theta_min), np.asarray(a.theta_max),
                              float(rig_meta["x_min"]), float(rig_meta["x_max"]), status,
                              duty_top=np.asarray(controller.top_duties))
    if loop is homing:  # the scenario never ran: no tracking figures for it
        metrics = dataclasses.replace(metrics, E_p_mm=math.nan, E_rms_mm=math.nan)
    rec.segments_.insert(0, (0.0, segment[0], segment[1],
                             {**segment[2], "duration": float(ref.shape[0] * rec.Ts)}))
    run_meta = {"scenario": scenario.name, "variant": controller.variant,
                "status": status, "realtime": str(bool(realtime)).lower()}
    if homing is not None:
        run_meta["homing"] = "fault" if homing.fault is not None else "done"
    if seed is not None:
        run_meta["seed"] = str(seed)
    if loop.fault is not None:
        run_meta["fault"] = loop.fault.code
    return ScenarioResult(scenario, controller, loop, metrics, rig_meta, plant, seed, run_meta,
                        homing)


def sim_rig_for(scenario: Scenario, plant_cfg: PlantConfig | None = None,
                seed: int | None = None, rig_class: type[DeploySimRig] = DeploySimRig,
                **rig_kwargs: Any) -> tuple[DeploySimRig, PlantConfig, int]:
    """The simulated rig set up for a scenario, as ``simulate --controller`` sets it up.

    The plant gets the scenario's changes
    (:func:`~pneutune.control.sim.closed_loop.scenario_plant`);
    the piston rests at x_r(0) with the chamber pressures in force balance; the noise seed is
    ``seed`` or the plant's ``sim.seed``.

    Parameters
    ----------
    scenario : Scenario
        The scenario.
    plant_cfg : PlantConfig, optional
        The plant; default the paper's rig.
    seed : int, optional
        Sensor-noise seed.
    rig_class : type
        :class:`DeploySimRig` or a subclass (e.g.
        :class:`pneutune.control.rig.faults.FaultySimRig`).
    **rig_kwargs
        Further arguments of ``rig_class`` (e.g. ``faults``).

    Returns
    -------
    (rig, plant, seed)
    """
    base = plant_cfg if plant_cfg is not None else PlantConfig()
    pcfg = scenario_plant(base, scenario)
    seed_used = pcfg.sim.seed if seed is None else int(seed)
    ref0 = scenario_reference(scenario, pcfg.rig_metadata())[0, 0]
    rig = rig_class(pcfg, x0=float(ref0), seed=seed_used, **rig_kwargs)
    return rig, pcfg, seed_used


__all__ = [
    "HOME_HOLD_S",
    "HOME_MODES",
    "HOME_MOVE_S",
    "START_TOLERANCE",
    "STATUS_FAULT",
    "LoopResult",
    "LoopSettings",
    "ScenarioResult",
    "TimingStats",
    "homing_move",
    "run_loop",
    "run_scenario",
    "scenario_reference",
    "sim_rig_for",
]
