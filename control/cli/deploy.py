"""``deploy``: load a controller.yaml into the runtime and run it against a rig, supervised."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pneutune.control.cli.common import (
    info,
    make_parser,
    plant_meta,
    print_json,
    run_cli,
    scenario_log_path,
)
from pneutune.control.constants import HOME_MODES
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig, load_plant
from pneutune.control.errors import ConfigError, ExperimentError
from pneutune.control.law.layout import pack
from pneutune.control.rig.protocol import Rig
from pneutune.control.rig.supervisor import FAIL_SAFE_MODES
from pneutune.control.sim.table import format_table

#: Exit status of a run stopped by a supervisor fault.
EXIT_FAULT = 3
#: Where logs go by default: ``<DEFAULT_LOG_DIR>/<scenario>.mcap``.
DEFAULT_LOG_DIR = Path("reports") / "deploy"
#: Rig kinds of ``--rig``.
RIG_KINDS: tuple[str, ...] = ("sim", "pipe-sim", "exec")
#: Relative tolerance of the Ts and pwm_hz comparison between controller and rig.
RIG_MATCH_RTOL = 1.0e-9

DESCRIPTION = """\
Load a controller.yaml (contract 4, as `tune` writes it) into the controller runtime and run it
against a rig, under the safety supervisor; write the run as an MCAP log (contract 1:
/rig/sensors, /rig/valves, /control/reference, /control/state, /rig/events, rig metadata) that
`identify` accepts, and print the paper's indices beside its Table 1.

Loading is strict and nothing runs on an invalid config: an unknown key, a wrong type, a value
out of range, theta_min >= theta_max, or a rig.Ts / rig.pwm_hz that differs from the rig's each
give one `error:` line naming the file and the key, and exit status 2.

The runtime calls the same compiled control step as `simulate` every Ts. On the simulated rig
with the same plant and seed, `deploy` gives exactly the figures of `simulate --controller`.

Rigs (--rig):
  sim[:P.yaml]        the simulated rig in this process (plant.yaml merged over the paper's rig)
  pipe-sim[:P.yaml]   the same rig in a child process, over the example driver's pipe protocol
                      (pneutune/control/rig/pipe.py; the interface a hardware driver implements)
  exec:"CMD ARGS"     any driver program speaking the pipe protocol pneutune.rig/1 on its
                      stdin/stdout (a C program on a DAQ card, a Python script on a serial
                      port; docs/deploy.md). Each scenario starts a fresh driver process; in
                      CMD, {scenario} and {seed} are replaced by the scenario's name and the
                      seed first, and {sample_period} by the controller's rig.Ts (a
                      simulated rig needs them, a hardware driver may ignore them),
                      then CMD is split like a shell would (no shell runs). Its hello gives the
                      rig block (Ts and pwm_hz must equal the controller's); a driver that is
                      not there, dies at once, sends a bad hello or none within 10 s is bad
                      input (exit 2, with the driver's last stderr lines). A reply later than
                      2 s or an E reply during the run, or a driver that fails to start after
                      an earlier scenario ran, is a rig_io fault (exit 3).
                      `python -m pneutune.control.driver check "CMD ARGS"` checks a driver.

Safety supervisor (docs/deploy.md): a sensor reading NaN, stale or out of range, the supply
lost, the position outside limits.x_min/x_max, or a chamber above limits.p_max: in that very
sample the valves go to the fail-safe state (all closed, holding the piston; --fail-safe
exhaust vents both chambers instead), the event is logged on /rig/events and deploy exits 3.
Warnings (logged, the run goes on): the supply 1 bar away from the model's, or theta-hat of the
mass or friction held on its bound: run identify again.

Exit status: 0 done (warnings allowed); 2 bad input (nothing ran); 3 a supervisor fault stopped
the run (log written, `error:` line on stderr); 1 an internal failure.
"""

EPILOG = """\
examples:
  deploy data/controller-paper.yaml
  deploy reports/tune/controller.yaml --scenario all --json
  deploy data/controller-paper.yaml --scenario table1 --rig sim:my-plant.yaml --seed 3
  deploy data/controller-paper.yaml --scenario sine-0.75hz --realtime --log /tmp/run.mcap
  deploy data/controller-paper.yaml --rig pipe-sim --duration 2
  deploy data/controller-paper.yaml --scenario table1 --rig exec:"python -m
         pneutune.control.driver serve --scenario {scenario} --seed {seed}"
  deploy data/controller-paper.yaml --rig exec:"./rig_driver" --duration 2
  deploy reports/tune/controller.yaml --rig exec:"./rig_driver" --scenario all --home always
         (every scenario starts after a move to its x_r(0) and 1 s holding there)
  identify reports/deploy/sine-0.5hz.mcap         # close the loop: log -> identify -> tune

scenarios: sine-0.5hz (default), sine-0.75hz, sine-0.5hz-heavy, square-0.5hz,
disturbance-0.5hz; table1 = the first four; all = all five; or a list such as
square-0.5hz,disturbance-0.5hz. Several scenarios write
F-<scenario>.mcap for --log F.mcap, or reports/deploy/<scenario>.mcap by default; a fault
stops the remaining scenarios.
"""


def parse_rig(spec: str) -> tuple[str, str | None]:
    """Split a ``--rig`` value into (kind, argument).

    Returns
    -------
    (kind, argument)
        ``kind`` one of :data:`RIG_KINDS`; ``argument`` the plant path or None for ``sim`` and
        ``pipe-sim``, the driver command (with its placeholders) for ``exec``.

    Raises
    ------
    ExperimentError
        An unknown kind, an empty path, or a bad driver command
        (:func:`~pneutune.control.rig.pipe.exec_command`).
    """
    from pneutune.control.rig.pipe import exec_command

    kind, sep, arg = spec.partition(":")
    if kind not in RIG_KINDS:
        raise ExperimentError(f"--rig: unknown rig {kind!r}; expected sim[:P.yaml], "
                              f"pipe-sim[:P.yaml] or exec:\"CMD ARGS\"")
    if kind == "exec":
        exec_command(arg, "sine-0.5hz", 0, 1.0)  # the checks, before anything runs
        return kind, arg
    if sep and not arg:
        raise ExperimentError(f"--rig {spec!r}: the plant path after ':' is empty")
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


def check_reference_in_limits(controller: ControllerConfig, scenario: Any,
                              rig_meta: dict[str, Any], controller_file: str) -> None:
    """The scenario's reference must lie within the controller's position limits.

    Raises
    ------
    ExperimentError
        Naming the scenario, the span of its reference on this rig and the limits.
    """
    from pneutune.control.rig.runtime import scenario_reference

    x_r = scenario_reference(scenario, rig_meta)[:, 0]
    lo, hi = float(x_r.min()), float(x_r.max())
    lim = controller.limits
    if lo < lim.x_min or hi > lim.x_max:
        raise ExperimentError(f"scenario {scenario.name}: its reference spans [{lo * 1e3:.2f}, "
                              f"{hi * 1e3:.2f}] mm on this rig (centred mid-stroke), outside the "
                              f"limits [{lim.x_min * 1e3:.2f}, {lim.x_max * 1e3:.2f}] mm of "
                              f"{controller_file}: the rig's stroke is too short for it, or the "
                              f"controller's limits are another rig's")


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


def _log_path(log: str | None, scenario: str, several: bool) -> Path:
    if log is None:
        return DEFAULT_LOG_DIR / f"{scenario}.mcap"
    return scenario_log_path(log, scenario, several)


def _timing_line(name: str, timing: dict[str, Any]) -> str:
    line = (f"{name}: step p50/p99 {timing['step_p50_us']:.1f}/{timing['step_p99_us']:.1f} µs, "
            f"sensor-to-valve p50/p99 {timing['loop_p50_us']:.1f}/{timing['loop_p99_us']:.1f} µs")
    if timing["realtime"]:
        line += (f"; realtime: {timing['overruns']} overruns, jitter p50/p99/max "
                 f"{timing['jitter_p50_us']:.0f}/{timing['jitter_p99_us']:.0f}/"
                 f"{timing['jitter_max_us']:.0f} µs")
    return line


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``deploy``; returns the exit status (0, 3; 2 via PneutuneError)."""
    from pneutune.control.rig.pipe import ExecRig, PipeRig, RigIOError, exec_command
    from pneutune.control.rig.runtime import run_scenario, sim_rig_for
    from pneutune.control.rig.supervisor import Event, Supervisor, SupervisorSettings
    from pneutune.control.sim.closed_loop import scenario_plant
    from pneutune.control.sim.scenarios import resolve_scenarios

    parser = make_parser("deploy", DESCRIPTION, EPILOG)
    parser.add_argument("controller", metavar="C.yaml", help="controller.yaml (contract 4)")
    parser.add_argument("--rig", default="sim", metavar="RIG",
                        help="sim[:P.yaml] (default sim), pipe-sim[:P.yaml] or "
                             "exec:\"CMD ARGS\" (below)")
    parser.add_argument("--scenario", default="sine-0.5hz", metavar="S",
                        help="scenario name, table1, all, or a comma-separated list of them "
                             "(default sine-0.5hz)")
    parser.add_argument("--realtime", action="store_true",
                        help="pace the loop to wall time; report overruns and jitter")
    parser.add_argument("--log", metavar="F.mcap",
                        help="the log to write (default reports/deploy/<scenario>.mcap)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object on stdout (prose goes to stderr)")
    parser.add_argument("--seed", type=int, metavar="N",
                        help="sensor-noise seed of the simulated rig (default: sim.seed, 1); "
                             "{seed} of an exec: command")
    parser.add_argument("--duration", type=float, metavar="S",
                        help="run only the first S seconds of each scenario (a homing move "
                             "before it keeps its 4 s)")
    parser.add_argument("--fail-safe", choices=sorted(FAIL_SAFE_MODES), default="hold",
                        help="valve state on a fault: hold (all closed, default) or exhaust")
    parser.add_argument("--plots", metavar="DIR", help="write PNG figures of each run to DIR")
    parser.add_argument("--home", choices=HOME_MODES, default="auto",
                        help="move the piston from where it rests to the scenario's start "
                             "x_r(0) under the controller and supervisor before the scenario "
                             "(a 3 s quintic, then 1 s holding): auto (default) when it rests "
                             "more than 1 mm away, always, or off (a distant piston is then "
                             "the fault start_position)")
    args = parser.parse_args(argv)

    # --- everything is checked before anything runs ----------------------------------------
    controller = load_controller(args.controller)
    kind, rig_arg = parse_rig(args.rig)
    command, plant_path = (rig_arg, None) if kind == "exec" else (None, rig_arg)
    plant_cfg = load_plant(plant_path)
    if command is None:  # an exec: driver tells its rig in its hello, checked below
        rig_source = f"plant {plant_path}" if plant_path else "the default plant, the paper's rig"
        check_rig_compatible(controller, plant_cfg.rig_metadata(), args.controller, rig_source)
    scenarios = resolve_scenarios(args.scenario)
    if command is None:
        for sc in scenarios:
            check_reference_in_limits(controller, sc, plant_cfg.rig_metadata(), args.controller)
    if args.seed is not None and args.seed < 0:
        raise ExperimentError(f"--seed must be >= 0, got {args.seed}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0.0):
        raise ExperimentError(f"--duration must be > 0 s, got {args.duration}")
    seed = plant_cfg.sim.seed if args.seed is None else args.seed
    plant_cfg = plant_cfg.with_updates({"sim": {"seed": seed}})
    settings = SupervisorSettings.from_controller(controller)
    cfg_vec = pack(controller)
    fail_safe = FAIL_SAFE_MODES[args.fail_safe]
    several = len(scenarios) > 1
    base_meta = {"controller": args.controller, "controller_sha256": sha256_file(args.controller),
                 "rig": kind, "fail_safe": args.fail_safe}
    base_meta.update({"rig_command": command} if command is not None else plant_meta(plant_path))

    results: dict[str, dict[str, Any]] = {}
    timings: dict[str, dict[str, Any]] = {}
    faults: list[dict[str, Any]] = []
    warnings: list[dict[str, Any]] = []
    rows = []
    for sc in tqdm(scenarios, desc="scenarios", unit="scenario", disable=None, leave=False):
        rig: Rig
        pcfg: PlantConfig | None
        if kind == "sim":
            rig, pcfg, _ = sim_rig_for(sc, plant_cfg, seed)
        else:
            try:
                if command is not None:  # the driver's rig is what it says it is: no truth
                    pcfg = None
                    rig = ExecRig(exec_command(command, sc.name, seed,
                                               float(controller.rig.Ts)))
                else:
                    pcfg = scenario_plant(plant_cfg, sc)
                    rig = PipeRig(plant=plant_path, scenario=sc.name, seed=seed)
            except RigIOError as exc:
                if not results:  # nothing ran: bad input (exit 2, the driver's stderr tail)
                    raise
                # a driver that ran an earlier scenario fails to start for this one: the runs
                # so far stand (their logs are written), this one is a rig_io fault at t = 0
                fault = Event(0.0, "error", "rig_io", f"the rig did not start: {exc}")
                faults.append({"scenario": sc.name, "phase": "scenario", **fault.as_dict()})
                break
        try:
            check_rig_compatible(controller, rig.rig_metadata(), args.controller,
                                 f"rig {kind}")
            check_sampled_at_control_rate(rig, kind)
            check_reference_in_limits(controller, sc, rig.rig_metadata(), args.controller)
            res = run_scenario(controller, sc, rig, supervisor=Supervisor(settings),
                               realtime=args.realtime, record_truth=command is None,
                               cfg_vec=cfg_vec, fail_safe=fail_safe, duration=args.duration,
                               plant=pcfg,
                               seed=seed if command is None or "{seed}" in command else None,
                               home=args.home)
        finally:
            rig.close()
        path = _log_path(args.log, sc.name, several)
        res.save_log(os.fspath(path), run=base_meta)
        m = res.metrics.as_dict()
        m["log"] = str(path)
        m["samples"] = res.loop.n_done
        m["events"] = [e.as_dict() for e in res.loop.events]
        homing_fault = res.homing is not None and res.homing.fault is not None
        if res.homing is not None:
            m["homing"] = {"status": "fault" if homing_fault else "done",
                           "samples": res.homing.n_done,
                           "timing": res.homing.timing.as_dict()}
        results[sc.name] = m
        if not homing_fault:  # a move that faulted has its timing under "homing" only
            timings[sc.name] = res.loop.timing.as_dict()
        rows.append((sc.name, m, sc.paper))
        warnings += [{"scenario": sc.name, **e.as_dict()} for e in res.loop.events
                     if e.level == "warning"]
        if args.plots and res.loop.n_done > 1 and not homing_fault:
            from pneutune.control.cli.plots import plot_closed_loop

            m["plots"] = [str(p) for p in plot_closed_loop(res.closed_loop_result(), args.plots)]
        if res.fault is not None:
            faults.append({"scenario": sc.name, "phase": "homing" if homing_fault else "scenario",
                           **res.fault.as_dict()})
            break

    not_run = [sc.name for sc in scenarios if sc.name not in results]
    if args.json:
        print_json({"scenarios": results, "faults": faults, "warnings": warnings,
                    "realtime": {"enabled": bool(args.realtime), "scenarios": timings},
                    "not_run": not_run, "controller": args.controller,
                    "variant": controller.variant, "rig": args.rig, "seed": seed})
    else:
        info(format_table(rows, f"deploy {args.controller} ({controller.variant}) on rig "
                                f"{args.rig}, seed {seed}"))
        for name, m in results.items():
            if "homing" in m:
                info(_timing_line(f"{name} (homing)", m["homing"]["timing"]))
            if name in timings:
                info(_timing_line(name, timings[name]))
        for name, m in results.items():
            for e in m["events"]:
                if e["code"] == "homing":
                    info(f"{name}: homing: {e['message']}")
        for w in warnings:
            info(f"warning: {w['scenario']}: t={w['t']:.3f} s: {w['code']}: {w['message']}")
        for m in results.values():
            info(f"wrote {m['log']}" + (f" (figures in {args.plots}/)" if "plots" in m else ""))
        if not_run:
            info(f"not run after the fault: {', '.join(not_run)}")
    if faults:
        f = faults[0]
        log = results[f["scenario"]]["log"] if f["scenario"] in results else "none written"
        where = ("during the homing move before scenario" if f.get("phase") == "homing"
                 else "in scenario")
        info(f"error: fault {f['code']} {where} {f['scenario']} at t={f['t']:.4f} s: "
             f"{f['message']} (log: {log})")
        return EXIT_FAULT
    return 0


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)


if __name__ == "__main__":  # pragma: no cover
    entry()
