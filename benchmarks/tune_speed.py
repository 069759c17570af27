"""Wall time of ``tune --trials 200`` with the default settings, trials per second, and the
simulated seconds per wall second of the objective's closed loops.

Runs the ``tune`` console command (a fresh process: imports and loading the cached numba code
included) on a fresh study in a temporary folder, on ``--model`` (default: the command's own
default ``reports/identify/model.yaml`` if it exists, else the truth model of the default plant,
``model_from_plant(PlantConfig())``; ``--model truth`` forces the latter), and prints:

* the wall time of the command (target, issue 5: at most 120 s on the 2-core CI machine);
* trials per second (finished trials / wall time of the command), and of the optimisation alone;
* complete/pruned/failed counts, the best objective and the paper's on the same plants.

Default settings: five scenarios (Table 1 + disturbance) at their full durations, 8 plant draws
run on as many numba threads as there are CPUs (``--jobs``), CVaR 0.25, MedianPruner after each
scenario, one worker (reproducible). ``--workers 2`` measures the two-worker variant.

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

    .venv/bin/python benchmarks/tune_speed.py [--trials 200] [--workers 1] [--model M.yaml]
        [--pwm latched] [--throughput-only] [--repeat 5]
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

import numba
import numpy as np

from pneutune.control.contracts.model import ModelConfig, load_model, save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.objective import ObjectiveSettings, TuneObjective
from pneutune.tune.space import controller_from_params


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


def main() -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--model", help="model.yaml, or 'truth' (default: reports/identify/model.yaml "
                    "if it exists, else the truth model of the default plant)")
    ap.add_argument("--pwm", choices=("immediate", "latched"), default="immediate",
                    help="PWM update mode of the truth model (default immediate)")
    ap.add_argument("--repeat", type=int, default=5, help="throughput repeats (default 5)")
    ap.add_argument("--throughput-only", action="store_true",
                    help="print the closed-loop throughput only, do not run tune")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="pneutune-tune-bench-"))
    try:
        default = Path("reports/identify/model.yaml")
        choice = args.model or (str(default) if default.is_file() else "truth")
        model = tmp / "model.yaml" if choice == "truth" else Path(choice)
        if choice == "truth":
            plant = PlantConfig().with_updates({"rig": {"pwm_update": args.pwm}},
                                               source=f"<pwm_update {args.pwm}>")
            save_model(model_from_plant(plant), model)
        throughput(load_model(model), args.repeat)
        if args.throughput_only:
            return 0
        exe = shutil.which("tune", path=os.path.dirname(sys.executable)) or "tune"
        cmd = [exe, "--model", str(model), "--trials", str(args.trials), "--workers",
               str(args.workers), "--out", str(tmp / "out"), "--json"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            sys.stderr.write(proc.stderr)
            return proc.returncode
        res = json.loads(proc.stdout)
        tr = res["trials"]
        print(f"tune --trials {args.trials} --workers {args.workers} (default settings), "
              f"{os.cpu_count()} CPUs, model: "
              f"{f'model_from_plant(PlantConfig(), {args.pwm})' if choice == 'truth' else choice}")
        print(f"  wall time of the command   {wall:8.1f} s   (target, issue 12: <= 60 s)")
        print(f"  trials per second          {tr['this_run'] / wall:8.2f}   "
              f"(optimisation alone: {tr['this_run'] / res['wall_s']:.2f}, {res['wall_s']:.1f} s)")
        print(f"  trials                     {tr['complete']} complete, {tr['pruned']} pruned, "
              f"{tr['failed']} failed")
        print(f"  best objective             {res['objective']['tuned']:8.4f}   (trial "
              f"{res['best']['trial']}; data/controller-paper.yaml: "
              f"{res['objective']['paper']:.4f})")
        for name, m in res["nominal"]["tuned"].items():
            p = res["nominal"]["paper"][name]
            print(f"  nominal {name:<18} tuned E_p {m['E_p_mm']:.3f} E_rms {m['E_rms_mm']:.3f} "
                  f"mm | paper E_p {p['E_p_mm']:.3f} E_rms {p['E_rms_mm']:.3f} mm")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
