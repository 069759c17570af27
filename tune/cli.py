"""``tune``: robust Optuna tuning of the modified DARC in closed-loop simulation.

A thin shell over :func:`pneutune.tune.api.tune`: the flags become :class:`TuneSettings`, the
result is printed (prose on stderr, one JSON object on stdout with ``--json``).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pneutune.control.cli.common import caused_by_interrupt, info, make_parser, print_json, run_cli
from pneutune.control.constants import WEAK_B_SPAN
from pneutune.control.contracts.controller import DEAD_ZONE_MODES
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS

from .api import DEFAULT_OUT, TuneSettings, tune
from .objective import DEFAULT_SCENARIOS, ObjectiveSettings, TuneError
from .pruners import PRUNERS
from .samplers import CMAES_WARM_START, DEFAULT_SAMPLER, SAMPLERS
from .space import VARIANTS
from .storage import DEFAULT_JOURNAL, redact_url

DEFAULT_MODEL = "reports/identify/model.yaml"

DESCRIPTION = f"""\
Tune the modified DARC (Qian et al. 2014, Secs. 3-5) on an identified model (model.yaml,
contract 3) with Optuna, in closed-loop simulation, and write DIR/controller.yaml (contract 4)
and DIR/report.md.

Searched (14 parameters, log scales): the gains k1-k3, h2, h3 and r3, the six adaptation rates
Γ and the two Kalman filters' Q. On a model where some valve's b is weakly identified (a b
range wider than {WEAK_B_SPAN:g}, as from a short closed-loop log) also the viscous estimate's
start θ̂3(0), from the model's nominal b_v up to four times it. The rest of θ's box and start
are the model's.

Objective: the four Table-1 scenarios and the disturbance scenario, each simulated on plants
drawn from the model's uncertainty (the nominal plant, two corners of the box, a Latin
hypercube); per scenario the CVaR of the cost over the draws, averaged over the scenarios. The
cost is the tracking error relative to the paper's Table 1 plus penalties for valve chattering,
chamber pressures outside [p0/2, p_s + 0.5 bar] and end-stop contact. 1.0 means "as good as the
paper's rig on every scenario". An unstable run prunes its trial, and so does one that is worse
than earlier trials on the runs done so far (--pruner: staged, median, wilcoxon or none). Before
writing, the best trials are run on held-out draws (new noise, new hypercube plants) and the
first that completes every run is kept (the held-out guard; report.md says when it passed over
the study's best).
docs/tuning.md.

When the model came from a closed-loop log that `deploy --log` wrote, the controller that ran is
replayed on the model's nominal plant beside the log's measured E_p, and the tuned one with it
(report.md, "The log's own closed loop"). A warning says when the rig tracked twice as well or
badly as the model, or when the tuned controller does worse than the logged one there: deploy
both on the rig and keep the better. The logged controller is also a trial of the study, right
after the paper's gains, so a re-tune after a re-identification starts from what ran on the rig.

The study lives in a storage (default DIR/study.journal, an Optuna journal file; optuna-dashboard
opens it). Re-running the same command resumes it: --trials N is the number of finished
(complete or pruned) trials the study holds in total, so a killed run completes the remainder.
"""

EPILOG = """\
examples:
  tune --trials 200
  tune --model reports/identify/model.yaml --trials 400 --workers 2 --seed 3
  tune --trials 200 --sampler cmaes        (CMA-ES after a TPE warm start; pip install cmaes)
  tune --trials 200 --variant pid          (the PID baseline, same objective: a fair comparison)
  tune --trials 200 --restarts 3           (three studies, the best on unseen plants: 3x the time)
  tune --trials 1000 --storage postgresql://tune@db.lan:5432/pneutune --study axis1 --workers 2
      (run the same command on several hosts: they share the study; docs/tuning.md)

With one worker the same seed gives the same trials and the same best trial. Outputs in DIR:
controller.yaml, report.md, history.png, importance.png, plant-nominal.yaml, plant-worst.yaml
(`simulate --controller DIR/controller.yaml --plant DIR/plant-nominal.yaml --scenario all`
repeats the objective's nominal runs).
"""


def _scenarios(value: str) -> tuple[str, ...]:
    names: list[str] = []
    for part in value.split(","):
        part = part.strip()
        if part in GROUPS:
            names += GROUPS[part]
        elif part in SCENARIOS:
            names.append(part)
        else:
            known = ", ".join([*SCENARIOS, *GROUPS])
            raise TuneError(f"--scenarios: unknown scenario {part!r}; expected a comma-separated "
                            f"list of: {known}")
    return tuple(dict.fromkeys(names))


def _resume_hint(args: Any, bar: Any) -> None:
    """After a Ctrl-C: where the finished trials are, and how to go on."""
    bar.close()
    where = redact_url(args.storage) if args.storage else str(Path(args.out) / DEFAULT_JOURNAL)
    info(f"tune: every finished trial is kept in {where}; run the same command again to resume "
         "the study")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``tune``."""
    parser = make_parser("tune", DESCRIPTION, EPILOG)
    parser.add_argument("--model", metavar="M.yaml", default=DEFAULT_MODEL,
                        help=f"identified model (default {DEFAULT_MODEL})")
    parser.add_argument("--trials", type=int, required=True, metavar="N",
                        help="finished (complete + pruned) trials the study holds in total")
    parser.add_argument("--storage", metavar="URL",
                        help=f"journal file path, sqlite:///F.db or postgresql://... "
                             f"(default DIR/{DEFAULT_JOURNAL})")
    parser.add_argument("--study", metavar="NAME",
                        help="study name (default tune-<model sha256[:12]>-seed<S>)")
    parser.add_argument("--workers", type=int, default=1, metavar="K",
                        help="worker processes on this host (default 1: reproducible)")
    parser.add_argument("--jobs", type=int, metavar="J",
                        help="threads per worker that run a trial's plant draws in parallel "
                             "(default: the available CPUs with --workers 1, else 1; the "
                             "results do not depend on it)")
    parser.add_argument("--seed", type=int, default=1, metavar="S",
                        help="seed of the plant draws, sensor noise and samplers (default 1)")
    parser.add_argument("--out", metavar="DIR", default=DEFAULT_OUT,
                        help=f"output folder (default {DEFAULT_OUT})")
    parser.add_argument("--draws", type=int, default=ObjectiveSettings.n_draws, metavar="D",
                        help=f"plants per scenario (default {ObjectiveSettings.n_draws})")
    parser.add_argument("--scenarios", metavar="S,...", default=",".join(DEFAULT_SCENARIOS),
                        help="scenarios, in evaluation order (default: table1 + "
                             "disturbance-0.5hz)")
    parser.add_argument("--duration", type=float, metavar="SECONDS",
                        help="override every scenario's duration (quick experiments only; the "
                             "figures then differ from Table 1's protocol)")
    parser.add_argument("--variant", choices=VARIANTS, default="modified_darc",
                        help="what to tune: the paper's modified DARC (default) or the pid "
                             "baseline on the same valve logic, with the same objective, so that "
                             "the comparison is fair")
    parser.add_argument("--sampler", choices=SAMPLERS, default=DEFAULT_SAMPLER,
                        help="tpe (default) or cmaes: TPE for the first "
                             f"{CMAES_WARM_START} complete trials, then CMA-ES started from "
                             "their best (needs: pip install 'pneutune[cmaes]'); a study "
                             "keeps its sampler (default study name gets -cmaes)")
    parser.add_argument("--dead-zone", choices=DEAD_ZONE_MODES, default="up",
                        help="how the tuned controller commands a small opening inside the "
                             "valves' dead zone: up (default: at least the smallest pulse that "
                             "opens the valve, every PWM period) or dither (whole smallest "
                             "pulses in some periods, their mean the wanted opening). Dither "
                             "measured worse on four of five fleet plants (better on one latched "
                             "plant; docs/notes/2026-11-26-tune-levers.md); try it on a rig "
                             "whose smallest pulse is large (default study name gets -dither)")
    parser.add_argument("--pruner", choices=PRUNERS, default=None,
                        help="how trials are stopped early: staged (default for a new "
                             "study: the running mean after the first scenario against the "
                             "median of the trials that went past it, after each later "
                             "scenario against their best quarter), median (the running mean "
                             "after each scenario against the median of the complete trials; "
                             "every study made before staged), wilcoxon (each run's cost is "
                             "reported, runs "
                             "in a per-trial order, and a trial stops once a Wilcoxon "
                             "signed-rank test finds it worse than the best trial on the same "
                             "runs: about twice as fast, but a worse best trial on some seeds; "
                             "docs/tuning.md) or none. A completed trial's value is the same "
                             "with any. A study keeps its pruner: without the flag a resumed "
                             "study uses its own")
    parser.add_argument("--restarts", type=int, default=1, metavar="K",
                        help="run K independent studies (seeds S..S+K-1, each of --trials "
                             "trials, K times the time; with --study NAME they are "
                             "NAME-seed<S>, ...) and keep the controller that scores best on "
                             "selection draws with new noise and new plants, the same for "
                             "every study. On the fleet's models "
                             "three restarts brought the true plant's figure from 0.94 (one "
                             "study, mean over seeds) to 0.83-0.84 (docs/tuning.md, "
                             "\"Restarts\"). Default 1")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object on stdout (progress and prose on stderr)")
    args = parser.parse_args(argv)
    settings = TuneSettings(
        trials=args.trials, out=args.out, storage=args.storage, study=args.study,
        workers=args.workers, jobs=args.jobs, seed=args.seed, sampler=args.sampler,
        pruner=args.pruner, restarts=args.restarts,
        objective=ObjectiveSettings(scenarios=_scenarios(args.scenarios), n_draws=args.draws,
                                    duration=args.duration, variant=args.variant,
                                    dead_zone=args.dead_zone))
    bar = tqdm(total=args.trials * args.restarts, desc="tune", unit="trial", file=sys.stderr,
               disable=None, leave=False)

    def progress(done: int, total: int) -> None:
        bar.total = max(total, done)
        bar.n = done
        bar.refresh()

    try:
        result = tune(args.model, settings, progress=progress,
                      notes=lambda line: info(f"  {line}"))
    except Exception as exc:
        if not caused_by_interrupt(exc):
            raise
        _resume_hint(args, bar)
        raise
    except KeyboardInterrupt:
        _resume_hint(args, bar)
        raise
    finally:
        bar.close()
    summary = result.summary()
    if args.json:
        print_json(summary)
    else:
        tr = summary["trials"]
        paper = result.comparison.paper.value
        info(f"study {summary['study']}: {tr['complete']} complete, {tr['pruned']} pruned, "
             f"{tr['failed']} failed ({tr['this_run']} this run, in {summary['wall_s']:.1f} s of "
             "optimisation)")
        if summary["restarts"]:
            info(f"{len(summary['restarts'])} restarts in {summary['wall_s_restarts']:.1f} s; "
                 f"kept seed {summary['seed']}'s study")
        info(f"best trial #{result.best.number}: objective {result.best.value:.4f} (paper's "
             f"gains: {'n/a, a run of them failed' if paper is None else round(paper, 4)})")
        info(f"wrote {summary['controller']}, {summary['report']}")
    return 0


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)


if __name__ == "__main__":  # pragma: no cover
    entry()


__all__ = ["entry", "main"]
