"""Running an excitation protocol on any rig, supervised: what ``record`` and ``simulate
--experiment`` run.

:func:`execute_protocol` plays the segments of a protocol
(:mod:`~pneutune.control.rig.identification_run`, :mod:`~pneutune.control.rig.commissioning_run`)
against a :class:`~pneutune.control.rig.protocol.Rig`, hardware or simulated, and records every
sample. The duties change every control period (the rig block's ``rig.Ts``); the sensors are
read and logged every sample of the rig (its ``Ts``, which divides ``rig.Ts``).

Safety, as in ``deploy``: the supervisor (:class:`~pneutune.control.rig.supervisor.Supervisor`)
checks every sample before its duties are computed (NaN, out-of-range or stale sensors, supply
loss, over-pressure, the stroke limits). A fault writes the fail-safe duties in the same sample,
is logged on ``/rig/events`` and stops the run. The stroke limits of :func:`protocol_settings`
keep the piston :data:`DEFAULT_STROKE_MARGIN` of the stroke away from both end stops, except
where the protocol touches a stop on purpose: in a segment that names it in
:attr:`~pneutune.control.rig.identification_run.Segment.contacts`, and afterwards until the
piston has left the stop's margin (it starts there after a valve test, or when it rests on a
stop at the start). A Ctrl-C (``KeyboardInterrupt``) is handled the same way: fail-safe duties,
an ``interrupted`` event, the run stops. Either way the recording keeps the completed segments
only (:attr:`ProtocolRun.recording`), a valid log for ``identify``.

The segments come from :mod:`~pneutune.control.rig.excitation_plan` (the protocol by name, the
``--segments`` selection and its lead-ins, the stroke check). Every approach onto an end stop
is measured (:func:`~pneutune.control.rig.contacts.measure_contacts`: the speed of the piston
over the :data:`~pneutune.control.rig.contacts.CONTACT_WINDOW` before it reached the stop) and
logged as an ``end_stop_contact`` event (a ``contact_speed`` warning when it exceeds twice the
planned speed).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.errors import ExperimentError
from pneutune.control.logs.recording import Recording
from pneutune.control.rig.contacts import CONTACT_WARN_FACTOR, Contact, measure_contacts
from pneutune.control.rig.excitation_plan import (
    check_stroke,
    default_sample_period,
    experiment_protocol,
    protocol_band,
    select_segments,
)
from pneutune.control.rig.identification_run import (
    DEFAULT_CONTACT_SPEED,
    Segment,
    position_loop,
    samples_per_control,
)
from pneutune.control.rig.protocol import Rig, SimulatedRig
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES, Event, Supervisor, SupervisorSettings
from pneutune.control.rig.wire import RigIOError

#: Margin the supervisor keeps between the piston and each end stop outside the planned
#: contacts, as a fraction of the stroke (1 mm on a 50 mm stroke). The protocols move within
#: 10-90 % of the stroke.
DEFAULT_STROKE_MARGIN: float = 0.02
#: Highest chamber pressure allowed, above the rig block's supply pressure [Pa]: a closed
#: chamber that a moving piston compresses may pass the supply a little; a regulator that
#: fails open does by far more.
DEFAULT_P_MAX_ABOVE_SUPPLY: float = 1.0e5
#: Longest sensor silence [s]: five 4 ms control periods, as in the paper's controller.yaml.
DEFAULT_SENSOR_TIMEOUT: float = 0.02
#: Event codes of a protocol run (beside the supervisor's fault codes).
EVENT_CODES: tuple[str, ...] = ("end_stop_contact", "contact_speed", "interrupted", "rig_io")

#: ``progress(done, total, label)``: samples done, samples in all, the current segment's label.
Progress = Callable[[int, int, str], None]


def protocol_settings(rig_meta: Mapping[str, Any], *, margin: float = DEFAULT_STROKE_MARGIN,
                      p_max: float | None = None,
                      sensor_timeout_s: float = DEFAULT_SENSOR_TIMEOUT) -> SupervisorSettings:
    """The supervisor's thresholds for an excitation protocol on a rig, from its rig block.

    A protocol runs before any controller exists, so the limits come from the rig block:
    the stroke less ``margin`` at each end, the supply pressure plus
    :data:`DEFAULT_P_MAX_ABOVE_SUPPLY`, the model's supply for the supply-loss rule.

    Parameters
    ----------
    rig_meta : mapping
        The rig block (``x_min``, ``x_max``, ``p0``, ``p_s``).
    margin : float
        Margin from each end stop, as a fraction of the stroke, in [0, 0.1].
    p_max : float, optional
        Highest chamber pressure [Pa abs]; default ``p_s`` + :data:`DEFAULT_P_MAX_ABOVE_SUPPLY`.
    sensor_timeout_s : float
        Longest sensor silence [s].

    Returns
    -------
    SupervisorSettings

    Raises
    ------
    ExperimentError
        A margin outside [0, 0.1] or a ``p_max`` not above the supply.
    """
    if not 0.0 <= margin <= 0.1:
        raise ExperimentError(f"the stroke margin must lie in [0, 0.1] of the stroke, got {margin}")
    x_min, x_max = float(rig_meta["x_min"]), float(rig_meta["x_max"])
    p0, p_s = float(rig_meta["p0"]), float(rig_meta["p_s"])
    limit = p_s + DEFAULT_P_MAX_ABOVE_SUPPLY if p_max is None else float(p_max)
    if not (math.isfinite(limit) and limit > p_s):
        raise ExperimentError(f"p_max must be above the rig's supply p_s = {p_s:g} Pa, got "
                              f"{limit:g} Pa")
    m = margin * (x_max - x_min)
    wide = (-1.0e9,) * 6, (1.0e9,) * 6  # no θ̂ in a protocol: its warnings never fire
    return SupervisorSettings(x_min=x_min + m, x_max=x_max - m, p_max=limit,
                              sensor_timeout_s=sensor_timeout_s, p0=p0, p_s_model=p_s,
                              theta_min=wide[0], theta_max=wide[1],
                              x_span_margin=0.01 + m)


@dataclass
class ProtocolRun:
    """What :func:`execute_protocol` produced.

    Attributes
    ----------
    recording : Recording
        Every sample of the completed segments (all of them when the run completed), the
        labels of those segments and every event (contacts, the fault).
    segments : list of Segment
        The segments that were to run.
    completed : int
        How many of them completed.
    fault : Event or None
        The supervisor's fault, the ``rig_io`` fault of a rig that failed, or the
        ``interrupted`` event of a Ctrl-C.
    contacts : list of Contact
        The end-stop contacts measured.
    samples_run : int
        Samples run, the interrupted segment's included.
    """

    recording: Recording
    segments: list[Segment]
    completed: int
    fault: Event | None = None
    contacts: list[Contact] = field(default_factory=list)
    samples_run: int = 0

    @property
    def interrupted(self) -> bool:
        """Stopped by a Ctrl-C."""
        return self.fault is not None and self.fault.code == "interrupted"

    @property
    def complete(self) -> bool:
        """Every segment ran."""
        return self.completed == len(self.segments)

    @property
    def missing(self) -> list[str]:
        """Labels of the segments that did not complete."""
        return [s.label for s in self.segments[self.completed:]]


class _StrokeGuard:
    """The supervisor's stroke limits, relaxed on the side of a planned contact.

    A side is relaxed (its limit moved out to the end stop plus the margin again) during a
    segment that names its stop, and stays relaxed until the piston is back inside the strict
    limit; a piston resting beyond a strict limit at the start relaxes that side too.
    """

    def __init__(self, supervisor: Supervisor, rig_meta: Mapping[str, Any]) -> None:
        self.supervisor = supervisor
        self.strict = supervisor.settings
        out = self.strict.x_min - float(rig_meta["x_min"])  # the margin
        self.loose = {"x_min": float(rig_meta["x_min"]) - out,
                      "x_max": float(rig_meta["x_max"]) + out}
        self.relaxed: set[str] = set()
        self.segment_contacts: tuple[str, ...] = ()

    def segment(self, contacts: tuple[str, ...]) -> None:
        self.segment_contacts = contacts
        self._update(self.relaxed | set(contacts))

    def sample(self, x: float) -> None:
        """Tighten a side the piston has left; relax one it rests beyond at the first sample."""
        relaxed = set(self.relaxed)
        for side in tuple(relaxed):
            inside = x >= self.strict.x_min if side == "x_min" else x <= self.strict.x_max
            if inside and math.isfinite(x) and side not in self.segment_contacts:
                relaxed.discard(side)
        if relaxed != self.relaxed:
            self._update(relaxed)

    def start(self, x: float) -> None:
        if not math.isfinite(x):
            return
        relaxed = set(self.relaxed)
        if x < self.strict.x_min:
            relaxed.add("x_min")
        if x > self.strict.x_max:
            relaxed.add("x_max")
        self._update(relaxed)

    def _update(self, relaxed: set[str]) -> None:
        self.relaxed = relaxed
        s = self.strict
        self.supervisor.settings = dataclasses.replace(
            s, x_min=self.loose["x_min"] if "x_min" in relaxed else s.x_min,
            x_max=self.loose["x_max"] if "x_max" in relaxed else s.x_max)


def execute_protocol(rig: Rig, segments: Sequence[Segment], band: float, *,
                     supervisor: Supervisor | None = None,
                     fail_safe: tuple[float, float, float, float] = FAIL_SAFE_DUTIES,
                     per_control: int | None = None, record_truth: bool = False,
                     progress: Progress | None = None) -> ProtocolRun:
    """Run segments on a rig, supervised, and record everything (contract 1 topics).

    Parameters
    ----------
    rig : Rig
        The rig, sampled every ``rig.Ts``. It is not closed here.
    segments : sequence of Segment
        The protocol (or the part of it to run,
        :func:`~pneutune.control.rig.excitation_plan.select_segments`).
    band : float
        Saturation band of the position loop of reference segments [m].
    supervisor : Supervisor, optional
        The safety supervisor (:func:`protocol_settings`), reset here; None runs unsupervised
        (tests, benchmarks).
    fail_safe : 4 floats
        Duties written on a fault or an interrupt.
    per_control : int, optional
        Rig samples per control period; default ``rig_metadata()["Ts"] / rig.Ts``. The duties
        change only every ``per_control`` samples, and every segment lasts a whole number of
        control periods.
    record_truth : bool
        Record ``/sim/truth``; the rig must then be a
        :class:`~pneutune.control.rig.protocol.SimulatedRig`.
    progress : callable, optional
        ``progress(done, total, label)`` every few hundred samples and at each segment.

    Returns
    -------
    ProtocolRun

    Raises
    ------
    TypeError
        ``record_truth`` for a rig that is not a ``SimulatedRig``.
    """
    truth: Callable[[], np.ndarray] | None = None
    if record_truth:
        if not isinstance(rig, SimulatedRig):
            raise TypeError(f"record_truth needs a SimulatedRig (one with truth()), got "
                            f"{type(rig).__name__}")
        truth = rig.truth
    rig_meta = dict(rig.rig_metadata())
    Ts = float(rig.Ts)
    if per_control is None:
        per_control = samples_per_control(float(rig_meta["Ts"]), Ts)
    control_Ts = Ts * per_control
    lengths = [round(s.duration / control_Ts) * per_control for s in segments]
    n_total = sum(lengths)
    rec = Recording(n_total, Ts, truth=truth is not None, reference=True)
    guard = None
    if supervisor is not None:
        supervisor.reset()
        guard = _StrokeGuard(supervisor, rig_meta)
    fs = np.asarray(fail_safe, dtype=np.float64)
    k = 0
    completed = 0
    ends: list[int] = []
    fault: Event | None = None
    duties = np.zeros(4)
    label = segments[0].label if segments else ""
    try:
        for seg, n_seg in zip(segments, lengths, strict=True):
            label = seg.label
            rec.segment(k * Ts, seg.label, seg.kind, seg.params)
            if guard is not None:
                guard.segment(seg.contacts)
            if progress is not None:
                progress(k, n_total, label)
            controller = seg.controller() if seg.controller is not None else None
            for j in range(n_seg):
                t = k * Ts
                try:
                    y = rig.read()
                    stamps = rig.sample_times()
                except RigIOError as exc:
                    fault = Event(t, "error", "rig_io", f"reading the rig failed: {exc}")
                    break
                if guard is not None and supervisor is not None:
                    if k == 0:
                        guard.start(float(y[0]))
                    guard.sample(float(y[0]))
                    fault = supervisor.check_sensors(t, y, stamps)
                    if fault is not None:
                        break
                rec.sensors_[k] = y
                rec.sample_ages(k, t, stamps)
                if truth is not None:
                    rec.truth_[k] = truth()
                control = j % per_control == 0
                if seg.reference is not None:
                    xr, vr, ar = seg.reference(j * Ts)
                    rec.reference_[k] = (xr, vr, ar)
                    if control:
                        duties = position_loop(float(y[0]), xr, band)
                elif controller is not None:
                    if control:
                        duties = controller(j * Ts, y)
                    ref = getattr(controller, "reference", None)
                    if ref is not None:
                        rec.reference_[k] = ref
                elif control:
                    duties = seg.duties if seg.duties is not None else np.zeros(4)
                rec.duties_[k] = duties
                try:
                    if control:
                        rig.write(duties)
                    rig.advance()
                except RigIOError as exc:
                    fault = Event(t, "error", "rig_io", f"the rig failed: {exc}")
                    k += 1
                    break
                k += 1
                if progress is not None and k % 2000 == 0:
                    progress(k, n_total, label)
            if fault is not None:
                break
            completed += 1
            ends.append(k)
    except KeyboardInterrupt:
        fault = Event(k * Ts, "error", "interrupted",
                      f"interrupted (Ctrl-C) in segment {label} at t={k * Ts:.4f} s")
    samples_run = k
    if fault is not None:
        try:
            rig.write(fs)
            done = f"; fail-safe: valves [a_in, a_out, b_in, b_out] = {fs.tolist()}"
        except RigIOError as exc:
            done = f"; writing the fail-safe duties failed too ({exc})"
        fault = Event(fault.t, fault.level, fault.code,
                      f"{fault.message}{done}; the log keeps the {completed} completed "
                      f"segment(s) of {len(segments)}")
        rec.truncate(ends[-1] if ends else 0)
        del rec.segments_[completed:]
    if progress is not None:
        progress(samples_run, n_total, label)
    contacts = measure_contacts(rec, list(segments)[:completed])
    for c in contacts:
        fast = c.speed > CONTACT_WARN_FACTOR * c.planned
        rec.event(c.t, "warning" if fast else "info",
                  "contact_speed" if fast else "end_stop_contact",
                  f"the piston reached the {c.stop} stop at {c.speed * 1e3:.1f} mm/s "
                  f"({c.segment}, planned {c.planned * 1e3:.0f} mm/s)"
                  + (": faster than planned; lower --contact-speed" if fast else ""))
    if fault is not None:
        rec.event(fault.t, fault.level, fault.code, fault.message)
    return ProtocolRun(rec, list(segments), completed, fault, contacts, samples_run)


def record_protocol(rig: Rig, name: str, *, segments: str | Sequence[str] | None = None,
                    contact_speed: float = DEFAULT_CONTACT_SPEED,
                    settings: SupervisorSettings | None = None, supervised: bool = True,
                    fail_safe: tuple[float, float, float, float] = FAIL_SAFE_DUTIES,
                    record_truth: bool = False,
                    progress: Progress | None = None) -> ProtocolRun:
    """Run a named protocol (or the part ``segments`` selects) on a rig, supervised.

    Parameters
    ----------
    rig : Rig
        The rig; its rig block gives the stroke and the control period, its ``Ts`` the sample
        period.
    name : {"identification", "commissioning"}
        The protocol.
    segments : str or sequence of str, optional
        ``--segments`` patterns (:func:`~pneutune.control.rig.excitation_plan.select_segments`);
        default the whole protocol.
    contact_speed : float
        Speed of the approaches onto the end stops [m/s].
    settings : SupervisorSettings, optional
        The supervisor's thresholds; default :func:`protocol_settings` of the rig block.
    supervised : bool
        Run the supervisor (False only for studies on a simulated rig).
    fail_safe : 4 floats
        Duties on a fault or an interrupt.
    record_truth : bool
        Record ``/sim/truth`` (a simulated rig).
    progress : callable, optional
        ``progress(done, total, label)``.

    Returns
    -------
    ProtocolRun
    """
    rig_meta = rig.rig_metadata()
    chosen = select_segments(experiment_protocol(name, rig_meta, contact_speed=contact_speed),
                             segments, rig_meta)
    check_stroke(chosen, rig_meta)
    sup = None
    if supervised:
        sup = Supervisor(settings if settings is not None else protocol_settings(rig_meta))
    return execute_protocol(rig, chosen, protocol_band(rig_meta), supervisor=sup,
                            fail_safe=fail_safe, record_truth=record_truth, progress=progress)


def record_on_sim(name: str, plant_cfg: Any, *, seed: int | None = None,
                  sample_period: float | None = None, x0: float | None = None,
                  record_truth: bool = True, progress: Progress | None = None,
                  **kwargs: Any) -> ProtocolRun:
    """:func:`record_protocol` on the simulated rig in process.

    Parameters
    ----------
    name : {"identification", "commissioning"}
        The protocol.
    plant_cfg : PlantConfig
        The simulated plant.
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.
    sample_period : float, optional
        Sample period [s], dividing ``rig.Ts``; default
        :func:`~pneutune.control.rig.excitation_plan.default_sample_period`.
    x0 : float, optional
        Where the piston rests at the start [m]; default mid-stroke.
    record_truth : bool
        Record ``/sim/truth``.
    progress : callable, optional
        ``progress(done, total, label)``.
    **kwargs
        Further arguments of :func:`record_protocol` (``segments``, ``contact_speed``, ...).

    Returns
    -------
    ProtocolRun
        Its recording is saved with ``plant_cfg.rig_metadata()``.
    """
    from pneutune.control.rig.simrig import SimRig

    control_Ts = float(plant_cfg.rig.Ts)
    period = default_sample_period(name, control_Ts) if sample_period is None else sample_period
    samples_per_control(control_Ts, period)  # the check, before the rig is built
    rig = SimRig(plant_cfg, x0=x0, seed=seed, sample_period=period)
    return record_protocol(rig, name, record_truth=record_truth, progress=progress, **kwargs)


__all__ = [
    "DEFAULT_P_MAX_ABOVE_SUPPLY",
    "DEFAULT_SENSOR_TIMEOUT",
    "DEFAULT_STROKE_MARGIN",
    "EVENT_CODES",
    "Progress",
    "ProtocolRun",
    "execute_protocol",
    "protocol_settings",
    "record_on_sim",
    "record_protocol",
]
