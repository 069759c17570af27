"""Homing: the piston moved from where it rests to the scenario's x_r(0) under the controller.

:func:`~pneutune.control.rig.scenario_run.run_scenario`'s ``home`` (``deploy --home``) runs
:func:`homing_move` before the scenario, under the same controller and supervisor: a quintic
move of :data:`HOME_MOVE_S` from the first reading, then :data:`HOME_HOLD_S` holding x_r(0).
``auto`` (the default) does so only when the first reading is more than ``start_tolerance``
away, ``always`` before every scenario, ``off`` never (a distant piston is then the fault
``start_position``). The first reading is taken once and serves the decision and the first
sample of whichever loop runs next (a simulated rig draws its noise per reading), so a run that
needs no homing is the run without it, sample for sample. After a move the scenario starts from
a fresh controller state and its own t = 0; the rig's clock runs on (``clock_offset`` of
:func:`~pneutune.control.rig.runtime.run_loop`: the supervisor's staleness rule compares the
rig's sample times with the loop's time shifted by the homing's length; the control law gets
the rig's time). A simulated rig in process holds its timed disturbance during the move and
starts it with the scenario (``set_scenario_start``, :func:`after_homing`); for a driver that
simulates one on its own clock a warning says it comes early. The homing samples are not in the
scenario's recording: at t = 0 it gets the move's warnings and an ``info`` event saying where
the piston came from and how close it got.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.rig.protocol import Rig
from pneutune.control.rig.runtime import LoopResult, LoopSettings, run_loop
from pneutune.control.rig.supervisor import Event, Supervisor
from pneutune.control.rig.wire import RigIOError
from pneutune.control.sim.scenarios import Scenario, move_and_hold

#: Homing: the quintic move from the resting position to x_r(0) [s] (a full 50 mm stroke at a
#: peak speed of 31 mm/s, below the Table-1 sines' 55 mm/s).
HOME_MOVE_S = 3.0
#: Homing: time holding x_r(0) after the move, for the pressures to settle [s].
HOME_HOLD_S = 1.0


def homing_move(rig: Rig, cfg_vec: np.ndarray, target: float,
                supervisor: Supervisor | None = None, settings: LoopSettings | None = None, *,
                move_s: float = HOME_MOVE_S, hold_s: float = HOME_HOLD_S,
                first: tuple[np.ndarray, np.ndarray | None] | RigIOError | None = None,
                on_sample: Callable[[int], None] | None = None) -> LoopResult:
    """Move the piston from where it rests to ``target`` under the controller (homing).

    The reference is :func:`~pneutune.control.sim.scenarios.move_and_hold` from the first
    position reading to ``target`` in ``move_s``, then ``hold_s`` at ``target``; the controller
    state starts there as in any run (:func:`~pneutune.control.rig.runtime.run_loop`), under
    the same supervisor.

    Parameters
    ----------
    rig : Rig
    cfg_vec : (CFG_SIZE,) float64
        The packed controller config.
    target : float
        Where the move ends: the scenario's x_r(0) [m].
    supervisor : Supervisor, optional
        As :func:`~pneutune.control.rig.runtime.run_loop` (reset here).
    settings : LoopSettings, optional
        As :func:`~pneutune.control.rig.runtime.run_loop`; its ``start_tolerance`` does not
        apply (the move starts where the piston is).
    move_s, hold_s : float
        Durations of the move and the hold [s].
    first : (sensors, sample_times) or RigIOError, optional
        The first sample's reading, already taken
        (:func:`~pneutune.control.rig.scenario_run.run_scenario`), or the error it raised;
        default: read it here.
    on_sample : callable, optional
        As :func:`~pneutune.control.rig.runtime.run_loop`.

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


def after_homing(rig: Rig, scenario: Scenario, plant: PlantConfig | None,
                 homing: LoopResult | None, offset: float, target: float) -> list[Event]:
    """Start the scenario's clock on the rig after a homing move; the events for its log.

    A rig with ``set_scenario_start`` (the simulated rigs in process) times its plant's force
    steps from the scenario's start; any other rig that simulates timed steps (the plant's, when
    known, else the scenario's) does so on its own clock, which a ``warning`` says. The move's
    warnings follow, at t = 0, then the ``info`` event ``homing``.

    Parameters
    ----------
    rig : Rig
        The rig the scenario runs on.
    scenario : Scenario
        The scenario that follows the move.
    plant : PlantConfig or None
        The simulated plant with the scenario's changes, when known.
    homing : LoopResult or None
        The homing move that ran (None: no move, nothing to do).
    offset : float
        Rig time of the scenario's first sample: the move's length [s].
    target : float
        x_r(0), where the move ended [m].

    Returns
    -------
    list of Event
        The events to put at the head of the scenario's log (none without a move).
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


__all__ = [
    "HOME_HOLD_S",
    "HOME_MOVE_S",
    "after_homing",
    "homing_move",
]
