"""``simulate``: run the simulated rig, open loop (identification or commissioning run) or
closed loop."""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Sequence
from typing import Any

from tqdm import tqdm

from pneutune.control.cli.common import info, make_parser, print_json, run_cli
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError
from pneutune.control.logs.recording import plant_meta
from pneutune.control.logs.writer import ZSTD_LEVELS
from pneutune.control.plant.params import load_sim_plant
from pneutune.control.rig.deploy import (
    check_rig_compatible,
    fit_reference_to_limits,
    scenario_log_path,
)
from pneutune.control.sim.table import format_table

DESCRIPTION = """\
Run the simulated rig (the paper's Sec. 2 model with valve switching, stiction, end stops and
noisy sensors) and write the run as an MCAP log (contract pneutune.log/1) that `identify`,
Foxglove or any MCAP reader opens.

Three modes:

  --experiment identification
      the identification run: each valve charging/discharging its chamber with the piston on
      an end stop (full duty and a duty sweep), ramps at several speeds in both directions,
      sines of rising frequency, rest. No tuned controller is needed: a proportional loop
      designed from the stroke alone moves the piston. --out is required. The loop updates
      the duties every rig.Ts (4 ms); the sensors are logged every --sample-period (default
      0.5 ms, a 2 kHz acquisition), fast enough to resolve the lag of the motion behind the
      pressure force that carries the moving mass (docs/identifiability.md).

  --experiment commissioning
      a second, independent protocol, as another rig's commissioning engineer would run it
      (about 76 s): an ascending duty staircase on each valve in turn with the piston held on
      an end stop (from ambient for a charging valve, from supply for an exhausting one),
      constant-velocity moves at 2-80 mm/s in both directions under a PI velocity loop
      designed from the stroke and rig.Ts alone, full-duty bursts with short braking pulses
      and closed-valve coasting, rest. --out is required. Logged at the control rate rig.Ts
      (--sample-period to log faster) and without /sim/truth, like a log from a rig you did
      not build.

  Both are `record --experiment NAME --rig sim[:P.yaml]`, the same code that runs them on
  a real rig through a driver, supervised (see `record --help`: --plan, --segments,
  --contact-speed).

  Which one: identification makes the log `identify` is designed around (its 0.5 ms
  samples resolve the moving mass); commissioning checks that `identify`, and the model it
  gives, hold up on a log of another design and at the control rate, where the moving mass
  is not resolved (`identify --mass`, or log it with --sample-period 0.0005). Either runs
  on any --plant.

  --controller C.yaml --scenario S
      closed loop: the controller of C.yaml (contract 4) tracks a scenario; prints E_p and
      E_rms over the last three periods (the paper's Sec. 5.1 indices) beside the paper's
      Table 1. Scenarios:
        sine-0.5hz         17.5 sin(pi t) mm, M = 1.05 kg
        sine-0.75hz        17.5 sin(1.5 pi t) mm
        sine-0.5hz-heavy   as sine-0.5hz with a 1.136 kg payload (M = 2.18 kg)
        square-0.5hz       smooth square, 17.5 mm, 0.8 s quintic edges
        disturbance-0.5hz  sine-0.5hz with 30 N at 7.6 s, 80 N at 9.8 s, removed at 11.9 s
        table1             the first four;  all: all five
"""

EPILOG = """\
examples:
  simulate --experiment identification --seed 3 --out /tmp/r.mcap
  simulate --experiment identification --sample-period 0.004 --out /tmp/r4ms.mcap
  simulate --experiment commissioning --plant plant.yaml --seed 5 --out /tmp/c.mcap
  simulate --controller data/controller-paper.yaml --scenario table1
  simulate --controller data/controller-paper.yaml --scenario all --json
  simulate --controller data/controller-paper.yaml --scenario table1 --law c-float
  simulate --controller reports/tune/controller.yaml --scenario sine-0.5hz --out run.mcap \\
           --plots reports/figs

With several scenarios, --out F.mcap writes F-<scenario>.mcap for each. plant.yaml is merged
over the paper's rig (contract 2). The same seed gives the same numbers in any
process.
"""


def _experiment(args: Any, seed: int) -> int:
    """``--experiment``: ``record`` on the simulated rig in process (the same code)."""
    from pneutune.control.cli.record import RecordOptions, execute

    if args.out is None:
        raise ExperimentError(f"--experiment {args.experiment} needs --out F.mcap")
    rig = "sim" + (f":{args.plant}" if args.plant else "")
    return execute(RecordOptions(experiment=args.experiment, rig=rig, out=args.out,
                                 sample_period=args.sample_period, seed=seed,
                                 compression_level=args.compression_level, json=args.json))


def _closed_loop(args: Any, plant_cfg: PlantConfig, seed: int) -> int:
    from pneutune.control.contracts.controller import load_controller
    from pneutune.control.law.layout import pack
    from pneutune.control.sim.closed_loop import simulate_scenario
    from pneutune.control.sim.scenarios import resolve_scenarios

    controller = load_controller(args.controller)
    if args.scenario is None:
        raise ExperimentError("--controller needs --scenario S (a name, table1, all or a "
                              "comma-separated list)")
    scenarios = resolve_scenarios(args.scenario)
    # the same checks as deploy: the law's filters and PWM inverse are built for one Ts and
    # PWM frequency, and a reference outside the limits (another rig's stroke) runs on the stops
    rig_meta = plant_cfg.rig_metadata()
    check_rig_compatible(controller, rig_meta, args.controller,
                         f"plant {args.plant}" if args.plant else "the default plant, the "
                         "paper's rig")
    scenarios, scaled = fit_reference_to_limits(controller, scenarios, rig_meta, args.controller)
    if scaled is not None:
        info(f"warning: reference_scaled: {scaled}")
    args.several = len(scenarios) > 1
    cfg_vec = pack(controller)
    results: dict[str, Any] = {}
    rows: list[Any] = []
    with contextlib.ExitStack() as stack:
        law = None if args.law == "installed" else _target_law(args.law, stack)
        for sc in tqdm(scenarios, desc="scenarios", unit="scenario", disable=None, leave=False):
            res = (simulate_scenario(controller, sc, plant_cfg, seed=seed,
                                     record_truth=bool(args.out), cfg_vec=cfg_vec)
                   if law is None else _through_runtime(controller, sc, plant_cfg, seed, law))
            _scenario_outputs(args, controller, sc, seed, res, results, rows)
    if args.json:
        print_json({"scenarios": results, "controller": args.controller, "seed": seed,
                    "variant": controller.variant, "law": args.law})
    else:
        info(format_table(rows, f"{args.controller} ({controller.variant}), seed {seed}"
                                + ("" if args.law == "installed" else f", law {args.law}"),
                          scenarios[0].scale))
        for _name, m in results.items():
            if "log" in m:
                info(f"wrote {m['log']}")
        if args.plots:
            info(f"figures in {args.plots}/")
    return 0 if all(m["status"] == "ok" for m in results.values()) else 1


def _target_law(kind: str, stack: contextlib.ExitStack) -> Any:
    """``--law c`` / ``c-float``: the law's C built as a target builds it, in a folder that
    lives as long as the run (:func:`pneutune.control.law.cbuild.build`)."""
    from pneutune.control.law.cbuild import CLaw, build

    real = "float" if kind == "c-float" else "double"
    folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="pneutune-law-"))
    return CLaw(build(folder, real), real).step_into


def _through_runtime(controller: Any, sc: Any, plant_cfg: PlantConfig, seed: int,
                     law: Any) -> Any:
    """One scenario on the simulated rig through the deploy runtime with ``law`` as the step
    (the runtime gives the figures of the compiled closed loop for the same plant and seed)."""
    from pneutune.control.rig.scenario_run import run_scenario, sim_rig_for

    rig, pcfg, _ = sim_rig_for(sc, plant_cfg, seed)
    try:
        res = run_scenario(controller, sc, rig, record_truth=True, plant=pcfg, seed=seed,
                           home="off", law=law)
    finally:
        rig.close()
    return res.closed_loop_result()


def _scenario_outputs(args: Any, controller: Any, sc: Any, seed: int, res: Any,
                      results: dict[str, Any], rows: list[Any]) -> None:
    """The metrics, the log and the figures of one scenario."""
    m = res.metrics.as_dict()
    results[sc.name] = m
    rows.append((sc.name, m, sc.paper))
    if args.out:
        path = scenario_log_path(args.out, sc.name, args.several)
        run_meta = {"seed": str(seed), "scenario": sc.name, "controller": args.controller,
                    "controller_sha256": sha256_file(args.controller),
                    "variant": controller.variant, **plant_meta(args.plant)}
        if args.law != "installed":
            run_meta["law"] = args.law
        res.recording().save(path, rig=res.plant.rig_metadata(), run=run_meta)
        m["log"] = str(path)
    if args.plots:
        from pneutune.control.cli.plots import plot_closed_loop

        m["plots"] = [str(p) for p in plot_closed_loop(res, args.plots)]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``simulate``."""
    parser = make_parser("simulate", DESCRIPTION, EPILOG)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--experiment", choices=["identification", "commissioning"],
                      help="excitation protocol to run (see above)")
    mode.add_argument("--controller", metavar="C.yaml", help="controller.yaml for a closed loop")
    parser.add_argument("--scenario", metavar="S",
                        help="scenario name, table1, all, or a comma-separated list of them")
    parser.add_argument("--out", metavar="F.mcap", help="the log to write")
    parser.add_argument("--plant", metavar="P.yaml", help="plant.yaml (default: the paper's rig)")
    parser.add_argument("--seed", type=int, metavar="N",
                        help="sensor-noise seed (default: sim.seed of the plant, 1)")
    parser.add_argument("--sample-period", type=float, metavar="S",
                        help="--experiment: sensor logging period [s], dividing rig.Ts "
                             "(default 0.0005 for identification, rig.Ts for commissioning)")
    parser.add_argument("--compression-level", type=int, metavar="L",
                        help="--experiment: zstd level of the log's chunks, 1-22 (default 3; "
                             "19 makes the log about 20 %% smaller and takes about five times "
                             "as long; `make data` uses it for data/run.mcap)")
    parser.add_argument("--plots", metavar="DIR", help="write PNG figures (closed loop) to DIR")
    parser.add_argument("--law", choices=("installed", "c", "c-float"), default="installed",
                        help="--controller: the control step: installed (default: the law's C "
                             "as the install compiled it, inside the compiled closed loop), c "
                             "(the same C built as a target builds it, strict C99, run through "
                             "the deploy runtime on the simulated rig: software in the loop) "
                             "or c-float (that build in single precision); needs a C compiler")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object on stdout (prose goes to stderr)")
    args = parser.parse_args(argv)
    if args.compression_level is not None and args.compression_level not in ZSTD_LEVELS:
        raise ExperimentError(f"--compression-level must be in {ZSTD_LEVELS.start}.."
                              f"{ZSTD_LEVELS.stop - 1}, got "
                              f"{args.compression_level}")

    plant_cfg = load_sim_plant(args.plant)
    if args.seed is not None and args.seed < 0:
        raise ExperimentError(f"--seed must be >= 0, got {args.seed}")
    seed = plant_cfg.sim.seed if args.seed is None else args.seed
    plant_cfg = plant_cfg.with_updates({"sim": {"seed": seed}})
    if args.experiment:
        if args.scenario or args.plots or args.law != "installed":
            raise ExperimentError("--scenario, --plots and --law go with --controller, "
                                  "not --experiment")
        return _experiment(args, seed)
    return _closed_loop(args, plant_cfg, seed)


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)


if __name__ == "__main__":  # pragma: no cover
    entry()
