"""What the valves' dead zone and the latched PWM update cost the tuned controller.

For fleet plants (:func:`fleet.fleet_plant`), this changes the true plant in one respect and
tunes on it as ``fleet.py --kinds t`` does (the changed plant read as a model, ranges ±20 %,
``tune --trials N --seed S`` for each of ``--tune-seeds``), then scores the tuned controller
and the paper's on the changed plant (noise seed 1000 + plant, as the fleet):

* ``no-dead-zone``: every valve with ``min_pulse = 0`` and ``delay_off = delay_on``, so the
  effective open fraction equals the duty (no jump at the minimum pulse: any small average
  opening is available, which is what dithering across PWM periods would approximate);
* ``immediate``: a latched plant with ``pwm_update: immediate`` (a new duty acts at once, not
  at the next 16.7 ms period);
* ``equal-timing``: every valve with a_in's ``delay_on``, ``delay_off`` and ``min_pulse`` (C
  and b unchanged), so that a_in's curve is right for all four valves. It changes the plant (a
  slow valve becomes as fast as a_in), so it is not a bound on what one curve per valve
  recovers (docs/tuning.md, "One PWM curve per valve");
* ``one-curve``: the plant as it is, the model (and so the controller) without the valves' own
  PWM curves (``valves.<v>.pwm``): every valve's duty inverted on a_in's curve, as before
  contract 4 had a curve per valve;
* ``dither``: the plant as it is, the controller tuned and scored with ``dead_zone: dither``
  (``tune --dead-zone dither``: whole smallest pulses in some PWM periods, their mean the wanted
  opening), what a controller can recover of the ``no-dead-zone`` row.

``as-is`` is the plant unchanged (what ``fleet.py --kinds t`` does, docs/tuning.md, "What limits
E_p").

    .venv/bin/python benchmarks/ideal_valves.py [--plants 0,5,10,1] [--trials 200]
        [--tune-seeds 1,2,3] [--only as-is,dither] [--out reports/ideal-valves]

One tune is one draw of a noisy search (TPE from one seed; a run of 200 trials can land in a
different basin): compare variants over several ``--tune-seeds``, not one.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from fleet import PAPER, SCORED, fleet_plant, score

from pneutune.control.constants import VALVES
from pneutune.control.contracts.model import ModelConfig, save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant


def variants(plant: PlantConfig) -> dict[str, PlantConfig]:
    """The plants per variant (module docstring); ``immediate`` only for a latched plant."""
    out = {"as-is": plant, "no-dead-zone": plant.with_updates({"valves": {
        n: {"min_pulse": 0.0, "delay_off": getattr(plant.valves, n).delay_on}
        for n in VALVES}})}
    a_in = plant.valves.a_in
    out["equal-timing"] = plant.with_updates({"valves": {
        n: {"delay_on": a_in.delay_on, "delay_off": a_in.delay_off, "min_pulse": a_in.min_pulse}
        for n in VALVES}})
    if plant.rig.pwm_update == "latched":
        out["immediate"] = plant.with_updates({"rig": {"pwm_update": "immediate"}})
    out["one-curve"] = plant
    out["dither"] = plant
    return out


def tune_and_score(i: int, tag: str, plant: PlantConfig, seed: int, trials: int,
                   work: Path) -> dict[str, float] | None:
    """``tune --seed seed`` on ``plant`` read as a model; E_p [mm] per scenario on ``plant``."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    model = model_from_plant(plant)
    if tag == "one-curve":
        data = model.to_dict()
        for name in VALVES:
            data["valves"][name].pop("pwm", None)
        model = ModelConfig.model_validate(data)
    save_model(model, work / "model.yaml")
    tune = shutil.which("tune", path=os.path.dirname(sys.executable)) or "tune"
    proc = subprocess.run([tune, "--model", str(work / "model.yaml"), "--trials", str(trials),
                           "--out", str(work / "tune"), "--seed", str(seed),
                           "--dead-zone", "dither" if tag == "dither" else "up", "--json"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        print(f"plant {i} {tag} seed {seed}: tune exit {proc.returncode}: "
              f"{proc.stderr.strip().splitlines()[-1:]}")
        return None
    tuned, _, _ = score(work / "tune" / "controller.yaml", plant, (1000 + i,))
    return tuned


def main() -> int:
    """Tune and score every plant x variant x tune seed; print one row each and the means."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", default="0,5,10,1", help="fleet plant indices (default 0,5,10,1)")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0, help="fleet seed (default 0)")
    ap.add_argument("--tune-seeds", default="1", help="comma-separated tune --seed values; "
                    "with several, a summary gives the mean and range per cell (default 1)")
    ap.add_argument("--out", default="reports/ideal-valves")
    ap.add_argument("--only", default="", help="comma-separated variants to run (default all: "
                    "as-is, no-dead-zone, equal-timing, immediate, one-curve, dither)")
    args = ap.parse_args()
    seeds = [int(k) for k in args.tune_seeds.split(",")]
    print("E_p [mm] tuned / paper's gains: " + " | ".join(SCORED))
    summary: list[tuple[str, np.ndarray]] = []
    for i in (int(k) for k in args.plants.split(",")):
        for tag, plant in variants(fleet_plant(i, args.seed, effects=False)).items():
            if args.only and tag not in args.only.split(","):
                continue
            paper, _, _ = score(PAPER, plant, (1000 + i,))
            label = f"plant {i} ({plant.rig.pwm_update if tag != 'immediate' else 'latched'}) {tag}"
            rows = []
            for seed in seeds:
                tuned = tune_and_score(i, tag, plant, seed, args.trials,
                                       Path(args.out) / f"plant{i:02d}-{tag}-seed{seed}")
                if tuned is None:
                    continue
                rows.append([tuned[s] for s in SCORED])
                print(f"{label} seed {seed}: "
                      + " | ".join(f"{tuned[s]:.2f} / {paper[s]:.2f}" for s in SCORED),
                      flush=True)
            if rows:
                summary.append((label, np.array(rows)))
    if len(seeds) > 1:
        print(f"\nmean (min-max) over tune seeds {args.tune_seeds}; last column: the mean of the "
              "largest E_p per run")
        for label, a in summary:
            cells = [f"{a[:, j].mean():.2f} ({a[:, j].min():.2f}-{a[:, j].max():.2f})"
                     for j in range(a.shape[1])]
            print(f"{label}: " + " | ".join(cells) + f" | {a.max(axis=1).mean():.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
