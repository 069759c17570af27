"""``record``: run an excitation protocol (the identification or the commissioning run) on any
rig, supervised, and log it for ``identify``."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from pneutune.control.cli.common import (
    first_interrupt_only,
    info,
    make_parser,
    print_json,
    run_cli,
)
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.errors import ExperimentError
from pneutune.control.logs.recording import plant_meta
from pneutune.control.logs.writer import ZSTD_LEVELS
from pneutune.control.rig.contacts import CONTACT_WARN_FACTOR
from pneutune.control.rig.excitation import (
    DEFAULT_SENSOR_TIMEOUT,
    DEFAULT_STROKE_MARGIN,
    ProtocolRun,
)
from pneutune.control.rig.excitation_plan import EXPERIMENTS, default_sample_period
from pneutune.control.rig.identification_run import DEFAULT_CONTACT_SPEED
from pneutune.control.rig.supervisor import FAIL_SAFE_MODES

#: Exit status of a run stopped by a supervisor fault (or a rig that failed): the log is written.
EXIT_FAULT = 3
#: Exit status of a run stopped by Ctrl-C: the log is written.
EXIT_INTERRUPTED = 130
#: Highest approach speed onto an end stop that ``--contact-speed`` takes [m/s].
MAX_CONTACT_SPEED = 0.5

DESCRIPTION = """\
Run an excitation protocol on a rig, under the safety supervisor, and write the run as an MCAP
log (contract pneutune.log/1, every segment labelled on /experiment/segment) for `identify`.
It needs no controller: the protocol's loops are designed from the stroke alone.

Protocols (--experiment):
  identification   each valve charges and vents its chamber with the piston held on an end
                   stop (full duty, repeated, then a duty sweep), the pressurised chamber
                   rests with its valves shut, then position-loop ramps at 3-100 mm/s and
                   sines of rising frequency (about 150 s on the paper's rig). Logged every
                   0.5 ms by default, which resolves the moving mass.
  commissioning    another vendor's protocol: valve staircases on the end stops, a velocity
                   loop at 2-80 mm/s, full-duty bursts with braking pulses (about 80 s).
                   Logged at the control rate by default.

Rigs (--rig), as in `deploy`:
  sim[:P.yaml]        the simulated rig in this process (default; plant.yaml merged over the
                      paper's rig)
  pipe-sim[:P.yaml]   the same rig in a child process, over the pipe protocol
  exec:"CMD ARGS"     any driver program speaking pneutune.rig/1 (docs/deploy.md). In CMD,
                      {scenario} is replaced by the experiment's name, {seed} by --seed and
                      {sample_period} by --sample-period (default 0.0005 for the
                      identification run). The driver's hello gives its sample period Ts and
                      its rig block (stroke, supply, and rig.Ts, the control period); Ts must
                      divide rig.Ts. The duties change every rig.Ts; every sample is logged.

Sample period: --sample-period S asks the rig to sample every S seconds (a driver must then
say Ts = S in its hello). Without it, a simulated rig samples at the protocol's default and a
driver at the period its hello gives.

Safety: the supervisor checks every sample as in `deploy` (NaN, out-of-range or stale sensors,
supply loss, a chamber above p_s + 1 bar or --p-max, the stroke limits). Outside the planned
end-stop contacts of the valve tests the piston must stay --stroke-margin of the stroke away
from either end stop. The valve tests reach their stops by a ramp at --contact-speed (default
50 mm/s), and the log shows the speed measured at every contact. A fault, or Ctrl-C, sends the
valves to the fail-safe state (--fail-safe) in that sample and writes the log of the completed
segments: `identify` uses what is there and says what is missing. --plan prints what the run
will do and moves nothing (a driver is only asked for its hello).

Exit status: 0 done; 2 bad input (nothing moved); 3 a fault stopped the run (log written);
130 interrupted by Ctrl-C (log written); 1 an internal failure.
"""

EPILOG = """\
examples:
  record --experiment identification --out data/my-run.mcap
  record --experiment identification --rig sim:plant.yaml --seed 3 --out run.mcap
  record --experiment identification --rig exec:"./rig_driver --sample-period {sample_period}" \\
         --sample-period 0.0005 --plan
  record --experiment identification --rig exec:"./rig_driver --sample-period {sample_period}" \\
         --sample-period 0.0005 --out run.mcap
  record --experiment identification --rig exec:"./rig_driver" --segments friction \\
         --out friction-after-seal-change.mcap      (rerun the friction ramps only)
  record --experiment commissioning --rig pipe-sim --segments 'valves:*' --out v.mcap
  identify run.mcap friction-after-seal-change.mcap   (one model from both logs)

--segments takes comma-separated groups or label patterns: rest, valves:a, valves:b,
friction, acceleration (identification) or bursts (commissioning); or labels such as
'constant_speed:*'. The chosen segments run in protocol order.
"""


@dataclass(frozen=True)
class RecordOptions:
    """What ``record`` (and ``simulate --experiment``) runs.

    Attributes
    ----------
    experiment : str
        ``identification`` or ``commissioning``.
    rig : str
        ``sim[:P.yaml]``, ``pipe-sim[:P.yaml]`` or ``exec:CMD``.
    out : str or None
        The log to write (required unless ``plan``).
    sample_period : float or None
        The sample period asked for [s].
    seed : int or None
        Noise seed of a simulated rig; ``{seed}`` of a driver command.
    segments : str or None
        ``--segments`` patterns.
    contact_speed : float
        Approach speed onto the end stops [m/s].
    stroke_margin : float
        Margin from the end stops outside the planned contacts, fraction of the stroke.
    p_max : float or None
        Highest chamber pressure [Pa abs].
    fail_safe : str
        ``hold`` or ``exhaust``.
    compression_level : int or None
        zstd level of the log.
    plan : bool
        Print the plan only.
    json : bool
        One JSON object on stdout.
    """

    experiment: str
    rig: str = "sim"
    out: str | None = None
    sample_period: float | None = None
    seed: int | None = None
    segments: str | None = None
    contact_speed: float = DEFAULT_CONTACT_SPEED
    stroke_margin: float = DEFAULT_STROKE_MARGIN
    p_max: float | None = None
    fail_safe: str = "hold"
    compression_level: int | None = None
    plan: bool = False
    json: bool = False


def _check(opts: RecordOptions) -> None:
    if opts.experiment not in EXPERIMENTS:
        raise ExperimentError(f"--experiment must be one of {', '.join(EXPERIMENTS)}, got "
                              f"{opts.experiment!r}")
    if opts.out is None and not opts.plan:
        raise ExperimentError(f"--experiment {opts.experiment} needs --out F.mcap (or --plan)")
    if opts.sample_period is not None and not (math.isfinite(opts.sample_period)
                                               and opts.sample_period > 0.0):
        raise ExperimentError(f"--sample-period must be > 0 s, got {opts.sample_period}")
    if not (math.isfinite(opts.contact_speed) and 0.0 < opts.contact_speed <= MAX_CONTACT_SPEED):
        raise ExperimentError(f"--contact-speed must lie in (0, {MAX_CONTACT_SPEED:g}] m/s, got "
                              f"{opts.contact_speed}")
    if opts.seed is not None and opts.seed < 0:
        raise ExperimentError(f"--seed must be >= 0, got {opts.seed}")
    if opts.compression_level is not None and opts.compression_level not in ZSTD_LEVELS:
        raise ExperimentError(f"--compression-level must be in {ZSTD_LEVELS.start}.."
                              f"{ZSTD_LEVELS.stop - 1}, got {opts.compression_level}")
    if opts.fail_safe not in FAIL_SAFE_MODES:
        raise ExperimentError(f"--fail-safe must be one of {', '.join(sorted(FAIL_SAFE_MODES))}, "
                              f"got {opts.fail_safe!r}")


def _open_rig(opts: RecordOptions) -> tuple[Any, dict[str, str], bool, int | None]:
    """The rig, its ``run`` metadata, whether it tells the truth, and the seed used (None for a
    driver whose command takes no ``{seed}``)."""
    from pneutune.control.plant.params import load_sim_plant
    from pneutune.control.rig.deploy import parse_rig
    from pneutune.control.rig.exec_rig import ExecRig, PipeRig, exec_command
    from pneutune.control.rig.simrig import SimRig
    from pneutune.control.rig.wire import divides

    kind, arg = parse_rig(opts.rig)
    if kind == "exec":
        assert arg is not None
        seed = 1 if opts.seed is None else opts.seed
        asked = opts.sample_period
        fill = asked
        if fill is None and opts.experiment == "identification":
            fill = default_sample_period(opts.experiment, 1.0)
        if fill is None and "{sample_period}" in arg:
            raise ExperimentError(f"--rig {opts.rig!r}: its command asks for {{sample_period}}; "
                                  f"give --sample-period S (the commissioning run logs at the "
                                  f"control rate, rig.Ts, by default)")
        rig = ExecRig(exec_command(arg, opts.experiment, seed, fill))
        meta = {"rig": "exec", "rig_command": arg}
        if "{seed}" not in arg:  # the driver's rig is what it is: no seed to record
            seed = None
        if asked is not None and not math.isclose(rig.Ts, asked, rel_tol=1e-9, abs_tol=0.0):
            rig.close()
            raise ExperimentError(f"--rig {opts.rig!r}: the driver's hello says Ts = {rig.Ts!r} s, "
                                  f"but --sample-period asked for {asked!r} s (does its "
                                  f"command pass {{sample_period}} on?)")
        return rig, meta, False, seed
    plant_cfg = load_sim_plant(arg)
    seed = plant_cfg.sim.seed if opts.seed is None else opts.seed
    plant_cfg = plant_cfg.with_updates({"sim": {"seed": seed}})
    control_Ts = float(plant_cfg.rig.Ts)
    period = (default_sample_period(opts.experiment, control_Ts) if opts.sample_period is None
              else opts.sample_period)
    if not divides(period, control_Ts):
        raise ExperimentError(f"--sample-period {period!r} s must divide the rig's control period "
                              f"rig.Ts = {control_Ts!r} s into whole samples")
    meta = {"rig": kind, **plant_meta(arg)}
    # the commissioning run stands for a log of a rig you did not build: no simulator truth
    truth = opts.experiment == "identification"
    if kind == "sim":
        return SimRig(plant_cfg, seed=seed, sample_period=period), meta, truth, seed
    rig = PipeRig(plant=arg, scenario=opts.experiment, seed=seed, sample_period=period)
    return rig, meta, truth, seed


def _print_plan(p: dict[str, Any], rig_meta: dict[str, Any], sample_period: float,
                name: str) -> None:
    lines = [f"plan of the {name} run: {len(p['segments'])} segments, {p['total_s']:.1f} s; "
             f"duties every rig.Ts = {float(rig_meta['Ts']) * 1e3:g} ms, sensors logged every "
             f"{sample_period * 1e3:g} ms"]
    width = max((len(r["label"]) for r in p["segments"]), default=10)
    t = 0.0
    for r in p["segments"]:
        lines.append(f"  {t:7.2f} s  {r['label']:<{width}}  {r['duration_s']:6.2f} s  {r['what']}")
        t += r["duration_s"]
    lines.append(f"total: {p['total_s']:.1f} s")
    lines.append(f"peak duty: {p['peak_duty']:g}")
    ps = p["peak_speed"]
    lines.append(f"peak planned speed: {ps['m_per_s'] * 1e3:.0f} mm/s ({ps['segment']})"
                 if ps["segment"] else "peak planned speed: none (no segment moves the piston "
                                       "under a loop)")
    for c in p["contacts"]:
        lines.append(f"end-stop contact: {c['stop']} in {c['segment']}, approach at "
                     f"{c['speed_m_per_s'] * 1e3:g} mm/s")
    if not p["contacts"]:
        lines.append("end-stop contacts: none")
    for m in p["open_loop_motion"]:
        lines.append(f"open-loop full-duty motion: {m['segment']} for {m['duration_s'] * 1e3:g} "
                     f"ms (speed not planned; the stroke limits hold)")
    for pr in p["pressures"]:
        lines.append(f"valve tests, chamber {pr['chamber'].upper()}: {pr['low_pa'] / 1e5:.3g} to "
                     f"{pr['high_pa'] / 1e5:.3g} bar abs (ambient to the supply p_s), through "
                     f"{', '.join(pr['valves'])} in {pr['segments']} segments")
    if "limits" in p:
        lim = p["limits"]
        lines.append(f"supervisor: x within [{lim['x_min'] * 1e3:.2f}, {lim['x_max'] * 1e3:.2f}] "
                     f"mm outside the contacts, chambers below {lim['p_max'] / 1e5:.3g} bar abs, "
                     f"supply above {lim['supply_min'] / 1e5:.3g} bar abs, sensors fresh within "
                     f"{lim['sensor_timeout_s'] * 1e3:g} ms")
    info("\n".join(lines))


def execute(opts: RecordOptions) -> int:
    """Run ``record`` with the given options; returns the exit status (0, 3, 130).

    Raises
    ------
    PneutuneError
        Bad input (exit 2 from the command): nothing moved.
    """
    _check(opts)
    rig, meta, truth, seed = _open_rig(opts)
    with first_interrupt_only("record: Ctrl-C again ignored: closing the valves and writing the "
                              "log of the completed segments"):
        return _record(opts, rig, meta, truth, seed)


def _record(opts: RecordOptions, rig: Any, meta: dict[str, str], truth: bool,
            seed: int | None) -> int:
    """The run on an open rig, then its log (:func:`execute`)."""
    from pneutune.control.rig.excitation import execute_protocol, protocol_settings
    from pneutune.control.rig.excitation_plan import (
        check_stroke,
        experiment_protocol,
        plan,
        protocol_band,
        select_segments,
    )
    from pneutune.control.rig.supervisor import Supervisor

    try:
        rig_meta = dict(rig.rig_metadata())
        sample_period = float(rig.Ts)
        segments = select_segments(
            experiment_protocol(opts.experiment, rig_meta, contact_speed=opts.contact_speed),
            opts.segments, rig_meta)
        check_stroke(segments, rig_meta)
        settings = protocol_settings(rig_meta, margin=opts.stroke_margin, p_max=opts.p_max,
                                     sensor_timeout_s=DEFAULT_SENSOR_TIMEOUT)
        the_plan = plan(segments, rig_meta, settings)
        if opts.plan:
            if opts.json:
                print_json({"plan": the_plan, "experiment": opts.experiment, "rig": opts.rig,
                            "sample_period": sample_period, "rig_block": rig_meta})
            else:
                _print_plan(the_plan, rig_meta, sample_period, opts.experiment)
            return 0
        bar = tqdm(total=1, desc=f"{opts.experiment} run", disable=None, leave=False,
                   bar_format="{percentage:3.0f}%|{bar}| {desc}")

        def progress(done: int, total: int, label: str) -> None:
            bar.total = max(total, 1)
            bar.n = done
            bar.set_description_str(f"{label}, {(total - done) * sample_period:.0f} s of the "
                                    f"run left", refresh=False)
            bar.refresh()

        try:
            run = execute_protocol(rig, segments, protocol_band(rig_meta),
                                   supervisor=Supervisor(settings),
                                   fail_safe=FAIL_SAFE_MODES[opts.fail_safe],
                                   record_truth=truth, progress=progress)
        finally:
            bar.close()
    finally:
        rig.close()
    return _finish(opts, run, rig_meta, meta, seed)


def _finish(opts: RecordOptions, run: ProtocolRun, rig_meta: dict[str, Any],
            meta: dict[str, str], seed: int | None) -> int:
    assert opts.out is not None
    rec = run.recording
    status = ("ok" if run.fault is None else "interrupted" if run.interrupted else "fault")
    run_meta = {**({} if seed is None else {"seed": str(seed)}),
                "experiment": opts.experiment, **meta,
                "status": status, "fail_safe": opts.fail_safe,
                "contact_speed": repr(float(opts.contact_speed)),
                "segments_completed": f"{run.completed}/{len(run.segments)}"}
    if opts.segments:
        run_meta["segments"] = opts.segments
    if run.fault is not None:
        run_meta["fault"] = run.fault.code
        if run.missing:
            run_meta["stopped_in"] = run.missing[0]
    # An excitation run's log is large (288k samples at 0.5 ms): no chunk or message indexes
    # (viewers read it linearly) and /sim/truth at the control period, which no identification
    # uses (docs/architecture.md, "Run logs").
    truth_every = max(1, round(float(rig_meta["Ts"]) / rec.Ts))
    rec.save(opts.out, rig=rig_meta, run=run_meta, indexed=False, truth_every=truth_every,
             compression_level=opts.compression_level)
    size = os.path.getsize(opts.out)
    topics = ["/rig/sensors", "/rig/valves"] if rec.n else []
    if rec.reference_ is not None and rec.n and bool(np.isfinite(rec.reference_[:, 0]).any()):
        topics.append("/control/reference")
    topics += ["/experiment/segment"] if rec.segments_ else []
    topics += ["/sim/truth"] if rec.truth_ is not None and rec.n else []
    topics += ["/rig/events"] if rec.events_ else []
    summary = {
        "out": opts.out, "experiment": opts.experiment, "seed": seed, "rig": opts.rig,
        "status": status, "duration_s": rec.n * rec.Ts, "samples": rec.n,
        "sample_period": rec.Ts, "control_period": float(rig_meta["Ts"]),
        "segments": len(rec.segments_), "segments_planned": len(run.segments),
        "missing_segments": run.missing, "topics": topics,
        "contacts": [c.as_dict() for c in run.contacts],
        "fault": None if run.fault is None else run.fault.as_dict(),
        "bytes": size, "sha256": sha256_file(opts.out),
    }
    if opts.json:
        print_json(summary)
    else:
        info(f"wrote {opts.out}: {opts.experiment} run, {summary['duration_s']:.1f} s, "
             f"{rec.n} samples every {rec.Ts * 1e3:g} ms, {len(rec.segments_)} segments, "
             f"{size / 1e6:.2f} MB, seed {seed}")
        info("topics: " + ", ".join(topics))
        for c in run.contacts:
            fast = c.speed > CONTACT_WARN_FACTOR * c.planned
            info(f"{'warning: ' if fast else ''}end-stop contact: {c.stop} at t={c.t:.3f} s, "
                 f"{c.speed * 1e3:.1f} mm/s (planned {c.planned * 1e3:g} mm/s"
                 + (f"; more than {CONTACT_WARN_FACTOR:g} times it: lower --contact-speed)"
                    if fast else ")"))
        if not rec.n:
            info("no segment completed: the log holds the run record and its events only")
    if run.fault is None:
        return 0
    left = (f"{len(run.missing)} segment(s) not run, from {run.missing[0]}" if run.missing
            else "every segment ran")
    info(f"error: {run.fault.code} at t={run.fault.t:.4f} s: {run.fault.message} (log: "
         f"{opts.out}; {left})")
    return EXIT_INTERRUPTED if run.interrupted else EXIT_FAULT


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``record``."""
    parser = make_parser("record", DESCRIPTION, EPILOG)
    parser.add_argument("--experiment", required=True, choices=EXPERIMENTS,
                        help="the protocol to run (above)")
    parser.add_argument("--rig", default="sim", metavar="RIG",
                        help="sim[:P.yaml] (default), pipe-sim[:P.yaml] or exec:\"CMD ARGS\"")
    parser.add_argument("--out", metavar="F.mcap", help="the log to write")
    parser.add_argument("--sample-period", type=float, metavar="S",
                        help="sample period [s], dividing rig.Ts (default: 0.0005 for "
                             "identification, rig.Ts for commissioning on a simulated rig; the "
                             "driver's own for exec:)")
    parser.add_argument("--seed", type=int, metavar="N",
                        help="noise seed of a simulated rig; {seed} of an exec: command")
    parser.add_argument("--segments", metavar="P[,P...]",
                        help="run only these groups or label patterns (below)")
    parser.add_argument("--contact-speed", type=float, default=DEFAULT_CONTACT_SPEED,
                        metavar="V", help="approach speed onto the end stops [m/s] (default "
                                          f"{DEFAULT_CONTACT_SPEED:g})")
    parser.add_argument("--stroke-margin", type=float, default=DEFAULT_STROKE_MARGIN,
                        metavar="F", help="keep the piston this fraction of the stroke from "
                                          "the end stops outside the planned contacts (default "
                                          f"{DEFAULT_STROKE_MARGIN:g})")
    parser.add_argument("--p-max", type=float, metavar="PA",
                        help="highest chamber pressure [Pa abs] (default p_s + 1 bar)")
    parser.add_argument("--fail-safe", choices=sorted(FAIL_SAFE_MODES), default="hold",
                        help="valve state on a fault or Ctrl-C: hold (all closed, default) or "
                             "exhaust")
    parser.add_argument("--compression-level", type=int, metavar="L",
                        help="zstd level of the log's chunks, 1-22 (default 3)")
    parser.add_argument("--plan", action="store_true",
                        help="print the segments, durations, speeds, contacts and pressures; "
                             "move nothing")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object on stdout (prose goes to stderr)")
    args = parser.parse_args(argv)
    return execute(RecordOptions(
        experiment=args.experiment, rig=args.rig, out=args.out, sample_period=args.sample_period,
        seed=args.seed, segments=args.segments, contact_speed=args.contact_speed,
        stroke_margin=args.stroke_margin, p_max=args.p_max, fail_safe=args.fail_safe,
        compression_level=args.compression_level, plan=args.plan, json=args.json))


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)


if __name__ == "__main__":  # pragma: no cover
    entry()
