"""The identification run: an excitation protocol a commissioning engineer runs on a new rig.

Like a commercial positioner's "identification run", it needs no tuned controller: every
segment uses either fixed open-loop duties or a proportional position loop designed from the
rig geometry alone (:func:`position_loop`). It only needs the stroke ends, so it runs unchanged
on any rig, simulated or real. Segments, in order, each labelled on ``/experiment/segment``:

1. ``rest``: valves closed, piston at rest (sensor noise, leaks, drift).
2. ``valve`` tests for chamber A with the piston held against the B-side end stop:
   ``approach`` (the position loop moves the piston onto the x_max stop along a ramp at the
   contact speed, :data:`DEFAULT_CONTACT_SPEED` unless asked otherwise, so that the stop's
   cushion takes a gentle contact), ``prepare`` (a_in + b_out fully open press the piston
   onto x_max; b_out stays open so B stays at ambient and the force ``(p_a - p0) A_a >= 0``
   keeps the piston on the stop), then
   ``FULL_DUTY_CYCLES`` full-duty cycles and, for each duty of the sweep, a ``valve_discharge``
   through a_out and a ``valve_charge`` through a_in; then the chamber, charged to supply, rests
   2 s with its valves shut (leak and the constant term D of Eq. 5).
   Each valve thus charges or discharges a fixed, known volume at full duty and over a sweep of
   duties: this gives C, b and the PWM curve.
3. The same for chamber B against the A-side end stop (a_out open, b_in / b_out swept).
4. ``constant_speed``: position-loop ramps at several speeds in both directions (friction).
5. ``acceleration``: position-loop sines of rising frequency whose duties saturate (mass):
   30 % of the stroke, less where that would pass :data:`MAX_SINE_SPEED`.
6. ``rest`` again.

Each part starts with a move of the position loop along a ramp at :data:`TRAVEL_SPEED` from
wherever the piston is (:class:`Move`), so that a part runs on its own (``record --segments``)
and no move is faster than planned. The segments of a part share a :attr:`Segment.group`;
those that may touch an end stop name it in :attr:`Segment.contacts`, and only there does the
supervisor of :mod:`pneutune.control.rig.excitation` let the piston reach the stop.

The position loop updates the duties every control period ``rig.Ts``, as the deployed
controller would; the sensors are logged every ``sample_period`` (default
:data:`IDENT_SAMPLE_PERIOD`, 0.5 ms), as fast as a data-acquisition card reads them. The fast
log is what makes the moving mass identifiable: on the paper's rig the mass shows only as a lag
M/b_v of about 0.3 ms between the pressure force and the motion, which 4 ms samples cannot
resolve (docs/identifiability.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.constants import A_IN, A_OUT, B_IN, B_OUT
from pneutune.control.errors import ExperimentError
from pneutune.control.logs.recording import Recording
from pneutune.control.rig.protocol import Rig

#: Duty sweep of the valve tests (1 first: the full-duty charge/discharge).
DEFAULT_DUTIES: tuple[float, ...] = (1.0, 0.7, 0.5, 0.35, 0.25, 0.18, 0.14, 0.11, 0.08, 0.05)
#: Full-duty charge/discharge cycles per chamber: b (the critical pressure ratio) shows only in
#: the shape of the subsonic part of a charge or a vent, so it is worth a few repetitions.
FULL_DUTY_CYCLES: int = 5
#: Ramp speeds of the friction segments [m/s].
DEFAULT_SPEEDS: tuple[float, ...] = (0.003, 0.006, 0.012, 0.025, 0.05, 0.1)
#: Sine frequencies [Hz] and cycles of the acceleration segments.
DEFAULT_SINES: tuple[tuple[float, int], ...] = ((0.5, 2), (1.0, 3), (2.0, 4), (3.0, 6))
#: Sine amplitude of the acceleration segments, as a fraction of the stroke [-].
SINE_STROKE_FRACTION: float = 0.3
#: Highest peak speed of a sine [m/s], a common rating of standard cylinders and their
#: cushions: the paper's rig (50 mm stroke) reaches 0.28 m/s at 3 Hz with 30 % of its stroke;
#: a longer stroke keeps to this speed with a smaller amplitude (a 1 m stroke would otherwise
#: swing 300 mm at 3 Hz, 5.7 m/s). A lower cap starves the mass estimate of acceleration: at
#: 0.3 m/s a 200 mm stroke's 4 ms log gave a mass 12 % high.
MAX_SINE_SPEED: float = 0.5
#: Speed of the ramp that takes the piston onto an end stop [m/s]: a fifth of what fully open
#: valves reached on the paper's rig (0.17-0.25 m/s), so the stop takes 1/25 of that kinetic
#: energy.
DEFAULT_CONTACT_SPEED: float = 0.05
#: Speed of the moves that start each part of a protocol [m/s].
TRAVEL_SPEED: float = 0.1
#: Time a move holds its target after the ramp [s].
MOVE_SETTLE_S: float = 0.5
#: End stops by name: the side of the stroke and its sign.
STOP_SIDES: dict[str, float] = {"x_min": -1.0, "x_max": 1.0}
#: Sensor logging period of the identification run [s]: 2 kHz, eight samples per 4 ms control
#: period. The mass estimate's scatter over noise seeds was about ±3 % at 0.5 ms and up to
#: ±8 % at 1 ms (docs/identifiability.md).
IDENT_SAMPLE_PERIOD: float = 5.0e-4

Reference = Callable[[float], tuple[float, float, float]]
#: A closed-loop segment's controller: ``(t_rel [s], sensors [x, p_a, p_b, p_s]) -> duties``.
SegmentController = Callable[[float, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Segment:
    """One step of an experiment.

    Attributes
    ----------
    label : str
        Unique, human-readable name (``valve_charge:a_in:0.50``).
    kind : str
        rest | prepare | valve_charge | valve_discharge | constant_speed | acceleration | hold
        (the commissioning run adds burst | brake | coast).
    duration : float
        [s].
    params : dict
        JSON-serialisable description (logged with the label).
    duties : ndarray or None
        Fixed open-loop duties [a_in, a_out, b_in, b_out], or None for the position loop.
    reference : callable or None
        ``t_rel -> (x_r, v_r, a_r)`` for the position loop.
    controller : callable or None
        Factory of a closed-loop controller with its own state: called once at the start of
        the segment, it returns a fresh :data:`SegmentController`, which gives the duties at
        every control instant of a segment without ``reference`` (``duties`` is then unused).
        A fresh controller per run keeps a protocol reusable. A controller with a
        ``reference`` attribute ``(x_r, v_r, a_r)`` has it logged on ``/control/reference``.
    group : str
        The part of the protocol the segment belongs to (``valves:a``, ``friction``, ...):
        what ``record --segments`` selects.
    contacts : tuple of str
        End stops (``x_min``, ``x_max``) the piston may touch in this segment; anywhere else
        the supervisor keeps it inside the stroke's margins.
    """

    label: str
    kind: str
    duration: float
    params: dict[str, Any] = field(default_factory=dict)
    duties: np.ndarray | None = None
    reference: Reference | None = None
    controller: Callable[[], SegmentController] | None = None
    group: str = ""
    contacts: tuple[str, ...] = ()


def mode_duties(u: float) -> np.ndarray:
    """The four duties of a signed command ``u`` in [-1, 1] (the paper's valve modes).

    u > 0 opens a_in and b_out with duty u (mode 1), u < 0 opens a_out and b_in with duty -u
    (mode 2), u = 0 closes all (mode 3).
    """
    d = np.zeros(4)
    if u > 0.0:
        d[A_IN] = d[B_OUT] = u
    elif u < 0.0:
        d[A_OUT] = d[B_IN] = -u
    return d


def position_loop(x: float, x_r: float, band: float) -> np.ndarray:
    """Proportional position loop that needs only the stroke: full duty beyond ``band``.

    ``u = clip((x_r - x) / band, -1, 1)``; u > 0 opens a_in and b_out with duty u (mode 1),
    u < 0 opens a_out and b_in with duty -u (mode 2).

    Parameters
    ----------
    x, x_r : float
        Measured and reference position [m].
    band : float
        Error at which the duty saturates [m].

    Returns
    -------
    ndarray
        The four duties.
    """
    return mode_duties(min(max((x_r - x) / band, -1.0), 1.0))


def valve_duties(**open_: float) -> np.ndarray:
    """The four duties with the named valves open: ``valve_duties(a_in=0.5, b_out=1.0)``."""
    d = np.zeros(4)
    for name, u in open_.items():
        d[{"a_in": A_IN, "a_out": A_OUT, "b_in": B_IN, "b_out": B_OUT}[name]] = u
    return d


class Move:
    """Position loop along a ramp from where the piston is to a target, then holding it.

    The ramp starts at the first position measured (at the segment's start), runs at ``speed``
    and ends at ``target``; :func:`position_loop` tracks it. A target beyond an end stop makes
    an approach: the piston meets the stop at about ``speed`` and the loop then presses it
    there.

    Parameters
    ----------
    target : float
        Where the ramp ends [m].
    speed : float
        Ramp speed [m/s], > 0.
    band : float
        Saturation band of the position loop [m].
    logged : bool
        Expose :attr:`reference` (logged on ``/control/reference``); False for a protocol
        whose logs carry no reference.
    """

    def __init__(self, target: float, speed: float, band: float, logged: bool = True) -> None:
        if not speed > 0.0:
            raise ExperimentError(f"a move's speed must be > 0 m/s, got {speed}")
        self.target = target
        self.speed = speed
        self.band = band
        self.logged = logged
        self.x0: float | None = None
        self._reference = (math.nan, 0.0, 0.0)

    @property
    def reference(self) -> tuple[float, float, float] | None:
        """The last ``(x_r, v_r, a_r)`` [m, m/s, m/s^2], or None when not ``logged``."""
        return self._reference if self.logged else None

    def __call__(self, t_rel: float, y: np.ndarray) -> np.ndarray:
        """The duties at a control instant, from the measured position ``y[0]`` [m]."""
        x = float(y[0])
        if self.x0 is None:
            self.x0 = x
        distance = self.target - self.x0
        travelled = self.speed * t_rel
        if travelled >= abs(distance):
            self._reference = (self.target, 0.0, 0.0)
        else:
            self._reference = (self.x0 + math.copysign(travelled, distance),
                               math.copysign(self.speed, distance), 0.0)
        return position_loop(x, self._reference[0], self.band)


def move_segment(label: str, kind: str, target: float, speed: float, band: float,
                 stroke: float, group: str, params: dict[str, Any] | None = None,
                 contacts: tuple[str, ...] = (), settle: float = MOVE_SETTLE_S,
                 logged: bool = True) -> Segment:
    """A :class:`Move` as a segment, long enough for a whole stroke at ``speed`` and ``settle``.

    Parameters
    ----------
    label, kind : str
        As :class:`Segment`.
    target, speed, band : float
        As :class:`Move` [m, m/s, m].
    stroke : float
        x_max - x_min [m]: the longest move, from anywhere.
    group : str
        The protocol part.
    params : dict, optional
        Logged with the label (``target`` and ``speed`` are added).
    contacts : tuple of str
        End stops the move may touch.
    settle : float
        Time after the longest ramp [s].
    logged : bool
        Log the move's reference (:class:`Move`).
    """
    def factory() -> SegmentController:
        return Move(target, speed, band, logged)

    return Segment(label, kind, stroke / speed + settle,
                   {**(params or {}), "target": target, "speed": speed},
                   controller=factory, group=group, contacts=contacts)


def approach(chamber: str, stop: str, x_min: float, x_max: float, speed: float,
             band: float, logged: bool = True) -> Segment:
    """The gentle move onto an end stop before a valve test.

    The ramp aims ``band`` beyond the stop, so that the position loop ends pressing the piston
    on it; the piston meets the stop at about ``speed`` (the run logs the speed measured).
    """
    target = x_max + band if stop == "x_max" else x_min - band
    return move_segment(f"approach:{chamber}:{stop}", "approach", target, speed, band,
                        x_max - x_min, f"valves:{chamber}",
                        {"chamber": chamber, "end_stop": stop}, contacts=(stop,),
                        logged=logged)


def _valve_block(chamber: str, duties: Sequence[float], x_min: float, x_max: float,
                 contact_speed: float, band: float) -> list[Segment]:
    """Charge/discharge sweep of one chamber with the piston held on the far end stop."""
    if chamber == "a":
        prep = valve_duties(a_in=1.0, b_out=1.0)
        hold, fill, vent, stop = "b_out", "a_in", "a_out", "x_max"
    else:
        prep = valve_duties(a_out=1.0, b_in=1.0)
        hold, fill, vent, stop = "a_out", "b_in", "b_out", "x_min"
    group, contacts = f"valves:{chamber}", (stop,)
    segs = [approach(chamber, stop, x_min, x_max, contact_speed, band),
            Segment(f"prepare:{chamber}", "prepare", 1.5,
                    {"chamber": chamber, "end_stop": stop, "open": [fill, hold]}, prep,
                    group=group, contacts=contacts)]
    sweep = [1.0] * (FULL_DUTY_CYCLES - 1) + list(duties)
    for rep, u in enumerate(sweep):
        t_half = min(max(0.8 / u, 0.8), 2.0)
        tag = f"{u:.2f}" if rep >= FULL_DUTY_CYCLES - 1 else f"{u:.2f}#{rep + 1}"
        for kind, valve in (("valve_discharge", vent), ("valve_charge", fill)):
            segs.append(Segment(
                f"{kind}:{valve}:{tag}", kind, t_half,
                {"chamber": chamber, "valve": valve, "duty": u, "held_open": hold,
                 "end_stop": stop},
                valve_duties(**{valve: u, hold: 1.0}), group=group, contacts=contacts))
    # valves shut with the chamber at supply pressure: what still changes the pressure is the
    # seal leak and the constant term D of Eq. (5)
    segs.append(Segment(f"valve_charge:{fill}:hold", "valve_charge", 1.0,
                        {"chamber": chamber, "valve": fill, "duty": 1.0, "held_open": hold,
                         "end_stop": stop}, valve_duties(**{fill: 1.0, hold: 1.0}),
                        group=group, contacts=contacts))
    segs.append(Segment(f"rest:{chamber}:pressurised", "rest", 2.0,
                        {"chamber": chamber, "held_open": hold, "end_stop": stop},
                        valve_duties(**{hold: 1.0}), group=group, contacts=contacts))
    segs.append(Segment(f"valve_discharge:{vent}:final", "valve_discharge", 1.0,
                        {"chamber": chamber, "valve": vent, "duty": 1.0, "held_open": hold,
                         "end_stop": stop}, valve_duties(**{vent: 1.0, hold: 1.0}),
                        group=group, contacts=contacts))
    return segs


def _hold(x: float, duration: float, label: str, group: str) -> Segment:
    return Segment(label, "hold", duration, {"x": x}, None, lambda t, x=x: (x, 0.0, 0.0),
                   group=group)


def _ramp(x_from: float, x_to: float, speed: float, group: str) -> Segment:
    direction = 1.0 if x_to > x_from else -1.0
    duration = abs(x_to - x_from) / speed

    def ref(t: float) -> tuple[float, float, float]:
        if t >= duration:
            return x_to, 0.0, 0.0
        return x_from + direction * speed * t, direction * speed, 0.0

    return Segment(f"constant_speed:{'+' if direction > 0 else '-'}{speed * 1e3:.0f}mm/s",
                   "constant_speed", duration,
                   {"speed": speed * direction, "x_from": x_from, "x_to": x_to}, None, ref,
                   group=group)


def _sine(mid: float, amp: float, freq: float, cycles: int, group: str) -> Segment:
    w = 2.0 * math.pi * freq

    def ref(t: float) -> tuple[float, float, float]:
        s, c = math.sin(w * t), math.cos(w * t)
        return mid + amp * s, amp * w * c, -amp * w * w * s

    return Segment(f"acceleration:sine:{freq:g}Hz", "acceleration", cycles / freq,
                   {"shape": "sine", "freq": freq, "amplitude": amp, "center": mid}, None, ref,
                   group=group)


def identification_protocol(x_min: float, x_max: float,
                            duties: Sequence[float] = DEFAULT_DUTIES,
                            speeds: Sequence[float] = DEFAULT_SPEEDS,
                            sines: Sequence[tuple[float, int]] = DEFAULT_SINES,
                            contact_speed: float = DEFAULT_CONTACT_SPEED,
                            ) -> list[Segment]:
    """The segments of the identification run for a rig with the given stroke.

    Parameters
    ----------
    x_min, x_max : float
        Stroke ends [m].
    duties : sequence of float
        Duty sweep of the valve tests.
    speeds : sequence of float
        Ramp speeds of the friction segments [m/s].
    sines : sequence of (float, int)
        (frequency [Hz], cycles) of the acceleration segments.
    contact_speed : float
        Speed of the approach onto each end stop [m/s].

    Returns
    -------
    list of Segment
        In the groups ``rest`` (first and last segment), ``valves:a``, ``valves:b``,
        ``friction`` and ``acceleration``.
    """
    if not x_max > x_min:
        raise ExperimentError(f"x_max > x_min must hold, got x_min={x_min}, x_max={x_max}")
    if not (math.isfinite(contact_speed) and contact_speed > 0.0):
        raise ExperimentError(f"the contact speed must be > 0 m/s, got {contact_speed}")
    stroke = x_max - x_min
    band = 0.05 * stroke
    mid = 0.5 * (x_min + x_max)
    lo, hi = x_min + 0.15 * stroke, x_max - 0.15 * stroke
    segs = [Segment("rest:start", "rest", 2.0, {}, np.zeros(4), group="rest")]
    segs += _valve_block("a", duties, x_min, x_max, contact_speed, band)
    segs += _valve_block("b", duties, x_min, x_max, contact_speed, band)
    segs.append(move_segment("hold:start_friction", "hold", lo, TRAVEL_SPEED, band, stroke,
                             "friction", {"x": lo}, settle=1.0))
    for v in speeds:
        travel = min(hi - lo, v * 4.0)
        segs.append(_ramp(lo, lo + travel, v, "friction"))
        segs.append(_hold(lo + travel, 0.4, f"hold:+{v * 1e3:.0f}mm/s", "friction"))
        segs.append(_ramp(lo + travel, lo, v, "friction"))
        segs.append(_hold(lo, 0.4, f"hold:-{v * 1e3:.0f}mm/s", "friction"))
    segs.append(move_segment("hold:start_acceleration", "hold", mid, TRAVEL_SPEED, band,
                             stroke, "acceleration", {"x": mid}))
    for freq, cycles in sines:
        amp = min(SINE_STROKE_FRACTION * stroke, MAX_SINE_SPEED / (2.0 * math.pi * freq))
        segs.append(_sine(mid, amp, freq, cycles, "acceleration"))
    segs.append(_hold(mid, 1.0, "hold:end", "acceleration"))
    segs.append(Segment("rest:end", "rest", 2.0, {}, np.zeros(4), group="rest"))
    return segs


def protocol_samples(segments: Sequence[Segment], Ts: float, per_control: int = 1) -> int:
    """Number of samples the protocol takes.

    Parameters
    ----------
    segments : sequence of Segment
        The protocol.
    Ts : float
        Control period [s].
    per_control : int
        Logged samples per control period.
    """
    return sum(round(s.duration / Ts) for s in segments) * per_control


def samples_per_control(Ts: float, sample_period: float) -> int:
    """Logged samples per control period: ``Ts / sample_period``, which must be an integer.

    Raises
    ------
    ExperimentError
        If ``sample_period`` is not positive, exceeds ``Ts`` or does not divide it.
    """
    if not 0.0 < sample_period <= Ts * (1.0 + 1e-9):
        raise ExperimentError(f"sample_period must lie in (0, rig.Ts = {Ts:g} s], "
                              f"got {sample_period:g} s")
    k = round(Ts / sample_period)
    if abs(k * sample_period - Ts) > 1e-9 * Ts:
        raise ExperimentError(f"sample_period must divide rig.Ts = {Ts:g} s into whole "
                              f"samples, got {sample_period:g} s")
    return k


def run_protocol(rig: Rig, segments: Sequence[Segment], band: float,
                 record_truth: bool = True, per_control: int = 1,
                 progress: Callable[[int, int], None] | None = None) -> Recording:
    """Run segments on a rig, unsupervised, and record everything (contract 1 topics).

    :func:`pneutune.control.rig.excitation.execute_protocol` without a supervisor, for tests
    and studies on simulated rigs; ``record`` and ``simulate --experiment`` run it supervised.

    Parameters
    ----------
    rig : Rig
        The rig, sampled every ``rig.Ts``.
    segments : sequence of Segment
        The protocol.
    band : float
        Saturation band of the position loop [m].
    record_truth : bool
        Record ``/sim/truth``; the rig must then be a
        :class:`~pneutune.control.rig.protocol.SimulatedRig`.
    per_control : int
        Rig samples per control period.
    progress : callable, optional
        Called as ``progress(done, total)`` every few hundred samples.

    Returns
    -------
    Recording
    """
    from pneutune.control.rig.excitation import execute_protocol

    report = None if progress is None else (lambda done, total, _label: progress(done, total))
    return execute_protocol(rig, segments, band, record_truth=record_truth,
                            per_control=per_control, progress=report).recording


def simulate_identification(plant_cfg: Any, seed: int | None = None,
                            progress: Callable[[int, int], None] | None = None,
                            sample_period: float = IDENT_SAMPLE_PERIOD) -> Recording:
    """Run the default identification protocol on the simulated rig.

    Parameters
    ----------
    plant_cfg : PlantConfig
        The simulated plant.
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.
    progress : callable, optional
        ``progress(done, total)`` callback.
    sample_period : float
        Sensor logging period [s]; it must divide ``rig.Ts`` (the control period of the
        position loop). ``rig.Ts`` itself gives a log at the controller's rate.

    Returns
    -------
    Recording
        Sensors, duties, reference, ``/sim/truth`` and segment labels, every
        ``sample_period``. Save it with ``plant_cfg.rig_metadata()``: the log's ``rig.Ts``
        stays the control period, and the run metadata carry ``sample_period``.
    """
    from pneutune.control.rig.excitation import record_on_sim

    report = None if progress is None else (lambda done, total, _label: progress(done, total))
    return record_on_sim("identification", plant_cfg, seed=seed, sample_period=sample_period,
                         progress=report, record_truth=True).recording
