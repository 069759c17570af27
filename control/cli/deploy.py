"""``deploy``: load a controller.yaml into the runtime and run it against a rig, supervised; or,
with ``--emit c``, write it as the C99 folder a target compiles."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pneutune.control.cli.common import (
    ArgumentParser,
    first_interrupt_only,
    info,
    make_parser,
    print_json,
    run_cli,
)
from pneutune.control.constants import HOME_MODES
from pneutune.control.law.cbuild import REALS
from pneutune.control.rig.deploy import DeployResult, deploy
from pneutune.control.rig.emit_c import EMIT_FORMATS, EmitResult, emit_c
from pneutune.control.rig.supervisor import FAIL_SAFE_MODES

#: Where logs go by default: ``<DEFAULT_LOG_DIR>/<scenario>.mcap``.
DEFAULT_LOG_DIR = Path("reports") / "deploy"

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
                      (pneutune/control/rig/wire.py; the interface a hardware driver implements)
  exec:"CMD ARGS"     any driver program speaking the pipe protocol pneutune.rig/1 on its
                      stdin/stdout (a C program on a DAQ card, a Python script on a serial
                      port; docs/deploy.md). Each scenario starts a fresh driver process; in
                      CMD, {scenario} and {seed} are replaced by the scenario's name and the
                      seed first, and {sample_period} by the controller's rig.Ts (a
                      simulated rig needs them, a hardware driver may ignore them),
                      then CMD is split like a shell would (no shell runs). Its hello gives the
                      rig block (Ts and pwm_hz must equal the controller's); a driver that is
                      not there, dies at once, sends a bad hello or none within 60 s is bad
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

For a target (--emit c --out DIR): nothing runs. The controller, checked as above, is written
as C99 a PLC or a microcontroller compiles without Python or a YAML parser: the law, the safety
supervisor and the controller API (control/law/c), and pt_config.c holding the controller as
`const pt_config_t PT_CONFIG` (the packed law and supervisor vectors bit for bit, the
--fail-safe duties, the file's sha256 and its provenance), with a Makefile and a README.txt:
build with `cc -std=c99 -O2 -c *.c` and link with -lm; -DPT_REAL_FLOAT builds in float (--real
float makes that the Makefile's default and checks every value fits a float). DIR must be new,
empty, or an earlier emit (replaced; its build products go with it); a folder holding anything
else is bad input (exit 2). A setting the C law does not handle is bad input too. The call
sequence, the memory footprint and a bare-metal example: docs/embedded.md.

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
  deploy reports/tune/controller.yaml --emit c --out build/axis1
         (the C99 folder for a target; cd build/axis1 && make, or cc -std=c99 -O2 -c *.c)
  deploy data/controller-paper.yaml --emit c --out build/axis1 --fail-safe exhaust --real float
         --json

scenarios: sine-0.5hz (default), sine-0.75hz, sine-0.5hz-heavy, square-0.5hz,
disturbance-0.5hz; table1 = the first four; all = all five; or a list such as
square-0.5hz,disturbance-0.5hz. Several scenarios write
F-<scenario>.mcap for --log F.mcap, or reports/deploy/<scenario>.mcap by default; a fault
stops the remaining scenarios.
"""


def _timing_line(name: str, timing: dict[str, Any]) -> str:
    line = (f"{name}: step p50/p99 {timing['step_p50_us']:.1f}/{timing['step_p99_us']:.1f} µs, "
            f"sensor-to-valve p50/p99 {timing['loop_p50_us']:.1f}/{timing['loop_p99_us']:.1f} µs")
    if timing["realtime"]:
        line += (f"; realtime: {timing['overruns']} overruns, jitter p50/p99/max "
                 f"{timing['jitter_p50_us']:.0f}/{timing['jitter_p99_us']:.0f}/"
                 f"{timing['jitter_max_us']:.0f} µs")
    return line


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``deploy``, a shell over :func:`pneutune.control.rig.deploy.deploy`;
    returns the exit status (0, 3; 2 via PneutuneError)."""

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
    parser.add_argument("--emit", choices=EMIT_FORMATS, metavar="c",
                        help="run nothing: write the controller as the C99 folder a target "
                             "compiles (needs --out; below)")
    parser.add_argument("--out", metavar="DIR",
                        help="with --emit c: the folder to write (new, empty, or an earlier emit)")
    parser.add_argument("--real", choices=REALS, default=None,
                        help="with --emit c: the precision the folder's Makefile builds, double "
                             "(default) or float (-DPT_REAL_FLOAT; every value checked to fit)")
    args = parser.parse_args(argv)

    if args.emit is not None or args.out is not None or args.real is not None:
        return _emit(parser, args)

    # everything is checked before anything runs (the library's own checks)
    with first_interrupt_only("deploy: Ctrl-C again ignored: closing the valves and writing "
                              "the log"):
        result = deploy(args.controller, rig=args.rig, scenarios=args.scenario,
                        seed=args.seed, duration=args.duration, fail_safe=args.fail_safe,
                        home=args.home, realtime=args.realtime, log=args.log,
                        log_dir=DEFAULT_LOG_DIR if args.log is None else None, progress=None)
    for run in result.runs:
        if args.plots and run.result.loop.n_done > 1 and not run.homing_fault:
            from pneutune.control.cli.plots import plot_closed_loop

            run.metrics["plots"] = [str(p) for p in
                                    plot_closed_loop(run.result.closed_loop_result(), args.plots)]
    if args.json:
        print_json(result.summary())
    else:
        _print_summary(result, args.plots)
    if result.faults:
        f = result.faults[0]
        ran = {r.name: r for r in result.runs}
        log = ran[f["scenario"]].log if f["scenario"] in ran else None
        where = ("during the homing move before scenario" if f.get("phase") == "homing"
                 else "in scenario")
        info(f"error: fault {f['code']} {where} {f['scenario']} at t={f['t']:.4f} s: "
             f"{f['message']} (log: {log or 'none written'})")
    return result.exit_status


#: Flags that only a run uses, with their defaults: given with --emit c, they are refused.
_RUN_ONLY: tuple[tuple[str, str, Any], ...] = (
    ("--rig", "rig", "sim"), ("--scenario", "scenario", "sine-0.5hz"),
    ("--realtime", "realtime", False), ("--log", "log", None), ("--seed", "seed", None),
    ("--duration", "duration", None), ("--plots", "plots", None), ("--home", "home", "auto"),
)


def _emit(parser: ArgumentParser, args: argparse.Namespace) -> int:
    """``--emit c``: write the folder, print what was written; nothing runs."""
    if args.emit is None:
        parser.error(f"{'--out' if args.out is not None else '--real'} needs --emit c")
    if args.out is None:
        parser.error("--emit c needs --out DIR")
    for flag, dest, default in _RUN_ONLY:
        if getattr(args, dest) != default:
            parser.error(f"{flag} does not apply with --emit c (nothing runs)")
    result = emit_c(args.controller, args.out, fail_safe=args.fail_safe,
                    real=args.real or "double")
    if args.json:
        print_json(result.summary())
    else:
        _print_emitted(result)
    return 0


def _print_emitted(result: EmitResult) -> None:
    """The folder, its files, the controller and the build line."""
    info(f"wrote {result.out}/: {', '.join(result.files)}")
    info(f"controller {result.controller} ({result.variant}), sha256 {result.sha256}, "
         f"fail-safe {result.fail_safe}")
    info(f"build: cd {result.out} && {result.build_line}, then link the objects with -lm "
         f"(or make; README.txt)")


def _print_summary(result: DeployResult, plots: str | None) -> None:
    """The table, the timings, the homing notes, the warnings and the files written."""
    info(result.table())
    for run in result.runs:
        m = run.metrics
        if "homing" in m:
            info(_timing_line(f"{run.name} (homing)", m["homing"]["timing"]))
        if not run.homing_fault:
            info(_timing_line(run.name, run.result.loop.timing.as_dict()))
    for run in result.runs:
        for e in run.metrics["events"]:
            if e["code"] == "homing":
                info(f"{run.name}: homing: {e['message']}")
    for w in result.warnings:
        info(f"warning: {w['scenario']}: t={w['t']:.3f} s: {w['code']}: {w['message']}")
    for run in result.runs:
        if run.log is not None:
            info(f"wrote {run.log}" + (f" (figures in {plots}/)" if "plots" in run.metrics
                                       else ""))
    if result.not_run:
        info(f"not run after the fault: {', '.join(result.not_run)}")


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)


if __name__ == "__main__":  # pragma: no cover
    entry()
