"""Best objective against the number of trials for each sampler (docs/tuning.md, "Sampler").

Runs the same study (same model, objective settings, plant draws, noise and pruner) once per
sampler and seed, each in a fresh journal in a temporary folder, through the library's own
:func:`pneutune.tune.study.run_study` (the code path of ``tune``; the sampler is the only
difference), after the same feasibility check ``tune`` does. Prints, per sampler, the best
objective after 25/50/100/... trials (mean and min..max over the seeds), the complete/pruned
counts and the wall time, and writes a PNG of the best so far against the trial number (one line
per sampler: the mean over seeds, with a min-max band).

Samplers (:mod:`pneutune.tune.samplers`): ``tpe`` (the default), ``cmaes`` (TPE for the first
25 complete trials, then CMA-ES warm-started from them; needs ``cmaes``) and ``gp`` (Optuna's
GPSampler; needs torch, e.g. ``PYTHONPATH=<dir with torch>``). A sampler whose package is
missing is skipped with a line saying so.

Default settings are reduced so that the whole benchmark takes about 10 minutes on a loaded
2-core machine: scenarios ``sine-0.5hz,square-0.5hz`` cut to 8 s (four periods; the metric
window is the last three), 4 plant draws (nominal, both corners, one hypercube point), 100
trials, seeds 1 to 5, the truth model ``model_from_plant(PlantConfig())``. ``--full`` selects
``tune``'s defaults (five full-length scenarios, 8 draws, 200 trials).

Trial 0 of every study is the paper's gains (as in ``tune``), and the first 10 trials of ``tpe``
and ``cmaes`` with the same seed are the same random start-up points, so the curves part only
where the samplers do.

    .venv/bin/python benchmarks/samplers.py [--samplers tpe,cmaes,gp] [--seeds 1,2,3]
        [--trials 100] [--full] [--model M.yaml] [--png reports/benchmarks/samplers.png]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from optuna.trial import TrialState

from pneutune.control.contracts.atomic import save_figure
from pneutune.control.contracts.model import ModelConfig, load_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.api import available_cpus
from pneutune.tune.feasibility import check_feasibility
from pneutune.tune.objective import ObjectiveSettings
from pneutune.tune.samplers import LIBRARY_SAMPLERS, SamplerError, check_sampler, describe
from pneutune.tune.study import StudySpec, run_study

QUICK = ObjectiveSettings(scenarios=("sine-0.5hz", "square-0.5hz"), n_draws=4, duration=8.0)


def best_so_far(study_trials: list, n_trials: int) -> np.ndarray:
    """Best COMPLETE objective among trials 0..i, for i < n_trials (NaN before the first)."""
    values = np.full(n_trials, np.inf)
    for t in study_trials:
        if t.number < n_trials and t.state == TrialState.COMPLETE and t.value is not None:
            values[t.number] = t.value
    best = np.minimum.accumulate(values)
    best[~np.isfinite(best)] = np.nan
    return best


def run_one(model: ModelConfig, sampler: str, seed: int, settings: ObjectiveSettings,
            trials: int, jobs: int) -> tuple[np.ndarray, float, dict[str, int]]:
    """One study; (best so far per trial, wall time [s] of the study, trial counts)."""
    feas = check_feasibility(model, seed, settings)
    objective = dataclasses.replace(settings, box=feas.box)
    with tempfile.TemporaryDirectory() as tmp:
        spec = StudySpec(str(Path(tmp) / "study.journal"), f"bench-{sampler}-seed{seed}", seed,
                         trials, 1, "benchmark", objective, jobs,
                         extra_first=() if feas.paper_failure is None
                         else (feas.reference_params,), sampler=sampler)
        run = run_study(spec, model)
        trials_ = run.study.get_trials(deepcopy=False)
        return best_so_far(trials_, trials), run.wall_s, run.counts_after


def checkpoints(trials: int) -> list[int]:
    """25, 50, 100, 200, ... up to ``trials`` (and ``trials`` itself)."""
    marks = [n for n in (10, 25, 50, 75, 100, 150, 200, 300, 400) if n < trials]
    return [*marks, trials]


def plot(curves: dict[str, np.ndarray], path: Path, title: str) -> None:
    """Best so far against the trial number: mean over seeds, min-max band."""
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    for i, (name, c) in enumerate(curves.items()):
        x = np.arange(1, c.shape[1] + 1)
        ax.fill_between(x, np.nanmin(c, axis=0), np.nanmax(c, axis=0), color=f"C{i}",
                        alpha=0.2, linewidth=0)
        ax.plot(x, np.nanmean(c, axis=0), color=f"C{i}", label=f"{name} (mean, min-max band)")
    ax.set_xlabel("trials")
    ax.set_ylabel("best objective so far (1 = the paper's Table 1)")
    ax.set_yscale("log")
    ax.set_title(title, fontsize=8)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samplers", default=",".join(LIBRARY_SAMPLERS))
    ap.add_argument("--seeds", default="1,2,3,4,5")
    ap.add_argument("--trials", type=int, help="trials per study (default 100, --full 200)")
    ap.add_argument("--full", action="store_true",
                    help="tune's default objective (5 full-length scenarios, 8 draws)")
    ap.add_argument("--scenarios", help="override the scenarios (comma-separated)")
    ap.add_argument("--draws", type=int, help="override the plant draws")
    ap.add_argument("--duration", type=float, help="override the scenario duration [s]")
    ap.add_argument("--model", help="model.yaml (default: the truth model of the default plant)")
    ap.add_argument("--jobs", type=int, default=min(available_cpus(), 4))
    ap.add_argument("--png", default="reports/benchmarks/samplers.png")
    args = ap.parse_args()

    settings = ObjectiveSettings() if args.full else QUICK
    if args.scenarios:
        settings = dataclasses.replace(settings, scenarios=tuple(args.scenarios.split(",")))
    if args.draws:
        settings = dataclasses.replace(settings, n_draws=args.draws)
    if args.duration:
        settings = dataclasses.replace(settings, duration=args.duration)
    trials = args.trials or (200 if args.full else 100)
    seeds = [int(s) for s in args.seeds.split(",")]
    model = load_model(args.model) if args.model else model_from_plant(PlantConfig())
    samplers = []
    for name in args.samplers.split(","):
        try:
            check_sampler(name)
            samplers.append(name)
        except SamplerError as exc:
            print(f"skip {name}: {exc}")
    dur = "full length" if settings.duration is None else f"{settings.duration:g} s"
    setup = (f"{','.join(settings.scenarios)} ({dur}), {settings.n_draws} draws, {trials} "
             f"trials, seeds {args.seeds}, model {args.model or 'truth (PlantConfig())'}, "
             f"jobs {args.jobs}")
    print(setup)
    for name in samplers:
        print(f"  {name}: {describe(name)}")
    marks = checkpoints(trials)
    curves: dict[str, np.ndarray] = {}
    rows = []
    for name in samplers:
        runs, walls, counts = [], [], []
        for seed in seeds:
            t0 = time.perf_counter()
            best, _, cnt = run_one(model, name, seed, settings, trials, args.jobs)
            walls.append(time.perf_counter() - t0)
            runs.append(best)
            counts.append(cnt)
            print(f"  {name} seed {seed}: best {best[-1]:.4f}, {cnt['COMPLETE']} complete / "
                  f"{cnt['PRUNED']} pruned, {walls[-1]:.1f} s", flush=True)
        curves[name] = np.array(runs)
        rows.append((name, curves[name], sum(walls),
                     np.mean([c["COMPLETE"] for c in counts]),
                     np.mean([c["PRUNED"] for c in counts])))
    print()
    head = "| sampler | " + " | ".join(f"best after {n}" for n in marks) + \
        " | complete / pruned (mean) | wall, all seeds |"
    print(head)
    print("|---" * (len(marks) + 3) + "|")
    for name, c, wall, nc, npr in rows:
        cells = [f"{np.nanmean(c[:, n - 1]):.3f} ({np.nanmin(c[:, n - 1]):.3f}-"
                 f"{np.nanmax(c[:, n - 1]):.3f})" for n in marks]
        print(f"| {name} | " + " | ".join(cells) + f" | {nc:.0f} / {npr:.0f} | {wall:.0f} s |")
    if curves:
        path = Path(args.png)
        path.parent.mkdir(parents=True, exist_ok=True)
        plot(curves, path, setup)
        print(f"\nwrote {path} ({path.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
