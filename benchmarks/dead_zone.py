"""Dead-zone rounding of the PWM inverse: up (today), nearest or down, measured on four plants.

Inside the PWM dead zone ``pwm_inverse`` (control/law/duty.py) rounds a wanted open fraction up
to the smallest pulse that opens the valve. This measures the alternatives before any contract
key exists for them, by giving the paper's controller the PWM curve that makes the unchanged
inverse round otherwise:

* ``nearest``: the jump at the minimum pulse moved to half its height (a wanted fraction below
  half the jump maps to a duty shorter than the minimum pulse: no opening);
* ``down``: the dead zone extended up to the jump (no opening below the jump).

Prints the mean E_p [mm] over noise seeds 1-3 of the five scored scenarios on the paper's rig
and fleet plants 0-2 (benchmarks/fleet.py). docs/tuning.md, "Dead-zone rounding".

    .venv/bin/python benchmarks/dead_zone.py
"""

from __future__ import annotations

import fleet
import numpy as np

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS

SCORED = fleet.SCORED


def variant(paper: ControllerConfig, kind: str) -> ControllerConfig:
    """The paper's controller with the PWM curve that rounds ``kind`` (module docstring)."""
    if kind == "up":
        return paper
    if any(v.pwm is not None for v in paper.valves.ordered()):
        raise SystemExit("dead_zone.py rewrites the top-level pwm only; this controller has "
                         "valve curves of its own (valves.<v>.pwm)")
    d, r = list(paper.pwm.duty), list(paper.pwm.ratio)
    j = next(i for i in range(1, len(d)) if d[i] == d[i - 1] and r[i] > r[i - 1])  # the jump
    dj, rj = d[j], r[j]
    low = rj / 2 if kind == "nearest" else rj
    data = paper.to_dict()
    data["pwm"] = {"duty": [0.0, dj * 0.999, dj, dj, *d[j + 1:]],
                   "ratio": [0.0, low, low, rj, *r[j + 1:]]}
    return ControllerConfig.model_validate(data)


def main() -> int:
    """Print the table."""
    paper = load_controller(fleet.PAPER)
    plants = {"the paper's rig": PlantConfig(),
              "fleet plant 0": fleet.fleet_plant(0, effects=False),
              "fleet plant 1 (latched)": fleet.fleet_plant(1, effects=False),
              "fleet plant 2": fleet.fleet_plant(2, effects=False)}
    print("mean E_p [mm] over seeds 1-3: " + " / ".join(SCORED))
    for name, plant in plants.items():
        for kind in ("up", "nearest", "down"):
            c = variant(paper, kind)
            eps = [np.mean([simulate_scenario(c, SCENARIOS[s], plant, seed=k).metrics.E_p_mm
                            for k in (1, 2, 3)]) for s in SCORED]
            print(f"{name:24s} {kind:8s} " + " / ".join(f"{e:.3f}" for e in eps), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
