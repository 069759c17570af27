"""The paper's rig reproduced: Table 1 with the paper's gains on a plant with real-rig effects.

The paper's gains (data/controller-paper.yaml) on the ideal simulated rig track better than the
paper's rig did (E_rms 0.09-0.13 mm against Table 1's 0.16-0.23 mm): a real axis has dynamics
the paper's model lacks. ``data/plant-paper-rig.yaml`` is the paper's geometry and valves plus
those effects at magnitudes inside published ranges (docs/real-rig.md gives each range and its
source). This script shows how close it comes to Table 1.

* default: run the four Table-1 scenarios with the paper's gains on ``--plant`` for noise seeds
  ``--seeds`` (default 1 2 3), and print E_p and E_rms (mean over the seeds and their range)
  against Table 1 with the relative difference; the row passes within ``--tolerance`` (25 %).
* ``--search N --out P.yaml``: choose the effect magnitudes by a seeded Optuna search (TPE,
  ``--search-seed``) of N trials inside the published ranges
  (:data:`pneutune.control.sim.rig_effects.MAGNITUDES`, and :data:`FRICTION`), minimising the
  largest relative difference from Table 1 over the eight figures (mean over ``--seeds``), and
  write the best plant. The ranges are fixed here, before any search: a search may pick inside
  them, never widen them.

    .venv/bin/python benchmarks/paper_rig.py [--plant data/plant-paper-rig.yaml] [--seeds 1 2 3]
    .venv/bin/python benchmarks/paper_rig.py --search 60 --out data/plant-paper-rig.yaml
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig, load_plant
from pneutune.control.contracts.yamlio import write_yaml
from pneutune.control.law.layout import pack
from pneutune.control.sim import rig_effects
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "data" / "controller-paper.yaml"
PLANT = ROOT / "data" / "plant-paper-rig.yaml"

#: What else the paper does not give, and the search may pick: the friction levels (only b_v is
#: in the paper, with the bounds 2000-5000 N s/m of its θ3; the others within
#: benchmarks/fleet.py's spread) and the sensors' noise (0.1-0.5 % of a 10 bar span for the
#: pressure transmitters; 2-20 um for a potentiometer on a 16-bit card): name -> (low, high).
FRICTION: dict[str, tuple[float, float]] = {
    "F_C": (30.0, 120.0),  # Coulomb level [N]
    "F_S_ratio": (1.1, 1.8),  # F_S / F_C [-]
    "v_s": (2.0e-3, 8.0e-3),  # Stribeck velocity [m/s]
    "b_v": (2000.0, 5000.0),  # viscous coefficient [N s/m]
    "p_noise": (100.0, 5000.0),  # pressure noise std [Pa]
    "x_noise": (2.0e-6, 2.0e-5),  # position noise std [m]
}


def plant_updates(m: dict[str, float]) -> dict[str, Any]:
    """plant.yaml updates for the magnitudes ``m``: every effect of
    :mod:`pneutune.control.sim.rig_effects` and the friction and noise of :data:`FRICTION`."""
    upd = rig_effects.plant_updates(m)
    upd["friction"].update({"F_C": m["F_C"], "F_S": m["F_C"] * m["F_S_ratio"], "v_s": m["v_s"],
                            "b_v": m["b_v"]})
    upd["sensors"].update({"p_noise": m["p_noise"], "x_noise": m["x_noise"]})
    return upd


def table1(plant: PlantConfig, seeds: list[int]) -> dict[str, np.ndarray]:
    """E_p and E_rms [mm] of the paper's gains per Table-1 scenario: array (seeds, 2)."""
    ctl = load_controller(PAPER)
    vec = pack(ctl)
    out = {}
    for name in GROUPS["table1"]:
        rows = []
        for seed in seeds:
            m = simulate_scenario(ctl, SCENARIOS[name], plant, seed=seed, cfg_vec=vec).metrics
            rows.append((m.E_p_mm, m.E_rms_mm))
        out[name] = np.array(rows)
    return out


def worst_difference(res: dict[str, np.ndarray]) -> float:
    """The largest |relative difference| from Table 1 over the eight mean figures."""
    worst = 0.0
    for name, arr in res.items():
        paper = SCENARIOS[name].paper
        assert paper is not None
        mean = arr.mean(axis=0)
        worst = max(worst, *(abs(mean[j] / paper[j] - 1.0) for j in range(2)))
    return worst


def report(res: dict[str, np.ndarray], tolerance: float) -> bool:
    """Print the comparison; whether every figure is within ``tolerance``."""
    ok = True
    print(f"{'scenario':18s} {'E_p paper':>9s} {'E_p here (range)':>24s} {'diff':>7s}   "
          f"{'E_rms paper':>11s} {'E_rms here (range)':>24s} {'diff':>7s}")
    for name, arr in res.items():
        paper = SCENARIOS[name].paper
        assert paper is not None
        cells = []
        for j in range(2):
            mean = arr[:, j].mean()
            diff = mean / paper[j] - 1.0
            ok = ok and abs(diff) <= tolerance
            cells.append(f"{paper[j]:9.2f} {mean:8.3f} ({arr[:, j].min():.3f}-"
                         f"{arr[:, j].max():.3f}) {diff:+7.0%}")
        print(f"{name:18s} {cells[0]}   {cells[1]}")
    print(f"every figure within {tolerance:.0%} of Table 1: {'yes' if ok else 'no'}")
    return ok


def search(trials: int, seeds: list[int], seed: int,
           start: dict[str, float] | None = None) -> tuple[dict[str, float], float]:
    """Seeded TPE search of the magnitudes (its first trial ``start``, if given); the best and
    its worst difference."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    base = PlantConfig()

    def objective(trial: optuna.Trial) -> float:
        m = {k: trial.suggest_float(k, r.low, r.high, log=r.log)
             for k, r in rig_effects.MAGNITUDES.items()}
        m |= {k: trial.suggest_float(k, lo, hi) for k, (lo, hi) in FRICTION.items()}
        plant = base.with_updates(plant_updates(m))
        worst = worst_difference(table1(plant, seeds))
        print(f"trial {trial.number:3d}: worst difference {worst:6.1%}", flush=True)
        return worst

    study = optuna.create_study(sampler=optuna.samplers.TPESampler(seed=seed))
    if start is not None:
        study.enqueue_trial(start)
    study.optimize(objective, n_trials=trials)
    return dict(study.best_params), float(study.best_value)


def main(argv: list[str] | None = None) -> int:
    """Run the comparison (or the search); exit 0 when every figure is within tolerance."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", type=Path, default=PLANT, help="plant.yaml to compare")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="noise seeds")
    ap.add_argument("--tolerance", type=float, default=0.25, help="relative (default 0.25)")
    ap.add_argument("--search", type=int, default=0, metavar="N",
                    help="choose the magnitudes by N search trials instead")
    ap.add_argument("--search-seed", type=int, default=1, help="seed of the search")
    ap.add_argument("--out", type=Path, help="where --search writes the best plant (and its "
                    "magnitudes beside it, as OUT.params.json)")
    ap.add_argument("--start", type=Path, metavar="PARAMS.json",
                    help="--search starts from these magnitudes (an earlier search's)")
    args = ap.parse_args(argv)
    if args.search:
        if args.out is None:
            ap.error("--search needs --out")
        t0 = time.perf_counter()
        start = json.loads(args.start.read_text()) if args.start else None
        best, worst = search(args.search, args.seeds, args.search_seed, start)
        print(f"best of {args.search} trials ({time.perf_counter() - t0:.0f} s): worst "
              f"difference {worst:.1%}")
        for k, v in best.items():
            print(f"  {k} = {v:.4g}")
        header = (f"The paper's rig with real-rig effects (benchmarks/paper_rig.py --search "
                  f"{args.search} --search-seed {args.search_seed} --seeds "
                  f"{' '.join(map(str, args.seeds))}"
                  + (f" --start {args.start.name}" if args.start else "")
                  + f"): worst difference from Table 1 {worst:.1%}. Magnitudes inside the "
                  "published ranges of docs/real-rig.md.")
        write_yaml(args.out, PlantConfig().with_updates(plant_updates(best)).to_dict(),
                   header=header)
        params = args.out.with_suffix(".params.json")
        params.write_text(json.dumps(best, indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.out} and {params}")
        args.plant = args.out
    plant = load_plant(args.plant)
    print(f"{args.plant.name}: effects {', '.join(plant.effects) or 'none'}; paper's gains; "
          f"noise seeds {' '.join(map(str, args.seeds))}")
    t0 = time.perf_counter()
    ok = report(table1(plant, args.seeds), args.tolerance)
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
