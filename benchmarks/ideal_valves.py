"""What the valves' dead zone and the latched PWM update cost the tuned controller (issue 12).

For fleet plants (:func:`fleet.fleet_plant`), this changes the true plant in one respect and
tunes on it as ``fleet.py --kinds t`` does (the changed plant read as a model, ranges ±20 %,
``tune --trials N --seed 1``), then scores the tuned controller and the paper's on the changed
plant (noise seed 1000 + plant, as the fleet):

* ``no-dead-zone``: every valve with ``min_pulse = 0`` and ``delay_off = delay_on``, so the
  effective open fraction equals the duty (no jump at the minimum pulse: any small average
  opening is available, which is what dithering across PWM periods would approximate);
* ``immediate``: a latched plant with ``pwm_update: immediate`` (a new duty acts at once, not
  at the next 16.7 ms period).

Compare with the plant as it is (``fleet.py --kinds t``, docs/tuning.md, "What limits E_p").

    .venv/bin/python benchmarks/ideal_valves.py [--plants 0,5,10,1] [--trials 200]
        [--out reports/ideal-valves]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

from fleet import PAPER, SCORED, fleet_plant, score

from pneutune.control.constants import VALVES
from pneutune.control.contracts.model import save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant


def variants(plant: PlantConfig) -> dict[str, PlantConfig]:
    """The changed plants (module docstring); ``immediate`` only for a latched plant."""
    out = {"no-dead-zone": plant.with_updates({"valves": {
        n: {"min_pulse": 0.0, "delay_off": getattr(plant.valves, n).delay_on}
        for n in VALVES}})}
    if plant.rig.pwm_update == "latched":
        out["immediate"] = plant.with_updates({"rig": {"pwm_update": "immediate"}})
    return out


def main() -> int:
    """Tune and score every plant x variant; print one row each."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", default="0,5,10,1", help="fleet plant indices (default 0,5,10,1)")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0, help="fleet seed (default 0)")
    ap.add_argument("--out", default="reports/ideal-valves")
    args = ap.parse_args()
    tune = shutil.which("tune", path=os.path.dirname(sys.executable)) or "tune"
    print("E_p [mm] tuned / paper's gains: " + " | ".join(SCORED))
    for i in (int(k) for k in args.plants.split(",")):
        for tag, plant in variants(fleet_plant(i, args.seed)).items():
            work = Path(args.out) / f"plant{i:02d}-{tag}"
            shutil.rmtree(work, ignore_errors=True)
            work.mkdir(parents=True)
            save_model(model_from_plant(plant), work / "model.yaml")
            proc = subprocess.run([tune, "--model", str(work / "model.yaml"), "--trials",
                                   str(args.trials), "--out", str(work / "tune"), "--seed", "1",
                                   "--json"], capture_output=True, text=True)
            if proc.returncode != 0:
                print(f"plant {i} {tag}: tune exit {proc.returncode}: "
                      f"{proc.stderr.strip().splitlines()[-1:]}")
                continue
            tuned, _ = score(work / "tune" / "controller.yaml", plant, 1000 + i)
            paper, _ = score(PAPER, plant, 1000 + i)
            print(f"plant {i} ({plant.rig.pwm_update if tag != 'immediate' else 'latched'}) "
                  f"{tag}: " + " | ".join(f"{tuned[s]:.2f} / {paper[s]:.2f}" for s in SCORED),
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
