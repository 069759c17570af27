"""``tune``: robust Optuna tuning of the modified DARC in closed-loop simulation."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from tqdm import tqdm

from pneutune.control.cli.common import info, make_parser, print_json, run_cli
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import (
    PAPER_CONTROLLER,
    ProvenanceConfig,
    load_controller,
    save_controller,
)
from pneutune.control.contracts.model import load_model
from pneutune.control.contracts.yamlio import write_yaml
from pneutune.control.errors import ConfigError
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS

from .feasibility import InfeasibleModelError, check_feasibility
from .objective import DEFAULT_SCENARIOS, ObjectiveSettings, TuneError, TuneObjective
from .report import compare, write_report
from .space import controller_from_params, search_space
from .study import (
    DEFAULT_JOURNAL,
    StudySpec,
    default_study_name,
    finished,
    run_study,
    storage_scheme,
)
from .study import _redact as redact

DEFAULT_MODEL = "reports/identify/model.yaml"
DEFAULT_OUT = "reports/tune"

DESCRIPTION = """\
Tune the modified DARC (Qian et al. 2014, Secs. 3-5) on an identified model (model.yaml,
contract 3) with Optuna, in closed-loop simulation, and write DIR/controller.yaml (contract 4)
and DIR/report.md.

Objective: the four Table-1 scenarios and the disturbance scenario, each simulated on plants
drawn from the model's uncertainty (the nominal plant, two corners of the box, a Latin
hypercube); per scenario the CVaR of the cost over the draws, averaged over the scenarios. The
cost is the tracking error relative to the paper's Table 1 plus penalties for valve chattering,
chamber pressures outside [p0/2, p_s + 0.5 bar] and end-stop contact. 1.0 means "as good as the
paper's rig on every scenario". An unstable run prunes its trial. docs/tuning.md.

The study lives in a storage (default DIR/study.journal, an Optuna journal file; optuna-dashboard
opens it). Re-running the same command resumes it: --trials N is the number of finished
(complete or pruned) trials the study holds in total, so a killed run completes the remainder.
"""

EPILOG = """\
examples:
  tune --trials 200
  tune --model reports/identify/model.yaml --trials 400 --workers 2 --seed 3
  tune --trials 1000 --storage postgresql://tune@db.lan:5432/pneutune --study axis1 --workers 2
      (run the same command on several hosts: they share the study; docs/tuning.md)

With one worker the same seed gives the same trials and the same best trial. Outputs in DIR:
controller.yaml, report.md, history.png, importance.png, plant-nominal.yaml, plant-worst.yaml
(`simulate --controller DIR/controller.yaml --plant DIR/plant-nominal.yaml --scenario all`
repeats the objective's nominal runs).
"""


def _version() -> str:
    try:
        return metadata.version("pneutune")
    except metadata.PackageNotFoundError:  # pragma: no cover - not installed
        return "unknown"


def _cpus() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


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


def failure_summary(study: Any) -> str:
    """Why the trials of a study failed, most frequent first (``user_attrs["failure"]``)."""
    reasons: dict[str, int] = {}
    for t in study.get_trials(deepcopy=False):
        why = t.user_attrs.get("failure")
        if why:
            reasons[why] = reasons.get(why, 0) + 1
    if not reasons:
        return "no failure recorded (every trial was pruned by the median rule)"
    top = sorted(reasons.items(), key=lambda kv: -kv[1])[:3]
    return "; ".join(f"{n}x {why}" for why, n in top)


def provenance(model_sha256: str, study: str, trial: int, value: float, seed: int,
               notes: Sequence[str] = ()) -> dict[str, Any]:
    """The provenance block (``seed`` and ``notes`` only if this pneutune's contract 4 has
    those keys)."""
    prov: dict[str, Any] = {
        "model_sha256": model_sha256, "study": study, "trial": int(trial),
        "objective": float(value),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "version": _version(),
    }
    if "seed" in ProvenanceConfig.model_fields:
        prov["seed"] = int(seed)
    if notes and "notes" in ProvenanceConfig.model_fields:
        prov["notes"] = list(notes)
    return prov


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
                        help="processes per worker that run a trial's plant draws in parallel "
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
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object on stdout (progress and prose on stderr)")
    args = parser.parse_args(argv)

    if args.trials < 1:
        raise TuneError(f"--trials must be >= 1, got {args.trials}")
    if args.workers < 1:
        raise TuneError(f"--workers must be >= 1, got {args.workers}")
    if args.seed < 0:
        raise TuneError(f"--seed must be >= 0, got {args.seed}")
    if args.jobs is not None and args.jobs < 1:
        raise TuneError(f"--jobs must be >= 1, got {args.jobs}")
    model_path = Path(args.model)
    if not model_path.is_file():
        raise ConfigError(str(model_path), "", "no such model file; run identify first "
                          "(`identify LOG.mcap` writes reports/identify/model.yaml) or pass "
                          "--model M.yaml")
    model = load_model(model_path)
    model_sha = sha256_file(model_path)
    try:  # a model whose θ box or valves cannot make a contract-4 controller: say so up front
        controller_from_params(model, search_space(model).paper_params())
    except ConfigError as exc:
        raise ConfigError(str(model_path), exc.key, "cannot make a controller.yaml from this "
                          f"model: {exc.message}") from None
    settings = ObjectiveSettings(scenarios=_scenarios(args.scenarios), n_draws=args.draws,
                                 duration=args.duration)
    out = Path(args.out)
    storage = args.storage if args.storage else str(out / DEFAULT_JOURNAL)
    storage_scheme(storage)  # an unknown scheme is bad input before any simulation
    try:
        feas = check_feasibility(model, args.seed, settings,
                                 progress=lambda line: info(f"  {line}"))
    except InfeasibleModelError as exc:
        raise ConfigError(str(model_path), "", str(exc)) from None
    settings = dataclasses.replace(settings, box=feas.box)
    study_name = args.study or default_study_name(model_sha, args.seed)
    jobs = args.jobs if args.jobs is not None else (
        min(_cpus(), settings.n_draws) if args.workers == 1 else 1)
    spec = StudySpec(storage, study_name, args.seed, args.trials, args.workers, model_sha,
                     settings, jobs,
                     extra_first=None if feas.paper_failure is None else feas.reference_params)

    bar = tqdm(total=args.trials, desc="tune", unit="trial", file=sys.stderr, disable=None,
               leave=False)

    def progress(done: int, total: int) -> None:
        bar.total = max(total, done)
        bar.n = done
        bar.refresh()

    try:
        summary = run_study(spec, model, progress=progress)
    finally:
        bar.close()
    study = summary.study
    counts = summary.counts_after
    complete = [t for t in study.get_trials(deepcopy=False) if t.state.name == "COMPLETE"]
    if not complete:
        raise ConfigError(str(model_path), "", f"study {study_name!r}: no trial completed "
                          f"({counts['PRUNED']} pruned, {counts['FAIL']} failed): "
                          f"{failure_summary(study)}; check the model's ranges and fit")
    best = study.best_trial

    prov = provenance(model_sha, study_name, best.number, float(best.value), args.seed,
                      feas.notes())
    tuned = controller_from_params(model, best.params, prov)
    paper_path = PAPER_CONTROLLER
    paper = load_controller(paper_path)

    objective = TuneObjective(model, args.seed, settings)
    comp = compare(objective, tuned, paper)
    out.mkdir(parents=True, exist_ok=True)
    controller_path = out / "controller.yaml"
    header = (f"Tuned by `tune` (pneutune {prov['version']}): study {study_name}, trial "
              f"{best.number}, objective {best.value:.6g}, seed {args.seed}.\n"
              f"Model {model_path} (sha256 {model_sha}).\n"
              f"Nominal runs: simulate --controller {controller_path} --plant "
              f"{out / 'plant-nominal.yaml'} --scenario all\n"
              "Contract 4 (pneutune.controller/1); docs/tuning.md.")
    save_controller(tuned, controller_path, header=header)
    nominal_path = out / "plant-nominal.yaml"
    worst_path = out / "plant-worst.yaml"
    write_yaml(nominal_path, objective.draws[0].plant.to_dict(),
               header=f"The nominal plant of {model_path} (draw 0), sensor-noise seed "
                      f"{objective.draws[0].noise_seed}. Contract 2.")
    wd = objective.draws[comp.worst_draw]
    write_yaml(worst_path, wd.plant.to_dict(),
               header=f"Draw {wd.index} ({wd.label}) of {model_path}, seed {args.seed}: where "
                      "the tuned controller does worst. Contract 2.")
    report_info = {
        "model": str(model_path), "model_sha256": model_sha, "storage": redact(storage),
        "n_trials": args.trials, "counts": counts, "controller": str(controller_path),
        "paper_path": os.path.relpath(paper_path) if paper_path.is_absolute() else str(
            paper_path),
        "plant_nominal": str(nominal_path), "plant_worst": str(worst_path),
        "feasibility": feas.notes(),
    }
    report_path = write_report(out, objective, study, best, tuned, paper, comp, report_info)
    # the file written loads back equal (contract 4 round trip)
    if load_controller(controller_path) != tuned:  # pragma: no cover - a bug in save/load
        raise RuntimeError(f"{controller_path} does not load back equal to the tuned config")

    result = {
        "controller": str(controller_path), "report": str(report_path),
        "plant_nominal": str(nominal_path), "plant_worst": str(worst_path),
        "model": str(model_path), "model_sha256": model_sha, "seed": args.seed,
        "study": study_name, "storage": redact(storage), "workers": args.workers,
        "jobs": jobs,
        "trials": {"wanted": args.trials, "finished": finished(counts),
                   "complete": counts["COMPLETE"], "pruned": counts["PRUNED"],
                   "failed": counts["FAIL"], "running": counts["RUNNING"],
                   "this_run": finished(counts) - finished(summary.counts_before),
                   "leftovers_failed": summary.leftovers_failed},
        "wall_s": summary.wall_s,
        "best": {"trial": best.number, "objective": best.value, "params": best.params},
        "narrowed": [list(b) for b in feas.box],
        "feasibility": feas.notes(),
        **comp.summary(),
    }
    if args.json:
        print_json(result)
    else:
        info(f"study {study_name}: {counts['COMPLETE']} complete, {counts['PRUNED']} pruned, "
             f"{counts['FAIL']} failed ({result['trials']['this_run']} this run, "
             f"{summary.wall_s:.1f} s)")
        info(f"best trial #{best.number}: objective {best.value:.4f} (paper's gains: "
             f"{comp.paper.value if comp.paper.value is None else round(comp.paper.value, 4)})")
        info(f"wrote {controller_path}, {report_path}")
    return 0


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)


if __name__ == "__main__":  # pragma: no cover
    entry()


__all__ = ["entry", "main", "provenance"]
