"""One scenario deployed on a rig: homing, the loop, the metrics and the log's metadata.

:func:`run_scenario` is what ``deploy`` runs per scenario: the scenario's reference at the
rig's Ts, centred at its mid-stroke (:func:`scenario_reference`); the homing move when the
piston rests away from x_r(0) (:mod:`~pneutune.control.rig.homing`); the deploy loop
(:func:`~pneutune.control.rig.runtime.run_loop`); the paper's indices over what ran
(:func:`~pneutune.control.sim.closed_loop.compute_metrics`). :func:`sim_rig_for` sets up the
simulated rig for a scenario as ``simulate --controller`` does, so that a deploy run on it
reproduces the simulator sample for sample.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.constants import HOME_MODES
from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.darc import step_into
from pneutune.control.law.layout import pack
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.homing import after_homing, homing_move
from pneutune.control.rig.protocol import Rig
from pneutune.control.rig.runtime import (
    START_TOLERANCE,
    LoopResult,
    LoopSettings,
    run_loop,
    warm_up,
)
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES, Event, Supervisor, SupervisorSettings
from pneutune.control.rig.wire import RigIOError
from pneutune.control.sim.closed_loop import (
    ClosedLoopResult,
    Metrics,
    compute_metrics,
    scenario_plant,
)
from pneutune.control.sim.scenarios import Scenario, fit_to_limits

#: Status of a run that a supervisor fault stopped (Metrics.status).
STATUS_FAULT = "fault"


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
        As :class:`~pneutune.control.rig.runtime.LoopSettings`.
    cfg_vec : ndarray, optional
        Pre-packed controller.
    duration : float, optional
        Run only the first ``duration`` seconds of the scenario [s].
    plant, seed : optional
        The simulated plant and seed, kept in the result (logs, plots).
    on_sample : callable, optional
        Progress callback.
    home : {"auto", "always", "off"}
        Move the piston to x_r(0) under the controller first
        (:func:`~pneutune.control.rig.homing.homing_move`): when it rests more than
        ``start_tolerance`` away, always, or never.
    start_tolerance : float
        Largest |x(0) - x_r(0)| of the scenario's start [m].
    law : callable, optional
        The control step (:attr:`~pneutune.control.rig.runtime.LoopSettings.law`); default
        the installed law.

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
        warm_up(cfg, ref, step_into if law is None else law)
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
        notes = after_homing(rig, scenario, plant, homing, offset, float(ref[0, 0]))
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
    the piston rests at x_r(0) with the chamber pressures in force balance, of the reference
    as it runs on this stroke (scaled to it where Table 1's does not fit,
    :func:`~pneutune.control.sim.scenarios.fit_to_limits`: a driver told only the scenario's
    name starts where ``deploy`` scales it to); the noise seed is ``seed`` or the plant's
    ``sim.seed``.

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
    meta = pcfg.rig_metadata()
    x_min, x_max = float(meta["x_min"]), float(meta["x_max"])
    (fitted,), _ = fit_to_limits([scenario], float(meta["Ts"]), 0.5 * (x_min + x_max), x_min,
                                 x_max)
    ref0 = scenario_reference(fitted, meta)[0, 0]
    rig = rig_class(pcfg, x0=float(ref0), seed=seed_used, **rig_kwargs)
    return rig, pcfg, seed_used


__all__ = [
    "STATUS_FAULT",
    "ScenarioResult",
    "run_scenario",
    "scenario_reference",
    "sim_rig_for",
]
