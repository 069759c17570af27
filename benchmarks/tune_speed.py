"""Wall time of ``tune --trials 200`` with the default settings, and trials per second.

Runs the ``tune`` console command (a fresh process: imports and loading the cached numba code
included) on a fresh study in a temporary folder, on ``--model`` (default: the command's own
default ``reports/identify/model.yaml`` if it exists, else the truth model of the default plant,
``model_from_plant(PlantConfig())``; ``--model truth`` forces the latter), and prints:

* the wall time of the command (target, issue 5: at most 120 s on the 2-core CI machine);
* trials per second (finished trials / wall time of the command), and of the optimisation alone;
* complete/pruned/failed counts, the best objective and the paper's on the same plants.

Default settings: five scenarios (Table 1 + disturbance) at their full durations, 8 plant draws
run in as many processes as there are CPUs (``--jobs``), CVaR 0.25, MedianPruner after each
scenario, one worker (reproducible). ``--workers 2`` measures the two-worker variant.

    .venv/bin/python benchmarks/tune_speed.py [--trials 200] [--workers 1] [--model M.yaml]
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

from pneutune.control.contracts.model import save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant


def main() -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--model", help="model.yaml, or 'truth' (default: reports/identify/model.yaml "
                    "if it exists, else the truth model of the default plant)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="pneutune-tune-bench-"))
    try:
        default = Path("reports/identify/model.yaml")
        choice = args.model or (str(default) if default.is_file() else "truth")
        model = tmp / "model.yaml" if choice == "truth" else Path(choice)
        if choice == "truth":
            save_model(model_from_plant(PlantConfig()), model)
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
              f"{'model_from_plant(PlantConfig())' if choice == 'truth' else choice}")
        print(f"  wall time of the command   {wall:8.1f} s   (target <= 120 s)")
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
