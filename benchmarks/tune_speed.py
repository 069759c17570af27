"""Wall time of ``tune --trials 200`` with the default settings, trials per second, and the
simulated seconds per wall second of the objective's closed loops.

Runs the ``tune`` console command (a fresh process: imports and loading the cached numba code
included, after a 2-trial warm-up run of each code that lets numba compile outside the
timing) on a fresh study in a temporary folder, on ``--model`` (default: the command's own
default ``reports/identify/model.yaml`` if it exists, else the truth model of the default plant,
``model_from_plant(PlantConfig())``; ``--model truth`` forces the latter), and prints:

* the wall time of the command (target: at most 45 s on the 2-core machine);
* trials per second (finished trials / wall time of the command), and of the optimisation alone;
* complete/pruned/failed counts, the best objective and the paper's on the same plants.

Default settings: five scenarios (Table 1 + disturbance) at their full durations, 8 plant draws
run on as many numba threads as there are CPUs (``--jobs``), CVaR 0.25, the median pruner after
each scenario or the Wilcoxon pruner after each chunk of runs (``--pruners``), one worker
(reproducible). ``--workers 2`` measures the two-worker variant.

Closed-loop throughput (``--throughput``, before the command runs): one full evaluation of the
paper's gains (every scenario x every draw of the objective, no abort) timed ``--repeat`` times
in this process, three ways, each printed as simulated seconds per wall second (min..max):

* ``serial``: one :func:`~pneutune.control.sim.closed_loop.run_prepared` call per run (the
  per-run Python round trip of the earlier objective);
* ``batch x1``: :meth:`TuneObjective.run_scenario` (one compiled call per scenario,
  :func:`~pneutune.control.sim.closed_loop.run_batch`) on one thread;
* ``batch xN``: the same on N = CPUs threads (what ``tune`` does).

The three give bit-identical metrics (checked here); only the wall time differs. ``--pwm`` picks
the truth model's PWM update mode (``immediate``/``latched``) when ``--model truth``.

Pruners (``--pruners``, default ``median,staged``): the command is run once per pruner
(``tune --pruner``), seed (``--seeds``) and round (``--rounds``), on the same model, hence the
same plant draws and noise for a seed; within a round the pruners alternate their order (so
that a change of the machine's load hits both alike). Printed per run, then per pruner the wall
times (min..max, median, runs) and per seed the best objective of each pruner: the first pruner
is the baseline (``median``: the pruning of every study before ``staged``), ``staged`` the
default (the median after the first scenario, the best quarter after each later one),
``wilcoxon`` the per-run signed-rank test against the best trial (docs/tuning.md, "Pruning").
A last line per pruner gives its best objectives against the baseline's on the same models and
seeds (geometric mean ratio, how many lower and higher, the one-sided signed-rank p that they
are worse) and its median wall time over the baseline's.

Several models (``--model A.yaml,B.yaml``): each is measured in turn, and a last table gives
per model the wall times (min..max) and the best objective of every pruner and seed.

Against an older revision (``--baseline REV``): the same commands are also run by the code of
``REV`` (a temporary ``git worktree``, put first on ``PYTHONPATH``, with the installed compiled
control law: ``REV``'s ``control/law/c`` must be the current one), alternating with the current
code in every round. The table then gives both wall times and both best objectives per
seed: a speed-up that keeps the objective's meaning finds the same best trial, or one no worse,
on the same draws and seeds.

    .venv/bin/python benchmarks/tune_speed.py [--trials 200] [--workers 1]
        [--model M.yaml[,M2.yaml...]] [--pwm latched] [--throughput-only] [--repeat 5]
        [--no-throughput] [--pruners median,staged] [--seeds 1,2,3] [--rounds 1]
        [--baseline REV]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numba
import numpy as np
from scipy.stats import wilcoxon

from pneutune.control.contracts.model import ModelConfig, load_model, save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.clib import library_path
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.objective import ObjectiveSettings, TuneObjective
from pneutune.tune.space import controller_from_params

#: The repository this benchmark belongs to (``--baseline`` makes its worktree from it).
REPO = Path(__file__).resolve().parents[1]


def throughput(model: ModelConfig, repeat: int) -> None:
    """Print the closed-loop throughput of one full evaluation, three ways (module docstring)."""
    cpus = os.cpu_count() or 1
    objective = TuneObjective(model, seed=1, settings=ObjectiveSettings(), jobs=cpus)
    controller = controller_from_params(model, objective.space.paper_params())
    sim_s = sum(s.duration for s in objective.scenarios) * len(objective.draws)

    def serial() -> list[tuple[float, float]]:
        return [(r.metrics.E_p_mm, r.metrics.E_rms_mm) for s in objective.scenarios
                for r in (objective.simulate(controller, s, d, abort=False)
                          for d in objective.draws)]

    def batch(threads: int) -> list[tuple[float, float]]:
        objective.jobs = threads
        return [(r.metrics.E_p_mm, r.metrics.E_rms_mm) for s in objective.scenarios
                for r in objective.run_scenario(controller, s, abort=False)]

    ways = {"serial": serial, "batch x1": lambda: batch(1), f"batch x{cpus}": lambda: batch(cpus)}
    reference = serial()  # compiles (or loads the cache) outside the timing
    batch(1)
    print(f"closed-loop throughput: {len(objective.scenarios)} scenarios x "
          f"{len(objective.draws)} draws = {sim_s:.0f} simulated s per evaluation, paper's gains, "
          f"{repeat} repeats (interleaved), numba threading layer "
          f"{numba.threading_layer()}")
    walls: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(repeat):  # interleaved, so that a load change hits every way alike
        for name, fn in ways.items():
            t0 = time.perf_counter()
            got = fn()
            walls[name].append(time.perf_counter() - t0)
            if not np.array_equal(np.array(got), np.array(reference)):
                raise SystemExit(f"{name}: metrics differ from the serial runs")
    for name, w in walls.items():
        print(f"  {name:<10} {sim_s / max(w):7.0f} .. {sim_s / min(w):7.0f} sim-s/wall-s   "
              f"({min(w):.2f} .. {max(w):.2f} s per evaluation)")


def run_tune(model: Path, out: Path, trials: int, workers: int, seed: int, pruner: str,
             env: dict[str, str] | None = None) -> tuple[float, dict[str, Any]]:
    """Run the ``tune`` command on a fresh study in ``out``.

    Parameters
    ----------
    model : Path
        model.yaml.
    out : Path
        Output folder (must not hold a study).
    trials, workers, seed : int
        ``--trials``, ``--workers``, ``--seed``.
    pruner : str
        ``--pruner``.
    env : dict, optional
        The command's environment (the baseline's ``PYTHONPATH``); default this process's.

    Returns
    -------
    float
        Wall time of the command [s].
    dict
        What ``tune --json`` printed.
    """
    exe = shutil.which("tune", path=os.path.dirname(sys.executable)) or "tune"
    cmd = [exe, "--model", str(model), "--trials", str(trials), "--workers", str(workers),
           "--seed", str(seed), "--pruner", pruner, "--out", str(out), "--json"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise SystemExit(proc.returncode)
    return wall, json.loads(proc.stdout)


def _value(value: float | None) -> str:
    """An objective value, or why there is none (a run of it failed on some draw)."""
    return "failed" if value is None else f"{value:.4f}"


def baseline_env(rev: str, tmp: Path) -> dict[str, str]:
    """An environment in which ``tune`` runs the code of revision ``rev`` (module docstring).

    Parameters
    ----------
    rev : str
        A git revision of this repository.
    tmp : Path
        Scratch folder: the worktree goes to ``tmp/baseline`` (remove it with
        :func:`remove_baseline`).

    Returns
    -------
    dict
        This process's environment with the worktree's package first on ``PYTHONPATH``.
    """
    tree = tmp / "baseline"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(tree), rev],
                   check=True)
    shim = tmp / "baseline-path" / "pneutune"  # pneutune is a namespace package
    shim.mkdir(parents=True)
    for part in ("control", "identify", "tune"):
        (shim / part).symlink_to(tree / part)
    installed = library_path()
    target = tree / "control" / "law" / installed.name
    if subprocess.run(["git", "-C", str(REPO), "diff", "--quiet", rev, "--",
                       "control/law/c"]).returncode != 0:
        raise SystemExit(f"error: --baseline {rev}: its control/law/c differs from the "
                         "installed law's; compare revisions with the same C law")
    shutil.copy2(installed, target)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(shim.parent),
                                                    env.get("PYTHONPATH")) if p)
    return env


def remove_baseline(tmp: Path) -> None:
    """Remove the worktree :func:`baseline_env` made, if any."""
    tree = tmp / "baseline"
    if tree.exists():
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)],
                       check=False)


def compare_best(best: dict[tuple[str, str, str, int], float],
                 walls: dict[tuple[str, str, str], list[float]], models: list[str],
                 codes: list[str], pruners: list[str], seeds: list[int]) -> None:
    """Print each (code, pruner) against the first one (the baseline) on the same models and
    seeds: the best objective's ratio (geometric mean, min .. max), how many studies it is lower
    and higher on, the one-sided Wilcoxon signed-rank p that it is higher (worse), and the
    median wall time of its runs over the baseline's."""
    arms = [(c, p) for c in codes for p in pruners]
    if len(arms) < 2:
        return
    base = arms[0]
    print(f"best objective and wall time against {base[1]} ({base[0]}), same models and seeds "
          "(ratio < 1: a lower, better objective; p: one-sided signed-rank test that it is "
          "worse)")
    for code, pruner in arms[1:]:
        pairs = [(best[(m, code, pruner, s)], best[(m, *base, s)]) for m in models for s in seeds]
        ratio = np.array([a / b for a, b in pairs])
        lower = int(np.sum(ratio < 1.0))
        higher = int(np.sum(ratio > 1.0))
        diffs = np.log(ratio)
        p = (float(wilcoxon(diffs, alternative="greater").pvalue)
             if np.any(diffs != 0.0) else 1.0)
        w_new = np.median([w for m in models for w in walls[(m, code, pruner)]])
        w_base = np.median([w for m in models for w in walls[(m, *base)]])
        print(f"  {pruner:<9} {code:<8} best x{float(np.exp(diffs.mean())):.3f} "
              f"({ratio.min():.3f} .. {ratio.max():.3f}) over {len(pairs)} studies: lower on "
              f"{lower}, higher on {higher}, p(worse) = {p:.3f}; median wall x"
              f"{w_new / w_base:.3f} ({w_new:.1f} s against {w_base:.1f} s)")


def main() -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--model", help="model.yaml, several separated by commas, or 'truth' "
                    "(default: reports/identify/model.yaml if it exists, else the truth model "
                    "of the default plant)")
    ap.add_argument("--pwm", choices=("immediate", "latched"), default="immediate",
                    help="PWM update mode of the truth model (default immediate)")
    ap.add_argument("--repeat", type=int, default=5, help="throughput repeats (default 5)")
    ap.add_argument("--throughput-only", action="store_true",
                    help="print the closed-loop throughput only, do not run tune")
    ap.add_argument("--no-throughput", action="store_true",
                    help="skip the closed-loop throughput, run tune only")
    ap.add_argument("--pruners", default="median,staged",
                    help="comma-separated tune --pruner values to compare (default "
                         "median,staged; the first is the baseline)")
    ap.add_argument("--seeds", default="1", help="comma-separated seeds (default 1)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="runs per pruner and seed, alternating the pruners (default 1)")
    ap.add_argument("--baseline", metavar="REV",
                    help="also run the commands with the code of this git revision, "
                         "alternating with the current code")
    args = ap.parse_args()
    pruners = [p.strip() for p in args.pruners.split(",") if p.strip()]
    seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    tmp = Path(tempfile.mkdtemp(prefix="pneutune-tune-bench-"))
    try:
        default = Path("reports/identify/model.yaml")
        choices = [c.strip() for c in (args.model or (str(default) if default.is_file()
                                                      else "truth")).split(",") if c.strip()]
        models: list[tuple[str, Path]] = []
        for choice in choices:
            if choice == "truth":
                path = tmp / "truth-model.yaml"
                plant = PlantConfig().with_updates({"rig": {"pwm_update": args.pwm}},
                                                   source=f"<pwm_update {args.pwm}>")
                save_model(model_from_plant(plant), path)
                models.append((f"model_from_plant(PlantConfig(), {args.pwm})", path))
            else:
                models.append((choice, Path(choice)))
        codes: dict[str, dict[str, str] | None] = {"current": None}
        if args.baseline:
            codes = {"current": None, args.baseline: baseline_env(args.baseline, tmp)}
        if not args.no_throughput:
            for name, path in models:
                print(f"model {name}")
                throughput(load_model(path), args.repeat)
        if args.throughput_only:
            return 0
        print(f"tune --trials {args.trials} --workers {args.workers} (default settings), "
              f"{os.cpu_count()} CPUs; pruners {', '.join(pruners)}, seeds "
              f"{', '.join(map(str, seeds))}, {args.rounds} round(s); code: "
              f"{', '.join(codes)}")
        walls: dict[tuple[str, str, str], list[float]] = {}
        best: dict[tuple[str, str, str, int], float] = {}
        k = 0
        # a source change makes numba compile the kernels anew in the first process (10-20 s):
        # each code runs a 2-trial tune first, outside the timing
        for code, env in codes.items():
            run_tune(models[0][1], tmp / f"warm-{code}", 2, 1, 1, pruners[0], env)
            shutil.rmtree(tmp / f"warm-{code}", ignore_errors=True)
        for name, path in models:
            print(f"model {name}")
            for rnd in range(args.rounds):
                for seed in seeds:
                    runs = [(code, pruner) for code in codes for pruner in pruners]
                    order = runs if k % 2 == 0 else runs[::-1]  # alternate who goes first
                    k += 1
                    for code, pruner in order:
                        out = tmp / f"out-{pruner}-{seed}-{rnd}"
                        wall, res = run_tune(path, out, args.trials, args.workers, seed, pruner,
                                             codes[code])
                        shutil.rmtree(out, ignore_errors=True)
                        tr = res["trials"]
                        walls.setdefault((name, code, pruner), []).append(wall)
                        best[(name, code, pruner, seed)] = res["objective"]["tuned"]
                        print(f"  round {rnd} seed {seed} {code:<8} {pruner:<9} wall "
                              f"{wall:6.1f} s (optimisation {res['wall_s']:5.1f} s, "
                              f"{tr['this_run'] / wall:5.2f} trials/s)  "
                              f"{tr['complete']:3d} complete {tr['pruned']:3d} pruned "
                              f"{tr['failed']} failed  best {res['objective']['tuned']:.4f} "
                              f"(trial {res['best']['trial']}; paper's "
                              f"{_value(res['objective']['paper'])})", flush=True)
        print("wall time of the command (target: <= 45 s on the 2-core machine), min .. max "
              "(median, runs), and the best objective per seed (a seeded study is "
              "reproducible: the same value in every round)")
        print(f"  {'model':<48} {'code':<8} {'pruner':<9} {'wall [s]':<26} best per seed "
              f"{', '.join(map(str, seeds))}")
        for name, _ in models:
            for code in codes:
                for pruner in pruners:
                    w = walls[(name, code, pruner)]
                    b = ", ".join(f"{best[(name, code, pruner, seed)]:.4f}" for seed in seeds)
                    span = f"{min(w):5.1f} .. {max(w):5.1f} ({float(np.median(w)):5.1f}, {len(w)})"
                    print(f"  {name[-48:]:<48} {code:<8} {pruner:<9} {span:<26} {b}")
        compare_best(best, walls, [name for name, _ in models], list(codes), pruners, seeds)
    finally:
        remove_baseline(tmp)
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
