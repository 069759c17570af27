"""``deploy(controller, rig, scenarios)``: the whole of the ``deploy`` command as a library call.

What the command does, a notebook does the same way, with the same checks::

    from pneutune.control import deploy
    result = deploy("data/controller-paper.yaml", rig="sim", scenarios="table1")
    result.summary()           # what `deploy --json` prints
    print(result.table())      # the paper's indices beside Table 1

Everything is checked before anything runs: the controller (contract 4), the rig's ``Ts`` and
``pwm_hz`` against the controller's, every scenario's reference against the position limits,
the seed and the duration. Each scenario then runs under the safety supervisor
(:mod:`.supervisor`) through :func:`~pneutune.control.rig.scenario_run.run_scenario`; a fault
stops the remaining scenarios. Run logs (contract 1) are written only when ``log`` or
``log_dir`` is given.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ConfigError, ExperimentError, argument_error
from pneutune.control.law.layout import pack
from pneutune.control.logs.recording import plant_meta
from pneutune.control.plant.params import load_sim_plant
from pneutune.control.sim.closed_loop import scenario_plant
from pneutune.control.sim.scenarios import AMPLITUDE, Scenario, fit_to_limits, resolve_scenarios

from .exec_rig import ExecRig, PipeRig, exec_command
from .protocol import Rig
from .scenario_run import ScenarioResult, run_scenario, sim_rig_for
from .supervisor import FAIL_SAFE_MODES, Event, Supervisor, SupervisorSettings
from .wire import RigIOError

#: Rig kinds of the ``rig`` argument.
RIG_KINDS: tuple[str, ...] = ("sim", "pipe-sim", "exec")
#: Relative tolerance of the Ts and pwm_hz comparison between controller and rig.
RIG_MATCH_RTOL = 1.0e-9
#: Exit status of a command whose run a supervisor fault stopped.
EXIT_FAULT = 3


def parse_rig(spec: str) -> tuple[str, str | None]:
    """Split a rig specification (``sim[:P.yaml]``, ``pipe-sim[:P.yaml]``, ``exec:CMD``).

    Returns
    -------
    (kind, argument)
        ``kind`` one of :data:`RIG_KINDS`; ``argument`` the plant path or None for ``sim`` and
        ``pipe-sim``, the driver command (with its placeholders) for ``exec``.

    Raises
    ------
    ExperimentError
        An unknown kind, an empty path, or a bad driver command
        (:func:`~pneutune.control.rig.exec_rig.exec_command`).
    """
    kind, sep, arg = spec.partition(":")
    if kind not in RIG_KINDS:
        raise argument_error(ExperimentError, "rig", f"{kind!r} is an unknown rig; expected "
                             "sim[:P.yaml], pipe-sim[:P.yaml] or exec:\"CMD ARGS\"")
    if kind == "exec":
        exec_command(arg, "sine-0.5hz", 0, 1.0)  # the checks, before anything runs
        return kind, arg
    if sep and not arg:
        raise argument_error(ExperimentError, "rig", f"{spec!r}: the plant path after ':' is "
                             "empty")
    return kind, (arg or None)


def check_rig_compatible(controller: ControllerConfig, rig_meta: dict[str, Any],
                         controller_file: str, rig_source: str) -> None:
    """The controller's ``rig.Ts`` and ``rig.pwm_hz`` must equal the rig's.

    The control law's discrete filters and the PWM inverse are designed for one sampling
    period and one PWM frequency; another rig's timing makes them wrong without any sign.

    Raises
    ------
    ConfigError
        Naming the controller file, the key (``rig.Ts`` or ``rig.pwm_hz``), both values and
        where the rig's came from.
    """
    for key, unit in (("Ts", "s"), ("pwm_hz", "Hz")):
        mine = float(getattr(controller.rig, key))
        theirs = float(rig_meta[key])
        if not math.isclose(mine, theirs, rel_tol=RIG_MATCH_RTOL, abs_tol=0.0):
            raise ConfigError(controller_file, f"rig.{key}",
                              f"must equal the rig's {key} = {theirs!r} {unit} ({rig_source}), "
                              f"got {mine!r} {unit}")


#: Relative difference of a geometry key of the rig block above which deploy warns [-].
GEOMETRY_RTOL = 0.05
#: The rig block's keys a controller is designed on that deploy compares with the rig's.
GEOMETRY_KEYS: tuple[tuple[str, str, float], ...] = (
    ("A_a", "m^2", 1.0), ("A_b", "m^2", 1.0), ("V0a", "m^3", 1.0), ("V0b", "m^3", 1.0))


def geometry_warnings(controller: ControllerConfig, rig_meta: dict[str, Any],
                      controller_file: str, rig_source: str) -> list[str]:
    """What differs between the controller's rig block and the rig, short of an error.

    Geometry differences are model error, which the robust terms are for, so they run; but a
    controller whose areas or volumes are another cylinder's was most likely made for another
    axis, and position limits past the rig's stroke leave the stroke supervisor unable to trip
    before an end stop. Each is one warning.

    Parameters
    ----------
    controller : ControllerConfig
    rig_meta : dict
        The rig's ``rig`` block (a plant's, or what a driver's hello reports).
    controller_file, rig_source : str
        For the messages.

    Returns
    -------
    list of str
        Empty when the controller matches the rig.
    """
    out = []
    diffs = []
    for key, unit, scale in GEOMETRY_KEYS:
        mine, theirs = float(getattr(controller.rig, key)), rig_meta.get(key)
        if theirs is None or not float(theirs) > 0.0:
            continue
        theirs = float(theirs)
        if abs(mine / theirs - 1.0) > GEOMETRY_RTOL:
            diffs.append(f"{key} {mine * scale:.4g} against {theirs * scale:.4g} {unit} "
                         f"({mine / theirs - 1.0:+.0%})")
    if diffs:
        out.append(f"the rig block of {controller_file} is another cylinder's than the rig's "
                   f"({rig_source}): {', '.join(diffs)}; it runs on that model error: identify "
                   f"and tune on this rig")
    lo, hi = rig_meta.get("x_min"), rig_meta.get("x_max")
    lim = controller.limits
    if lo is not None and hi is not None and (lim.x_min < float(lo) - 1e-9
                                              or lim.x_max > float(hi) + 1e-9):
        out.append(f"limits [{lim.x_min * 1e3:.2f}, {lim.x_max * 1e3:.2f}] mm of "
                   f"{controller_file} reach past the rig's stroke [{float(lo) * 1e3:.2f}, "
                   f"{float(hi) * 1e3:.2f}] mm ({rig_source}): the stroke supervisor cannot "
                   f"trip before the piston meets that end stop; put the rig's limits in the "
                   f"controller")
    return out


def _mismatch_warnings(controller: ControllerConfig, rig_meta: dict[str, Any],
                       controller_file: str, rig_source: str) -> list[dict[str, Any]]:
    """:func:`geometry_warnings` as deploy's warning records (``rig_mismatch``, for all
    scenarios)."""
    return [{"scenario": "all", "t": 0.0, "level": "warning", "code": "rig_mismatch",
             "message": m}
            for m in geometry_warnings(controller, rig_meta, controller_file, rig_source)]


def fit_reference_to_limits(controller: ControllerConfig, scenarios: Sequence[Scenario],
                            rig_meta: dict[str, Any], controller_file: str
                            ) -> tuple[list[Scenario], str | None]:
    """The scenarios as they run on this rig: their references, centred at its mid-stroke,
    must lie within its stroke and the controller's position limits; on a stroke too short for
    Table 1's 17.5 mm they are scaled down to fit
    (:func:`~pneutune.control.sim.scenarios.fit_to_limits`, what ``tune`` does on the same
    rig).

    Returns
    -------
    scenarios : list of Scenario
        As given, or all scaled by one factor.
    note : str or None
        What was scaled, for a warning record; None when nothing was.

    Raises
    ------
    ExperimentError
        The rig's mid-stroke is not inside the controller's limits (another rig's controller),
        or the stroke is too short for any reference.
    """
    lim = controller.limits
    x_min, x_max = float(rig_meta["x_min"]), float(rig_meta["x_max"])
    lo, hi = max(lim.x_min, x_min), min(lim.x_max, x_max)
    where = (f"the rig's stroke [{x_min * 1e3:.2f}, {x_max * 1e3:.2f}] mm and the limits "
             f"[{lim.x_min * 1e3:.2f}, {lim.x_max * 1e3:.2f}] mm of {controller_file}")
    try:
        fitted, factor = fit_to_limits(scenarios, float(rig_meta["Ts"]), 0.5 * (x_min + x_max),
                                       lo, hi)
    except ExperimentError as exc:
        raise ExperimentError(f"{where}: {exc}") from None
    if factor == 1.0:
        return fitted, None
    return fitted, (f"{where} are too short for Table 1's {AMPLITUDE * 1e3:.1f} mm about "
                    f"mid-stroke: the references are scaled by {factor:.3f} to "
                    f"{factor * AMPLITUDE * 1e3:.2f} mm, Table 1's figures alike (as tune "
                    "scores them on this stroke)")


def _scaled_warning(scenario: str, note: str) -> dict[str, Any]:
    """A ``reference_scaled`` warning record (:func:`fit_reference_to_limits`)."""
    return {"scenario": scenario, "t": 0.0, "level": "warning", "code": "reference_scaled",
            "message": note}


def check_sampled_at_control_rate(rig: Rig, rig_source: str) -> None:
    """The rig must sample at its control period: ``deploy`` runs the controller every sample.

    Raises
    ------
    ExperimentError
        A driver whose hello's ``Ts`` (its sample period) differs from its rig block's
        ``rig.Ts``, with what to do about it.
    """
    Ts, control = float(rig.Ts), float(rig.rig_metadata()["Ts"])
    if not math.isclose(Ts, control, rel_tol=RIG_MATCH_RTOL, abs_tol=0.0):
        raise ExperimentError(f"rig {rig_source}: the driver samples every {Ts!r} s (its hello's "
                              f"Ts) but deploy runs the controller at every sample, at the "
                              f"control period rig.Ts = {control!r} s: start the driver at "
                              f"rig.Ts (deploy fills {{sample_period}} in its command with it)")


def scenario_log_path(path: str | os.PathLike[str], scenario: str, several: bool) -> Path:
    """Where one scenario's log goes: ``path`` itself for a single scenario, else
    ``<stem>-<scenario><suffix>`` beside it (suffix ``.mcap`` if ``path`` has none)."""
    p = Path(path)
    return p.with_name(f"{p.stem}-{scenario}{p.suffix or '.mcap'}") if several else p


@dataclass(frozen=True, repr=False)
class ScenarioRun:
    """One scenario as deployed.

    Attributes
    ----------
    name : str
    metrics : dict
        The paper's indices and the run's facts, as ``deploy --json`` prints them per scenario
        (``samples``, ``events``, ``homing``, ``log`` when one was written).
    result : ScenarioResult
        The runtime's result (:meth:`~ScenarioResult.closed_loop_result` for plots,
        :meth:`~ScenarioResult.save_log` to write the log later).
    log : str or None
        The log written, if any.
    """

    name: str
    metrics: dict[str, Any]
    result: ScenarioResult
    log: str | None = None

    @property
    def homing_fault(self) -> bool:
        """The homing move before the scenario faulted (the scenario did not run)."""
        h = self.result.homing
        return h is not None and h.fault is not None

    def __repr__(self) -> str:
        m = self.metrics
        return (f"ScenarioRun({self.name!r}, E_p={m['E_p_mm']:.3f} mm, "
                f"E_rms={m['E_rms_mm']:.3f} mm, status={m.get('status', 'ok')!r}, "
                f"log={self.log!r})")


@dataclass(frozen=True, repr=False)
class DeployResult:
    """What :func:`deploy` produced.

    Attributes
    ----------
    controller : str
        The controller's file, or ``<controller>`` for one given in memory.
    config : ControllerConfig
    rig : str
        The rig specification.
    seed : int
    runs : tuple of ScenarioRun
        The scenarios that ran, in order.
    faults, warnings : tuple of dict
        Supervisor faults (at most one: it stops the run) and warnings, each with its
        ``scenario``.
    not_run : tuple of str
        Scenarios not run after a fault.
    realtime : bool
    """

    controller: str
    config: ControllerConfig
    rig: str
    seed: int
    runs: tuple[ScenarioRun, ...]
    faults: tuple[dict[str, Any], ...] = ()
    warnings: tuple[dict[str, Any], ...] = ()
    not_run: tuple[str, ...] = ()
    realtime: bool = False

    @property
    def exit_status(self) -> int:
        """The command's exit status: 0 done (warnings allowed), 3 a fault stopped the run."""
        return EXIT_FAULT if self.faults else 0

    def __getitem__(self, scenario: str) -> ScenarioRun:
        """The run of ``scenario``; :class:`KeyError` naming those that ran."""
        for r in self.runs:
            if r.name == scenario:
                return r
        raise KeyError(f"no run of {scenario!r}; ran: {', '.join(r.name for r in self.runs)}")

    def __repr__(self) -> str:
        runs = ", ".join(f"{r.name} E_p {r.metrics['E_p_mm']:.3f} mm" for r in self.runs)
        fault = f", fault {self.faults[0]['code']}" if self.faults else ""
        return (f"DeployResult(controller={self.controller!r} ({self.config.variant}), "
                f"rig={self.rig!r}, seed={self.seed}: {runs}{fault})")

    def summary(self) -> dict[str, Any]:
        """The object ``deploy --json`` prints."""
        timings = {r.name: r.result.loop.timing.as_dict() for r in self.runs
                   if not r.homing_fault}
        return {"scenarios": {r.name: r.metrics for r in self.runs},
                "faults": list(self.faults), "warnings": list(self.warnings),
                "realtime": {"enabled": bool(self.realtime), "scenarios": timings},
                "not_run": list(self.not_run), "controller": self.controller,
                "variant": self.config.variant, "rig": self.rig, "seed": self.seed}

    def table(self) -> str:
        """The paper's indices of every run beside Table 1's, as text."""
        from pneutune.control.sim.table import format_table

        rows = [(r.name, r.metrics, r.result.scenario.paper) for r in self.runs]
        scale = self.runs[0].result.scenario.scale if self.runs else 1.0
        return format_table(rows, f"deploy {self.controller} "
                            f"({self.config.variant}) on rig {self.rig}, seed {self.seed}",
                            scale)


def controller_source(controller: ControllerConfig | str | os.PathLike[str]
                      ) -> tuple[ControllerConfig, str, str]:
    """The config, a name for messages and the log, and its sha256.

    Parameters
    ----------
    controller : ControllerConfig or path-like
        controller.yaml (loaded strictly, contract 4) or a config in memory.

    Returns
    -------
    (ControllerConfig, str, str)
        The config; the file as given or ``<controller>``; the sha256 of the file's bytes, or
        of a config in memory its canonical JSON.

    Raises
    ------
    ConfigError
        An invalid controller.yaml.
    ExperimentError
        Neither a path nor a ControllerConfig.
    """
    if isinstance(controller, ControllerConfig):
        text = json.dumps(controller.to_dict(), sort_keys=True)
        return controller, "<controller>", hashlib.sha256(text.encode()).hexdigest()
    if not isinstance(controller, (str, os.PathLike)):
        raise argument_error(ExperimentError, "controller", "must be a controller.yaml path or "
                             f"a ControllerConfig, got {type(controller).__name__}")
    return load_controller(controller), os.fspath(controller), sha256_file(controller)


def deploy(controller: ControllerConfig | str | os.PathLike[str], rig: str = "sim",
           scenarios: str | Sequence[str] = "sine-0.5hz", *, seed: int | None = None,
           duration: float | None = None, fail_safe: str = "hold", home: str = "auto",
           realtime: bool = False, log: str | os.PathLike[str] | None = None,
           log_dir: str | os.PathLike[str] | None = None,
           progress: bool | None = False) -> DeployResult:
    """Run a controller against a rig, supervised, scenario after scenario.

    Parameters
    ----------
    controller : ControllerConfig or path-like
        controller.yaml (contract 4) or the config itself.
    rig : str
        ``sim[:P.yaml]`` (the simulated rig in this process, plant.yaml merged over the paper's
        rig), ``pipe-sim[:P.yaml]`` (the same in a child process over the pipe protocol) or
        ``exec:CMD ARGS`` (any driver program speaking pneutune.rig/1; docs/deploy.md).
    scenarios : str or sequence of str
        Scenario names or groups (``table1``, ``all``), or a comma-separated list of them.
    seed : int, optional
        Sensor-noise seed of a simulated rig (default the plant's ``sim.seed``); ``{seed}`` of
        an exec command.
    duration : float, optional
        Run only the first ``duration`` seconds of each scenario [s].
    fail_safe : str
        Valve state on a fault: ``hold`` (all closed) or ``exhaust``.
    home : str
        ``auto``, ``always`` or ``off``: the homing move to the scenario's start first.
    realtime : bool
        Pace the loop to wall time.
    log : path-like, optional
        Write the run log there (several scenarios: ``<stem>-<scenario>.mcap`` beside it).
    log_dir : path-like, optional
        Write each scenario's log as ``<log_dir>/<scenario>.mcap`` (``log`` wins).
    progress : bool or None
        A progress bar over the scenarios on stderr; None: only on a terminal.

    Returns
    -------
    DeployResult
        ``exit_status`` 3 when a supervisor fault stopped the run (the runs so far stand).

    Raises
    ------
    ConfigError
        An invalid controller or plant, or a rig whose Ts or pwm_hz differ from the
        controller's (nothing ran).
    ExperimentError
        A bad argument, scenario or reference outside the limits (nothing ran).
    RigIOError
        A driver that does not start for the first scenario (nothing ran).
    """
    cfg, name, sha = controller_source(controller)
    kind, rig_arg = parse_rig(rig)
    command, plant_path = (rig_arg, None) if kind == "exec" else (None, rig_arg)
    plant_cfg = load_sim_plant(plant_path)
    if command is None:  # an exec driver tells its rig in its hello, checked below
        rig_source = f"plant {plant_path}" if plant_path else "the default plant, the paper's rig"
        check_rig_compatible(cfg, plant_cfg.rig_metadata(), name, rig_source)
    resolved = resolve_scenarios(scenarios if isinstance(scenarios, str)
                                 else ",".join(scenarios))
    scaled: str | None = None
    if command is None:  # a simulated rig's stroke is known: fit the references up front
        resolved, scaled = fit_reference_to_limits(cfg, resolved, plant_cfg.rig_metadata(), name)
    if seed is not None and seed < 0:
        raise argument_error(ExperimentError, "seed", f"must be >= 0, got {seed}")
    if duration is not None and not (math.isfinite(duration) and duration > 0.0):
        raise argument_error(ExperimentError, "duration", f"must be > 0 s, got {duration}")
    if fail_safe not in FAIL_SAFE_MODES:
        raise argument_error(ExperimentError, "fail_safe", "must be one of "
                             f"{', '.join(sorted(FAIL_SAFE_MODES))}, got {fail_safe!r}")
    seed = plant_cfg.sim.seed if seed is None else seed
    plant_cfg = plant_cfg.with_updates({"sim": {"seed": seed}})
    settings = SupervisorSettings.from_controller(cfg)
    cfg_vec = pack(cfg)
    several = len(resolved) > 1
    base_meta = {"controller": name, "controller_sha256": sha, "rig": kind,
                 "fail_safe": fail_safe}
    base_meta.update({"rig_command": command} if command is not None else plant_meta(plant_path))

    runs: list[ScenarioRun] = []
    faults: list[dict[str, Any]] = []
    warnings: list[dict[str, Any]] = []
    if command is None:
        warnings += _mismatch_warnings(cfg, plant_cfg.rig_metadata(), name, rig_source)
        if scaled is not None:
            warnings.append(_scaled_warning("all", scaled))
    disable = None if progress is None else not progress
    for sc in tqdm(resolved, desc="scenarios", unit="scenario", disable=disable, leave=False):
        the_rig: Rig
        pcfg: PlantConfig | None
        if kind == "sim":
            the_rig, pcfg, _ = sim_rig_for(sc, plant_cfg, seed)
        else:
            try:
                if command is not None:  # the driver's rig is what it says it is: no truth
                    pcfg = None
                    the_rig = ExecRig(exec_command(command, sc.name, seed, float(cfg.rig.Ts)))
                else:
                    pcfg = scenario_plant(plant_cfg, sc)
                    the_rig = PipeRig(plant=plant_path, scenario=sc.name, seed=seed)
            except RigIOError as exc:
                if not runs:  # nothing ran: bad input
                    raise
                # a driver that ran an earlier scenario fails to start for this one: the runs
                # so far stand, this one is a rig_io fault at t = 0
                fault = Event(0.0, "error", "rig_io", f"the rig did not start: {exc}")
                faults.append({"scenario": sc.name, "phase": "scenario", **fault.as_dict()})
                break
        try:
            check_rig_compatible(cfg, the_rig.rig_metadata(), name, f"rig {kind}")
            if command is not None and not runs:  # the driver's rig, as its hello told it
                warnings += _mismatch_warnings(cfg, the_rig.rig_metadata(), name, f"rig {kind}")
            check_sampled_at_control_rate(the_rig, kind)
            (sc,), scaled = fit_reference_to_limits(cfg, [sc], the_rig.rig_metadata(), name)
            if scaled is not None:  # a driver's rig, as its hello tells it
                warnings.append(_scaled_warning(sc.name, scaled))
            res = run_scenario(cfg, sc, the_rig, supervisor=Supervisor(settings),
                               realtime=realtime, record_truth=command is None,
                               cfg_vec=cfg_vec, fail_safe=FAIL_SAFE_MODES[fail_safe],
                               duration=duration, plant=pcfg,
                               seed=seed if command is None or "{seed}" in command else None,
                               home=home)
        finally:
            the_rig.close()
        path: Path | None = None
        if log is not None:
            path = scenario_log_path(log, sc.name, several)
        elif log_dir is not None:
            path = Path(log_dir) / f"{sc.name}.mcap"
        if path is not None:
            res.save_log(os.fspath(path), run=base_meta)
        run = _scenario_run(sc.name, res, path)
        runs.append(run)
        warnings += [{"scenario": sc.name, **e.as_dict()} for e in res.loop.events
                     if e.level == "warning"]
        if res.fault is not None:
            faults.append({"scenario": sc.name,
                           "phase": "homing" if run.homing_fault else "scenario",
                           **res.fault.as_dict()})
            break
    ran = {r.name for r in runs}
    return DeployResult(name, cfg, rig, seed, tuple(runs), tuple(faults), tuple(warnings),
                        tuple(sc.name for sc in resolved if sc.name not in ran), realtime)


def _scenario_run(name: str, res: ScenarioResult, path: Path | None) -> ScenarioRun:
    """The run's metrics as ``deploy --json`` prints them."""
    m = res.metrics.as_dict()
    if path is not None:
        m["log"] = str(path)
    m["samples"] = res.loop.n_done
    m["events"] = [e.as_dict() for e in res.loop.events]
    if res.homing is not None:
        m["homing"] = {"status": "fault" if res.homing.fault is not None else "done",
                       "samples": res.homing.n_done, "timing": res.homing.timing.as_dict()}
    return ScenarioRun(name, m, res, None if path is None else str(path))


__all__ = [
    "EXIT_FAULT",
    "RIG_KINDS",
    "DeployResult",
    "ScenarioRun",
    "check_rig_compatible",
    "check_sampled_at_control_rate",
    "controller_source",
    "deploy",
    "fit_reference_to_limits",
    "geometry_warnings",
    "parse_rig",
    "scenario_log_path",
]
