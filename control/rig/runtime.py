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

A piston resting elsewhere is first moved to x_r(0) under the same controller and supervisor
(:mod:`~pneutune.control.rig.homing`); the loop then starts from the reading the homing decision
took (``first``) and on the rig's clock shifted by the move (``clock_offset``). Pacing to wall
time (``realtime``) and the timing statistics are :mod:`~pneutune.control.rig.pacing`'s;
:mod:`~pneutune.control.rig.scenario_run` runs a whole scenario and computes its metrics.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pneutune.control.law.darc import MEAS_SIZE, S_THETA, init_state, step_into
from pneutune.control.logs.recording import Recording
from pneutune.control.rig.pacing import Pacer, TimingStats
from pneutune.control.rig.protocol import Rig, SimulatedRig
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES, Event, Supervisor
from pneutune.control.rig.wire import RigIOError
from pneutune.control.sim.closed_loop import LOG_INDEX

#: Largest distance between the first position reading and x_r(0) [m].
START_TOLERANCE = 1.0e-3


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
        Pace the loop to wall time (:class:`~pneutune.control.rig.pacing.Pacer`).
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


def warm_up(cfg: np.ndarray, ref: np.ndarray,
            law: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], int] = step_into,
            ) -> None:
    """One control step on a scratch state, so that loading the compiled step does not delay
    the first sample of a paced run.

    Parameters
    ----------
    cfg : (CFG_SIZE,) float64
        The packed controller config.
    ref : (N, 3) float64
        The reference the loop will track; its first row is the scratch measurement's (nothing
        runs for an empty reference).
    law : callable
        The control step, with the signature of :func:`~pneutune.control.law.darc.step_into`.
    """
    if ref.shape[0] == 0:
        return
    scratch = init_state(cfg, float(ref[0, 0]), 2.0e5, 2.0e5)
    meas = np.zeros(MEAS_SIZE)
    meas[1] = ref[0, 0]
    meas[2:5] = (2.0e5, 2.0e5, 6.0e5)
    meas[5:8] = ref[0]
    law(scratch, meas, cfg, np.empty(4))


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

    def sample(self, k: int, sensors: np.ndarray, duties: np.ndarray, state: np.ndarray,
               t: float = 0.0, sample_times: np.ndarray | None = None) -> None:
        """Record sample ``k``: its readings, the duties written and the controller state;
        with ``sample_times`` (``rig.sample_times()`` on the loop's clock, ``t`` the sample's
        time there) also the readings' ages."""
        self.sensors[k] = sensors
        self.rec.sample_ages(k, t, sample_times)
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
        :func:`~pneutune.control.rig.scenario_run.run_scenario`, to decide on homing), or the
        error that reading raised: used for k = 0 instead of reading again (a rig_io fault for
        an error).
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
    pacer = Pacer(n, Ts, opts.realtime, opts.spin_s)
    law = step_into if opts.law is None else opts.law
    warm_up(cfg, ref, law)
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
            log.sample(k, s, duties, cs, t, stamps)
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


__all__ = [
    "START_TOLERANCE",
    "LoopResult",
    "LoopSettings",
    "run_loop",
    "warm_up",
]
