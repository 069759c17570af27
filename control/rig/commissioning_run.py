"""The commissioning run: a second excitation protocol, unlike the identification run.

A commissioning engineer with another vendor's tools excites a new rig differently from
:mod:`~pneutune.control.rig.identification_run`: staircases instead of charge/vent pairs, a
velocity loop instead of a position loop, open-loop bursts instead of sines, and a log at the
control rate without any simulator truth. ``identify`` must work on such a log too (any
honest contract-1 log; a test on data one did not design oneself), so this protocol is
deliberately not
the identification run re-sampled. It needs only the stroke ends and the control period
``Ts``, and every duty changes only at a control instant. Segments, in order, each labelled
on ``/experiment/segment``:

1. ``rest:start`` (1 s, valves closed): sensor noise and offsets at rest.
2. Valve staircases (:func:`valve_staircases`, 17.6 s), one valve at a time, the piston held on
   an end stop. Each staircase climbs through :data:`STAIR_DUTIES` without returning to zero,
   from a known pressure: ambient for a charging valve, supply for an exhausting one. The
   chamber under test is the one that pushes the piston into its stop and the other chamber
   is held open to ambient, so the net force ``(p - p0) A >= 0`` keeps the piston on the stop
   and the volume known. A staircase shows one valve's flow over the pressure range at rising
   duties: C, b, and the PWM curve with its dead zone (the lowest duty is below the default
   valves' minimum pulse). A charging staircase reaches supply before its last steps; the
   exhausting one carries the high duties down to ambient.
3. Constant-velocity moves at :data:`SPEEDS` in both directions (:func:`velocity_moves`,
   46.8 s) under :class:`VelocityLoop`, a PI velocity loop with a speed feedforward: friction
   (the Coulomb level, the viscous slope, stick-slip at the lowest speed) at steady speeds
   rather than along position-loop ramps.
4. Full-duty bursts with braking pulses (:func:`bursts`, 9.6 s): from a hold near one end, a
   mode fully open for a burst of :data:`BURSTS`, then the opposite mode for a shorter
   braking pulse, then all valves closed while the piston coasts and sticks. Fast pressure
   transients with the valves fully open, accelerations, and closed chambers acting as
   springs, where the identification run uses sines.
5. ``rest:end`` (1 s, valves closed).

The closed-loop parts (the holds and the velocity loop) are :attr:`Segment.controller`
factories designed from the stroke and ``Ts`` alone, never from the plant's parameters, so
the same protocol runs on any rig; the holds use the identification run's proportional
:func:`position_loop` but log no reference, as another vendor's log would not. On the paper's
rig the run lasts about 76 s.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from pneutune.control.errors import ExperimentError
from pneutune.control.logs.recording import Recording
from pneutune.control.rig.identification_run import (
    DEFAULT_CONTACT_SPEED,
    TRAVEL_SPEED,
    Segment,
    SegmentController,
    approach,
    mode_duties,
    move_segment,
    position_loop,
    valve_duties,
)

#: Ascending duties of the valve staircases.
STAIR_DUTIES: tuple[float, ...] = (0.06, 0.1, 0.15, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
#: Speeds of the constant-velocity moves [m/s].
SPEEDS: tuple[float, ...] = (0.002, 0.005, 0.01, 0.02, 0.04, 0.08)
#: (burst, braking pulse) lengths [s]. On the paper's rig the piston reaches its flow-limited
#: speed (about 0.1 m/s) within 20 ms of a burst, and a braking pulse of 12-16 ms takes most of
#: it out; a longer one drives the piston back.
BURSTS: tuple[tuple[float, float], ...] = ((0.04, 0.008), (0.08, 0.012), (0.12, 0.016))
#: Stroke time the velocity loop's feedforward assumes at full duty [s]: a cylinder sized for
#: its valves crosses its stroke in a few tenths of a second (the paper's rig in about 0.25 s).
FULL_DUTY_STROKE_TIME: float = 0.25
#: Window of the velocity estimate from position differences [s]: six 4 ms samples bring the
#: noise of a 5 um position sensor down to about 0.2 mm/s.
VELOCITY_WINDOW: float = 0.024
#: Integral time of the velocity loop [s].
INTEGRAL_TIME: float = 0.05
#: Fraction of the stroke the moves and holds keep away from either end.
END_MARGIN: float = 0.1
#: Longest constant-velocity move [s]: the slow moves cover less of the stroke.
MAX_MOVE_TIME: float = 5.0
#: Band of the holds' proportional position loop, as a fraction of the stroke.
HOLD_BAND: float = 0.05


def stair_step(duty: float) -> float:
    """Duration of one staircase step [s]: ``0.036 s / duty`` within [0.24, 0.6] s.

    A valve's flow scales with its duty, so a low duty needs longer for the pressure to move
    by a similar amount. The 0.6 s cap is long enough to show whether a dead-zone duty opens
    the valve at all; the 0.24 s floor keeps the high duties from spending their steps at the
    end pressure.
    """
    return min(max(0.036 / duty, 0.24), 0.6)


def _fixed(label: str, kind: str, duration: float, params: dict[str, Any], group: str,
           contacts: tuple[str, ...] = (), **open_: float) -> Segment:
    return Segment(label, kind, duration, params, valve_duties(**open_), group=group,
                   contacts=contacts)


def valve_staircases(x_min: float, x_max: float, duties: Sequence[float] = STAIR_DUTIES,
                     contact_speed: float = DEFAULT_CONTACT_SPEED) -> list[Segment]:
    """The valve staircases with their preparations (part 2 of the protocol).

    Parameters
    ----------
    x_min, x_max : float
        Stroke ends [m].
    duties : sequence of float
        Ascending duties of each staircase.
    contact_speed : float
        Speed of the approach onto each end stop [m/s].

    Returns
    -------
    list of Segment
        For chamber A against the x_max stop (B vented through b_out), then chamber B against
        the x_min stop (A vented through a_out): a gentle approach onto the stop, press it
        there, vent the chamber, climb the charging valve's staircase, top the chamber up to
        supply, climb the exhausting valve's staircase.
    """
    ascending = all(b > a for a, b in itertools.pairwise(duties))
    if not (ascending and 0.0 < duties[0] and duties[-1] <= 1.0):
        raise ExperimentError(f"staircase duties must ascend within (0, 1], got {list(duties)}")
    band = HOLD_BAND * (x_max - x_min)
    segs: list[Segment] = []
    for chamber, fill, vent, hold, stop, drive in (
            ("a", "a_in", "a_out", "b_out", "x_max", {"a_in": 1.0, "b_out": 1.0}),
            ("b", "b_in", "b_out", "a_out", "x_min", {"a_out": 1.0, "b_in": 1.0})):
        where = {"chamber": chamber, "end_stop": stop, "held_open": hold}
        group, contacts = f"valves:{chamber}", (stop,)
        segs.append(approach(chamber, stop, x_min, x_max, contact_speed, band, logged=False))
        segs.append(_fixed(f"prepare:{chamber}:to_{stop}", "prepare", 1.0, where, group,
                           contacts, **drive))
        segs.append(_fixed(f"prepare:{chamber}:vent", "prepare", 2.0, where, group, contacts,
                           **{vent: 1.0, hold: 1.0}))
        for valve, kind in ((fill, "valve_charge"), (vent, "valve_discharge")):
            if valve == vent:  # start the exhaust staircase from supply pressure
                segs.append(_fixed(f"prepare:{chamber}:charge", "prepare", 0.5, where, group,
                                   contacts, **{fill: 1.0, hold: 1.0}))
            for u in duties:
                segs.append(_fixed(f"staircase:{valve}:{u:.2f}", kind, stair_step(u),
                                   {**where, "valve": valve, "duty": u}, group, contacts,
                                   **{valve: u, hold: 1.0}))
    return segs


class VelocityLoop:
    """PI velocity loop with a speed feedforward, designed from the stroke and ``Ts`` alone.

    ``u = (v_r + e + sum(e) Ts / T_i) / v_ff`` with ``e = v_r - v_hat``, clipped to [-1, 1];
    u > 0 is mode 1 with duty u, u < 0 mode 2 with duty -u (:func:`mode_duties`). ``v_hat`` is
    the position difference over :data:`VELOCITY_WINDOW`, ``v_ff`` the speed the feedforward
    assumes at full duty (the stroke over :data:`FULL_DUTY_STROKE_TIME`), ``T_i`` is
    :data:`INTEGRAL_TIME`. The integral makes up for the valves' dead zone, the friction and a
    wrong ``v_ff`` within a few tenths of a second; while friction holds the piston it keeps
    growing, which gives stick-slip at the lowest speeds as on a real rig. Once the piston
    reaches ``x_stop`` the loop hands over to :func:`position_loop` holding ``x_stop``, so an
    integral wound up against a saturated duty never outlives its move.

    Parameters
    ----------
    speed : float
        Commanded velocity [m/s], signed.
    x_stop : float
        Where the move ends [m].
    stroke : float
        x_max - x_min [m].
    Ts : float
        Control period [s]: the interval between calls.
    """

    def __init__(self, speed: float, x_stop: float, stroke: float, Ts: float) -> None:
        self.speed = speed
        self.x_stop = x_stop
        self.Ts = Ts
        self.band = HOLD_BAND * stroke
        self.v_ff = stroke / FULL_DUTY_STROKE_TIME
        self.window = max(1, round(VELOCITY_WINDOW / Ts))
        self.history: deque[float] = deque(maxlen=self.window + 1)
        self.integral = 0.0
        self.arrived = False

    def __call__(self, t_rel: float, y: np.ndarray) -> np.ndarray:
        """The duties at a control instant, from the measured position ``y[0]`` [m]."""
        x = float(y[0])
        self.arrived = self.arrived or (x - self.x_stop) * math.copysign(1.0, self.speed) >= 0
        if self.arrived:
            return position_loop(x, self.x_stop, self.band)
        if not self.history:  # at rest before the move
            self.history.extend([x] * self.window)
        self.history.append(x)
        error = self.speed - (self.history[-1] - self.history[0]) / (self.window * self.Ts)
        self.integral += error * self.Ts
        u = (self.speed + error + self.integral / INTEGRAL_TIME) / self.v_ff
        return mode_duties(min(max(u, -1.0), 1.0))


def _hold(x: float, duration: float, label: str, band: float, group: str) -> Segment:
    def factory() -> SegmentController:
        return lambda t_rel, y: position_loop(float(y[0]), x, band)

    return Segment(label, "hold", duration, {"x": x}, controller=factory, group=group)


def _move(x: float, label: str, band: float, stroke: float, group: str) -> Segment:
    """A move at :data:`TRAVEL_SPEED` to ``x`` from wherever the piston is, then a hold."""
    return move_segment(label, "hold", x, TRAVEL_SPEED, band, stroke, group, {"x": x},
                        logged=False)


def velocity_moves(x_min: float, x_max: float, Ts: float,
                   speeds: Sequence[float] = SPEEDS) -> list[Segment]:
    """The constant-velocity moves (part 3 of the protocol).

    Parameters
    ----------
    x_min, x_max : float
        Stroke ends [m].
    Ts : float
        Control period [s].
    speeds : sequence of float
        Speeds [m/s], each run out and back.

    Returns
    -------
    list of Segment
        A hold at the low end of the range, then for each speed a move up, a hold, a move down
        and a hold. Each move covers the range [x_min, x_max] less :data:`END_MARGIN` of the
        stroke at each end, or what the speed covers in :data:`MAX_MOVE_TIME`; it lasts that
        travel time plus 0.4 s to break away and get up to speed.
    """
    stroke = x_max - x_min
    lo, hi = x_min + END_MARGIN * stroke, x_max - END_MARGIN * stroke
    band = HOLD_BAND * stroke
    segs = [_move(lo, "hold:start_velocity", band, stroke, "friction")]
    for v in speeds:
        travel = min(hi - lo, v * MAX_MOVE_TIME)
        for sign, x_from, x_to in ((1.0, lo, lo + travel), (-1.0, lo + travel, lo)):
            name = f"{'+' if sign > 0 else '-'}{v * 1e3:g}mm/s"

            def factory(speed: float = sign * v, x_to: float = x_to) -> SegmentController:
                return VelocityLoop(speed, x_to, stroke, Ts)

            segs.append(Segment(f"constant_speed:{name}", "constant_speed",
                                travel / v + 0.4,
                                {"speed": sign * v, "x_from": x_from, "x_to": x_to},
                                controller=factory, group="friction"))
            segs.append(_hold(x_to, 0.5, f"hold:{name}", band, "friction"))
    return segs


def bursts(x_min: float, x_max: float,
           lengths: Sequence[tuple[float, float]] = BURSTS) -> list[Segment]:
    """Full-duty bursts with braking pulses (part 4 of the protocol).

    Parameters
    ----------
    x_min, x_max : float
        Stroke ends [m].
    lengths : sequence of (float, float)
        (burst, braking pulse) lengths [s].

    Returns
    -------
    list of Segment
        For each length and each direction: a 1 s hold at :data:`END_MARGIN` of the stroke
        from the starting end, the burst (mode 1 or 2 at full duty), the braking pulse (the
        opposite mode at full duty) and 0.5 s of coasting with all valves closed.
    """
    stroke = x_max - x_min
    band = HOLD_BAND * stroke
    segs: list[Segment] = []
    for length, brake in lengths:
        for sign, x_start in ((1.0, x_min + END_MARGIN * stroke),
                              (-1.0, x_max - END_MARGIN * stroke)):
            name = f"{'+' if sign > 0 else '-'}{length * 1e3:g}ms"
            params = {"direction": sign, "burst": length, "brake": brake}
            segs.append(_move(x_start, f"hold:burst{name}", band, stroke, "bursts"))
            segs.append(Segment(f"burst:{name}", "burst", length, params, mode_duties(sign),
                                group="bursts"))
            segs.append(Segment(f"brake:{name}", "brake", brake, params,
                                mode_duties(-sign), group="bursts"))
            segs.append(Segment(f"coast:{name}", "coast", 0.5, params, np.zeros(4),
                                group="bursts"))
    return segs


def commissioning_protocol(x_min: float, x_max: float, Ts: float,
                           contact_speed: float = DEFAULT_CONTACT_SPEED) -> list[Segment]:
    """The segments of the commissioning run for a rig with the given stroke.

    Parameters
    ----------
    x_min, x_max : float
        Stroke ends [m].
    Ts : float
        Control period [s] of the closed-loop segments.
    contact_speed : float
        Speed of the approach onto each end stop [m/s].

    Returns
    -------
    list of Segment
        In the groups ``rest`` (first and last segment), ``valves:a``, ``valves:b``,
        ``friction`` (the velocity moves) and ``bursts``.
    """
    if not x_max > x_min:
        raise ExperimentError(f"x_max > x_min must hold, got x_min={x_min}, x_max={x_max}")
    if not Ts > 0.0:
        raise ExperimentError(f"Ts > 0 must hold, got Ts={Ts}")
    if not (math.isfinite(contact_speed) and contact_speed > 0.0):
        raise ExperimentError(f"the contact speed must be > 0 m/s, got {contact_speed}")
    return [Segment("rest:start", "rest", 1.0, {}, np.zeros(4), group="rest"),
            *valve_staircases(x_min, x_max, contact_speed=contact_speed),
            *velocity_moves(x_min, x_max, Ts),
            *bursts(x_min, x_max),
            Segment("rest:end", "rest", 1.0, {}, np.zeros(4), group="rest")]


def simulate_commissioning(plant_cfg: Any, seed: int | None = None,
                           progress: Callable[[int, int], None] | None = None,
                           sample_period: float | None = None,
                           record_truth: bool = False) -> Recording:
    """Run the commissioning protocol on the simulated rig, supervised.

    Parameters
    ----------
    plant_cfg : PlantConfig
        The simulated plant.
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.
    progress : callable, optional
        ``progress(done, total)`` callback.
    sample_period : float, optional
        Sensor logging period [s], dividing ``rig.Ts``; default ``rig.Ts``, the control rate
        (another rig's commissioning log rarely has more).
    record_truth : bool
        Record ``/sim/truth`` too (for tests; another rig's log has none).

    Returns
    -------
    Recording
        Sensors, duties and segment labels every ``sample_period``. Save it with
        ``plant_cfg.rig_metadata()``.
    """
    from pneutune.control.rig.excitation import record_on_sim

    report = None if progress is None else (lambda done, total, _label: progress(done, total))
    return record_on_sim("commissioning", plant_cfg, seed=seed, sample_period=sample_period,
                         progress=report, record_truth=record_truth).recording
