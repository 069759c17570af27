"""The identification run: an excitation protocol a commissioning engineer runs on a new rig.

Like a commercial positioner's "identification run", it needs no tuned controller: every
segment uses either fixed open-loop duties or a proportional position loop designed from the
rig geometry alone (:func:`position_loop`). It only needs the stroke ends, so it runs unchanged
on any rig, simulated or real. Segments, in order, each labelled on ``/experiment/segment``:

1. ``rest``: valves closed, piston at rest (sensor noise, leaks, drift).
2. ``valve`` tests for chamber A with the piston held against the B-side end stop:
   ``prepare`` (a_in + b_out fully open drive the piston to x_max; b_out stays open so B stays at
   ambient and the force ``(p_a - p0) A_a >= 0`` keeps the piston on the stop), then
   ``FULL_DUTY_CYCLES`` full-duty cycles and, for each duty of the sweep, a ``valve_discharge``
   through a_out and a ``valve_charge`` through a_in; then the chamber, charged to supply, rests
   2 s with its valves shut (leak and the constant term D of Eq. 5).
   Each valve thus charges or discharges a fixed, known volume at full duty and over a sweep of
   duties: this gives C, b and the PWM curve.
3. The same for chamber B against the A-side end stop (a_out open, b_in / b_out swept).
4. ``constant_speed``: position-loop ramps at several speeds in both directions (friction).
5. ``acceleration``: position-loop sines of rising frequency whose duties saturate (mass).
6. ``rest`` again.

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
from pneutune.control.rig.protocol import Rig, SimulatedRig

#: Duty sweep of the valve tests (1 first: the full-duty charge/discharge).
DEFAULT_DUTIES: tuple[float, ...] = (1.0, 0.7, 0.5, 0.35, 0.25, 0.18, 0.14, 0.11, 0.08, 0.05)
#: Full-duty charge/discharge cycles per chamber: b (the critical pressure ratio) shows only in
#: the shape of the subsonic part of a charge or a vent, so it is worth a few repetitions.
FULL_DUTY_CYCLES: int = 5
#: Ramp speeds of the friction segments [m/s].
DEFAULT_SPEEDS: tuple[float, ...] = (0.003, 0.006, 0.012, 0.025, 0.05, 0.1)
#: Sine frequencies [Hz] and cycles of the acceleration segments.
DEFAULT_SINES: tuple[tuple[float, int], ...] = ((0.5, 2), (1.0, 3), (2.0, 4), (3.0, 6))
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
        A fresh controller per run keeps a protocol reusable.
    """

    label: str
    kind: str
    duration: float
    params: dict[str, Any] = field(default_factory=dict)
    duties: np.ndarray | None = None
    reference: Reference | None = None
    controller: Callable[[], SegmentController] | None = None


def mode_duties(u: float) -> np.ndarray:
    """The four duties of a signed command ``u`` in [-1, 1] (the modes of DESIGN.md).

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


def _valve_block(chamber: str, duties: Sequence[float]) -> list[Segment]:
    """Charge/discharge sweep of one chamber with the piston held on the far end stop."""
    if chamber == "a":
        prep = valve_duties(a_in=1.0, b_out=1.0)
        hold, fill, vent, stop = "b_out", "a_in", "a_out", "x_max"
    else:
        prep = valve_duties(a_out=1.0, b_in=1.0)
        hold, fill, vent, stop = "a_out", "b_in", "b_out", "x_min"
    segs = [Segment(f"prepare:{chamber}", "prepare", 1.5,
                    {"chamber": chamber, "end_stop": stop, "open": [fill, hold]}, prep)]
    sweep = [1.0] * (FULL_DUTY_CYCLES - 1) + list(duties)
    for rep, u in enumerate(sweep):
        t_half = min(max(0.8 / u, 0.8), 2.0)
        tag = f"{u:.2f}" if rep >= FULL_DUTY_CYCLES - 1 else f"{u:.2f}#{rep + 1}"
        for kind, valve in (("valve_discharge", vent), ("valve_charge", fill)):
            segs.append(Segment(
                f"{kind}:{valve}:{tag}", kind, t_half,
                {"chamber": chamber, "valve": valve, "duty": u, "held_open": hold,
                 "end_stop": stop},
                valve_duties(**{valve: u, hold: 1.0})))
    # valves shut with the chamber at supply pressure: what still changes the pressure is the
    # seal leak and the constant term D of Eq. (5)
    segs.append(Segment(f"valve_charge:{fill}:hold", "valve_charge", 1.0,
                        {"chamber": chamber, "valve": fill, "duty": 1.0, "held_open": hold,
                         "end_stop": stop}, valve_duties(**{fill: 1.0, hold: 1.0})))
    segs.append(Segment(f"rest:{chamber}:pressurised", "rest", 2.0,
                        {"chamber": chamber, "held_open": hold, "end_stop": stop},
                        valve_duties(**{hold: 1.0})))
    segs.append(Segment(f"valve_discharge:{vent}:final", "valve_discharge", 1.0,
                        {"chamber": chamber, "valve": vent, "duty": 1.0, "held_open": hold,
                         "end_stop": stop}, valve_duties(**{vent: 1.0, hold: 1.0})))
    return segs


def _hold(x: float, duration: float, label: str) -> Segment:
    return Segment(label, "hold", duration, {"x": x}, None, lambda t, x=x: (x, 0.0, 0.0))


def _ramp(x_from: float, x_to: float, speed: float) -> Segment:
    direction = 1.0 if x_to > x_from else -1.0
    duration = abs(x_to - x_from) / speed

    def ref(t: float) -> tuple[float, float, float]:
        if t >= duration:
            return x_to, 0.0, 0.0
        return x_from + direction * speed * t, direction * speed, 0.0

    return Segment(f"constant_speed:{'+' if direction > 0 else '-'}{speed * 1e3:.0f}mm/s",
                   "constant_speed", duration,
                   {"speed": speed * direction, "x_from": x_from, "x_to": x_to}, None, ref)


def _sine(mid: float, amp: float, freq: float, cycles: int) -> Segment:
    w = 2.0 * math.pi * freq

    def ref(t: float) -> tuple[float, float, float]:
        s, c = math.sin(w * t), math.cos(w * t)
        return mid + amp * s, amp * w * c, -amp * w * w * s

    return Segment(f"acceleration:sine:{freq:g}Hz", "acceleration", cycles / freq,
                   {"shape": "sine", "freq": freq, "amplitude": amp, "center": mid}, None, ref)


def identification_protocol(x_min: float, x_max: float,
                            duties: Sequence[float] = DEFAULT_DUTIES,
                            speeds: Sequence[float] = DEFAULT_SPEEDS,
                            sines: Sequence[tuple[float, int]] = DEFAULT_SINES,
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

    Returns
    -------
    list of Segment
    """
    if not x_max > x_min:
        raise ExperimentError(f"x_max > x_min must hold, got x_min={x_min}, x_max={x_max}")
    stroke = x_max - x_min
    mid = 0.5 * (x_min + x_max)
    lo, hi = x_min + 0.15 * stroke, x_max - 0.15 * stroke
    segs = [Segment("rest:start", "rest", 2.0, {}, np.zeros(4))]
    segs += _valve_block("a", duties)
    segs += _valve_block("b", duties)
    segs.append(_hold(lo, 1.5, "hold:start_friction"))
    for v in speeds:
        travel = min(hi - lo, v * 4.0)
        segs.append(_ramp(lo, lo + travel, v))
        segs.append(_hold(lo + travel, 0.4, f"hold:+{v * 1e3:.0f}mm/s"))
        segs.append(_ramp(lo + travel, lo, v))
        segs.append(_hold(lo, 0.4, f"hold:-{v * 1e3:.0f}mm/s"))
    segs.append(_hold(mid, 1.0, "hold:start_acceleration"))
    for freq, cycles in sines:
        segs.append(_sine(mid, 0.3 * stroke, freq, cycles))
    segs.append(_hold(mid, 1.0, "hold:end"))
    segs.append(Segment("rest:end", "rest", 2.0, {}, np.zeros(4)))
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
    """Run segments on a rig and record everything (contract 1 topics).

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
        Rig samples per control period: the duties change only every ``per_control`` samples,
        and every segment lasts a whole number of control periods.
    progress : callable, optional
        Called as ``progress(done, total)`` every few hundred samples.

    Returns
    -------
    Recording

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
    control_Ts = rig.Ts * per_control
    n_total = protocol_samples(segments, control_Ts, per_control)
    rec = Recording(n_total, rig.Ts, truth=truth is not None, reference=True)
    k = 0
    duties = np.zeros(4)
    for seg in segments:
        n_seg = round(seg.duration / control_Ts) * per_control
        rec.segment(k * rig.Ts, seg.label, seg.kind, seg.params)
        controller = seg.controller() if seg.controller is not None else None
        for j in range(n_seg):
            y = rig.read()
            rec.sensors_[k] = y
            if truth is not None:
                rec.truth_[k] = truth()
            control = j % per_control == 0
            if seg.reference is not None:
                xr, vr, ar = seg.reference(j * rig.Ts)
                rec.reference_[k] = (xr, vr, ar)
                if control:
                    duties = position_loop(float(y[0]), xr, band)
            elif control and controller is not None:
                duties = controller(j * rig.Ts, y)
            elif control:
                duties = seg.duties if seg.duties is not None else np.zeros(4)
            rec.duties_[k] = duties
            if control:
                rig.write(duties)
            rig.advance()
            k += 1
            if progress is not None and k % 2000 == 0:
                progress(k, n_total)
    if progress is not None:
        progress(k, n_total)
    return rec


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
    from pneutune.control.rig.simrig import SimRig

    rig_cfg = plant_cfg.rig
    per_control = samples_per_control(rig_cfg.Ts, sample_period)
    segments = identification_protocol(rig_cfg.x_min, rig_cfg.x_max)
    fast = plant_cfg.with_updates({"rig": {"Ts": rig_cfg.Ts / per_control}})
    rig = SimRig(fast, seed=seed)
    band = 0.05 * (rig_cfg.x_max - rig_cfg.x_min)
    return run_protocol(rig, segments, band=band, record_truth=True, per_control=per_control,
                        progress=progress)
