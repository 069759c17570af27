"""What an excitation protocol will run on a rig, worked out without touching it.

The protocols by name (:func:`experiment_protocol`: the identification run,
:mod:`~pneutune.control.rig.identification_run`, and the commissioning run,
:mod:`~pneutune.control.rig.commissioning_run`), the part of one that ``--segments`` selects
with the lead-ins that put the piston where the protocol would have it
(:func:`select_segments`, :func:`lead_in`), the check that the stroke is long enough for the
constant-speed segments (:func:`check_stroke`), the band of the protocols' position loops
(:func:`protocol_band`), the sample period a protocol logs at (:func:`default_sample_period`)
and ``record --plan`` (:func:`plan`). :mod:`~pneutune.control.rig.excitation` runs the
segments, supervised.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pneutune.control.constants import VALVES
from pneutune.control.errors import ExperimentError
from pneutune.control.rig.identification_run import (
    DEFAULT_CONTACT_SPEED,
    IDENT_SAMPLE_PERIOD,
    TRAVEL_SPEED,
    Segment,
    move_segment,
)
from pneutune.control.rig.supervisor import SupervisorSettings

#: The protocols by name.
EXPERIMENTS: tuple[str, ...] = ("identification", "commissioning")
#: Saturation band of the protocols' position loops, as a fraction of the stroke.
BAND_FRACTION: float = 0.05
#: Shortest time a constant-speed segment must hold its speed [s]; a stroke too short for it
#: is bad input (:func:`check_stroke`).
MIN_CONSTANT_SPEED_S: float = 0.2


def experiment_protocol(name: str, rig_meta: Mapping[str, Any], *,
                        contact_speed: float = DEFAULT_CONTACT_SPEED) -> list[Segment]:
    """The segments of a named protocol for a rig.

    Parameters
    ----------
    name : {"identification", "commissioning"}
        The protocol.
    rig_meta : mapping
        The rig block (``x_min``, ``x_max``, ``Ts``: the control period).
    contact_speed : float
        Speed of the approaches onto the end stops [m/s].

    Returns
    -------
    list of Segment

    Raises
    ------
    ExperimentError
        An unknown name or contact speed that cannot work.
    """
    from pneutune.control.rig.commissioning_run import commissioning_protocol
    from pneutune.control.rig.identification_run import identification_protocol

    x_min, x_max = float(rig_meta["x_min"]), float(rig_meta["x_max"])
    if name == "identification":
        return identification_protocol(x_min, x_max, contact_speed=contact_speed)
    if name == "commissioning":
        return commissioning_protocol(x_min, x_max, float(rig_meta["Ts"]),
                                      contact_speed=contact_speed)
    raise ExperimentError(f"unknown experiment {name!r}; expected one of {', '.join(EXPERIMENTS)}")


def protocol_band(rig_meta: Mapping[str, Any]) -> float:
    """Saturation band of the protocols' position loops on a rig [m].

    Parameters
    ----------
    rig_meta : mapping
        The rig block (``x_min``, ``x_max``).

    Returns
    -------
    float
        :data:`BAND_FRACTION` of the stroke [m].
    """
    return BAND_FRACTION * (float(rig_meta["x_max"]) - float(rig_meta["x_min"]))


def check_stroke(segments: Sequence[Segment], rig_meta: Mapping[str, Any]) -> None:
    """Refuse a stroke too short for the protocol's constant-speed segments.

    A constant-speed segment covers a share of the stroke; at its speed it must last at least
    :data:`MIN_CONSTANT_SPEED_S`, or it shows the break-away and no steady sliding.

    Raises
    ------
    ExperimentError
        Naming the first segment that does not fit, the stroke it needs and the rig's.
    """
    stroke = float(rig_meta["x_max"]) - float(rig_meta["x_min"])
    for seg in segments:
        if seg.kind != "constant_speed":
            continue
        speed = abs(float(seg.params.get("speed", 0.0)))
        travel = abs(float(seg.params.get("x_to", 0.0)) - float(seg.params.get("x_from", 0.0)))
        if speed > 0.0 and travel < speed * MIN_CONSTANT_SPEED_S:
            need = stroke * speed * MIN_CONSTANT_SPEED_S / max(travel, 1e-12)
            raise ExperimentError(
                f"segment {seg.label} needs a stroke of at least {need * 1e3:.1f} mm "
                f"({MIN_CONSTANT_SPEED_S:g} s at {speed * 1e3:g} mm/s within its share of the "
                f"stroke); the rig's stroke x_max - x_min is {stroke * 1e3:.1f} mm (leave the "
                f"part out with --segments, or check the rig block)")


def select_segments(segments: Sequence[Segment], patterns: str | Sequence[str] | None,
                    rig_meta: Mapping[str, Any] | None = None) -> list[Segment]:
    """The segments a ``--segments`` selection names, in protocol order, with their lead-ins.

    Parameters
    ----------
    segments : sequence of Segment
        The whole protocol.
    patterns : str or sequence of str or None
        Comma-separated (or listed) shell-style patterns, each matched against every
        segment's group (``valves:a``, ``friction``, ...) and label (``constant_speed:*``);
        None or empty: every segment.
    rig_meta : mapping, optional
        The rig block. Given, a selection that starts inside a group gets the lead-in that
        puts the piston where the protocol would have it (:func:`lead_in`), so that no move
        is faster than planned and no end stop is met but by its approach.

    Returns
    -------
    list of Segment

    Raises
    ------
    ExperimentError
        A pattern that matches no segment (naming it and the groups there are).
    """
    if patterns is None:
        return list(segments)
    items = [p.strip() for p in (patterns.split(",") if isinstance(patterns, str) else patterns)]
    items = [p for p in items if p]
    if not items:
        return list(segments)
    keep = [False] * len(segments)
    for pat in items:
        hits = [i for i, s in enumerate(segments)
                if fnmatch.fnmatchcase(s.group, pat) or fnmatch.fnmatchcase(s.label, pat)]
        if not hits:
            groups = list(dict.fromkeys(s.group for s in segments))
            raise ExperimentError(f"--segments: {pat!r} names no segment of the protocol; its "
                                  f"groups are {', '.join(groups)} (or give a label pattern "
                                  f"such as 'constant_speed:*')")
        for i in hits:
            keep[i] = True
    out: list[Segment] = []
    for i, seg in enumerate(segments):
        if not keep[i]:
            continue
        if rig_meta is not None and (i == 0 or not keep[i - 1]):
            out += lead_in(segments, i, rig_meta)
        out.append(seg)
    return out


def _group_start(segments: Sequence[Segment], i: int) -> int:
    j = i
    while j > 0 and segments[j - 1].group == segments[i].group:
        j -= 1
    return j


def lead_in(segments: Sequence[Segment], i: int, rig_meta: Mapping[str, Any]) -> list[Segment]:
    """What must run before segment ``i`` when the segments before it in its group do not.

    A valve test (a segment with :attr:`~Segment.contacts`) gets its group's approach onto the
    stop and the preparations that follow it, and the preparations right before it; any other
    segment inside a group gets a :class:`~pneutune.control.rig.identification_run.Move` at
    :data:`~pneutune.control.rig.identification_run.TRAVEL_SPEED` to where the segments before
    it leave the piston (with a logged reference when the protocol logs references). A group's
    first segment needs none.

    Parameters
    ----------
    segments : sequence of Segment
        The whole protocol.
    i : int
        The first selected segment of a run of selected segments.
    rig_meta : mapping
        The rig block.

    Returns
    -------
    list of Segment
    """
    start = _group_start(segments, i)
    if start == i:
        return []
    seg = segments[i]
    if seg.contacts:
        lead = []
        for j in range(start, i):
            if segments[j].kind not in ("approach", "prepare"):
                break
            lead.append(segments[j])
        before = []
        for j in range(i - 1, start + len(lead) - 1, -1):
            if segments[j].kind != "prepare":
                break
            before.insert(0, segments[j])
        return lead + before
    for j in range(i - 1, start - 1, -1):
        p = segments[j].params
        pos = next((p[k] for k in ("x_to", "target", "x", "center") if k in p), None)
        if pos is not None:
            x_min, x_max = float(rig_meta["x_min"]), float(rig_meta["x_max"])
            return [move_segment(f"move:{seg.label}", "hold", float(pos), TRAVEL_SPEED,
                                 protocol_band(rig_meta), x_max - x_min, seg.group,
                                 {"x": float(pos)},
                                 logged=any(s.reference is not None for s in segments))]
    return []


def default_sample_period(name: str, control_Ts: float) -> float:
    """The sample period a protocol logs at by default [s].

    Parameters
    ----------
    name : {"identification", "commissioning"}
        The protocol.
    control_Ts : float
        The control period, the rig block's ``Ts`` [s].

    Returns
    -------
    float
        0.5 ms for the identification run
        (:data:`~pneutune.control.rig.identification_run.IDENT_SAMPLE_PERIOD`, which resolves
        the moving mass), the control period for the commissioning run.
    """
    return IDENT_SAMPLE_PERIOD if name == "identification" else control_Ts


def _what(seg: Segment) -> str:
    """What drives a segment, in words (for the plan)."""
    p = seg.params
    if seg.reference is not None:
        if seg.kind == "constant_speed":
            return (f"position loop on a ramp {p['x_from'] * 1e3:.1f} -> {p['x_to'] * 1e3:.1f} mm "
                    f"at {abs(p['speed']) * 1e3:g} mm/s")
        if seg.kind == "acceleration":
            return (f"position loop on a sine of {p['amplitude'] * 1e3:.1f} mm at {p['freq']:g} Hz "
                    f"about {p['center'] * 1e3:.1f} mm")
        return f"position loop holding {p.get('x', math.nan) * 1e3:.1f} mm"
    if seg.controller is not None:
        if "target" in p:
            return (f"move to {p['target'] * 1e3:.1f} mm at {p['speed'] * 1e3:g} mm/s from "
                    f"wherever the piston is, then hold")
        if seg.kind == "constant_speed":
            return (f"velocity loop at {p['speed'] * 1e3:g} mm/s from {p['x_from'] * 1e3:.1f} to "
                    f"{p['x_to'] * 1e3:.1f} mm")
        return f"position loop holding {p.get('x', math.nan) * 1e3:.1f} mm"
    d = seg.duties if seg.duties is not None else np.zeros(4)
    opened = [f"{v}={u:g}" for v, u in zip(VALVES, d.tolist(), strict=True) if u > 0.0]
    return "duties " + (", ".join(opened) if opened else "all closed") + " (open loop)"


def _planned_speed(seg: Segment) -> float:
    """Largest speed a segment asks for [m/s] (NaN for open-loop duties)."""
    p = seg.params
    if seg.kind == "acceleration" and "amplitude" in p:
        return abs(p["amplitude"]) * 2.0 * math.pi * p["freq"]
    if "speed" in p and seg.kind in ("constant_speed", "approach", "hold"):
        return abs(float(p["speed"]))
    if seg.reference is not None or seg.controller is not None:
        return 0.0
    return math.nan


def plan(segments: Sequence[Segment], rig_meta: Mapping[str, Any],
         settings: SupervisorSettings | None = None) -> dict[str, Any]:
    """What a protocol will do on a rig, worked out without touching it (``record --plan``).

    Parameters
    ----------
    segments : sequence of Segment
        The segments to run.
    rig_meta : mapping
        The rig block.
    settings : SupervisorSettings, optional
        The supervisor's thresholds, reported with the plan.

    Returns
    -------
    dict
        ``segments`` (label, group, kind, duration_s, what), ``total_s``, ``peak_duty``,
        ``peak_speed`` (m/s and the segment), ``contacts`` (stop, segment, speed),
        ``open_loop_motion`` (full-duty segments that move the piston: bursts and brakes),
        ``pressures`` (what the valve tests reach), ``limits``.
    """
    control_Ts = float(rig_meta["Ts"])
    rows = [{"label": s.label, "group": s.group, "kind": s.kind,
             "duration_s": round(s.duration / control_Ts) * control_Ts, "what": _what(s)}
            for s in segments]
    peak_duty = 0.0
    for s in segments:
        if s.duties is not None and s.reference is None and s.controller is None:
            peak_duty = max(peak_duty, float(np.max(s.duties)))
        else:
            peak_duty = 1.0  # the closed loops saturate at full duty
    speeds = [(_planned_speed(s), s.label) for s in segments]
    speeds = [(v, lab) for v, lab in speeds if math.isfinite(v)]
    top = max(speeds, default=(0.0, ""))
    p0, p_s = float(rig_meta["p0"]), float(rig_meta["p_s"])
    pressures = []
    for chamber in ("a", "b"):
        tests = [s for s in segments if s.params.get("chamber") == chamber
                 and s.kind in ("valve_charge", "valve_discharge")]
        if tests:
            valves = sorted({str(s.params.get("valve")) for s in tests})
            pressures.append({"chamber": chamber, "low_pa": p0, "high_pa": p_s,
                              "valves": valves, "segments": len(tests)})
    out: dict[str, Any] = {
        "segments": rows, "total_s": float(sum(r["duration_s"] for r in rows)),
        "peak_duty": peak_duty, "peak_speed": {"m_per_s": top[0], "segment": top[1]},
        "contacts": [{"stop": s.contacts[0], "segment": s.label,
                      "speed_m_per_s": float(s.params["speed"])}
                     for s in segments if s.kind == "approach"],
        "open_loop_motion": [{"segment": s.label, "duration_s": s.duration}
                             for s in segments if s.kind in ("burst", "brake")],
        "pressures": pressures,
    }
    if settings is not None:
        out["limits"] = {"x_min": settings.x_min, "x_max": settings.x_max,
                         "p_max": settings.p_max, "supply_min": settings.supply_min,
                         "sensor_timeout_s": settings.sensor_timeout_s}
    return out


__all__ = [
    "BAND_FRACTION",
    "EXPERIMENTS",
    "MIN_CONSTANT_SPEED_S",
    "check_stroke",
    "default_sample_period",
    "experiment_protocol",
    "lead_in",
    "plan",
    "protocol_band",
    "select_segments",
]
