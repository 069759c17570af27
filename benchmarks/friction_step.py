"""Where a steep Stribeck law limits the integration step: one step for the whole run against a
step chosen from the speed (docs/integration.md, "Steep friction").

A plant whose friction falls steeply from F_S to F_C (large F_S - F_C, small v_s) has an
unstable velocity mode on the falling branch, eigenvalue up to ((F_S - F_C) max|g'| - b_v)/M,
that RK4 must resolve. The integrator used to take the step for the stiffest speed for the whole
run; it now takes it only at the speeds that need it. For each plant and scenario this prints
E_p and E_rms [mm] and the wall time of

* ``global``: every step at most ``1.4 M / k_max`` (the earlier rule, reproduced by setting
  ``sim.dt`` to that step, which turns the speed rule off);
* ``local``: the integrator as it is (``sim.dt`` = 0.4 ms, shortened near v = 0 only);
* ``10 us``: the reference, every step 10 us;

with the controller of ``--controller`` (default: the paper's, ``data/controller-paper.yaml``)
and the scenario's own noise seed.

    .venv/bin/python benchmarks/friction_step.py
    .venv/bin/python benchmarks/friction_step.py --model MODEL.yaml --controller CTRL.yaml
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.model import load_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant.params import P_DTMIN, pack_plant
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
SCENARIO_NAMES = GROUPS["all"]
#: Steep variants of the paper's rig (F_S [N], F_C [N], v_s [m/s], alpha, b_v [N s/m], M [kg]).
STEEP = {
    "F_S 3x, v_s 2.5 mm/s": (150.0, 50.0, 2.5e-3, 2.0, 3500.0, 1.05),
    "F_S 2.9x, alpha 4.75, light": (217.0, 117.0, 4.66e-3, 4.75, 2169.0, 0.705),
    "alpha 3.2, v_s 1.8 mm/s": (101.5, 54.6, 1.81e-3, 3.19, 3520.0, 0.924),
}


def min_step(plant: PlantConfig) -> float:
    """The earlier rule's step: ``min(sim.dt, 1.4 M / k_max)`` [s] (the plant's ``P_DTMIN``)."""
    return float(pack_plant(plant).vec[P_DTMIN])


def steep_plants() -> dict[str, PlantConfig]:
    """The :data:`STEEP` variants of the default plant (payload as it is, mass adjusted)."""
    base = PlantConfig()
    return {label: base.with_updates({
        "friction": {"F_S": fs, "F_C": fc, "v_s": vs, "alpha": alpha, "b_v": bv},
        "mass": mass - base.payload})
        for label, (fs, fc, vs, alpha, bv, mass) in STEEP.items()}


def run(plant: PlantConfig, controller: ControllerConfig, name: str) -> tuple[float, float, float]:
    """(E_p, E_rms) [mm] and wall time [s] of one scenario."""
    t0 = time.perf_counter()
    m = simulate_scenario(controller, SCENARIOS[name], plant).metrics
    return m.E_p_mm, m.E_rms_mm, time.perf_counter() - t0


def main() -> None:
    """Print the comparison."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", help="model.yaml: use its nominal plant and its 'slow' and "
                    "'fast' corners and the draws whose friction limits the step")
    ap.add_argument("--controller", default=str(ROOT / "data" / "controller-paper.yaml"))
    ap.add_argument("--draws", type=int, default=8)
    args = ap.parse_args()
    controller = load_controller(args.controller)
    if args.model:
        from pneutune.tune.plants import draw_plants
        model = load_model(args.model)
        plants = {f"draw {d.index} ({d.label})": d.plant
                  for d in draw_plants(model, args.draws, 1)}
    else:
        plants = steep_plants()
    simulate_scenario(controller, SCENARIOS["sine-0.5hz"], PlantConfig())  # compile
    dev = {"global": [], "local": []}
    time_sum = {"global": 0.0, "local": 0.0, "10 us": 0.0}
    for label, plant in plants.items():
        h = min_step(plant)
        if h >= plant.sim.dt:
            print(f"{label}: friction does not limit the step (1.4 M/k_max >= sim.dt); skipped")
            continue
        print(f"{label}: 1.4 M/k_max = {h * 1e6:.1f} us, sim.dt = {plant.sim.dt * 1e6:.0f} us")
        variants = {"global": plant.with_updates({"sim": {"dt": h}}), "local": plant,
                    "10 us": plant.with_updates({"sim": {"dt": 1.0e-5}})}
        for name in SCENARIO_NAMES:
            res = {k: run(p, controller, name) for k, p in variants.items()}
            ref = res["10 us"]
            for k in time_sum:
                time_sum[k] += res[k][2]
            row = []
            for k in ("global", "local"):
                ep, erms, wall = res[k]
                dev[k].append((abs(ep - ref[0]), abs(erms - ref[1])))
                row.append(f"{k} {ep:.3f}/{erms:.3f} ({wall * 1e3:4.0f} ms)")
            print(f"  {name:18s} " + "  ".join(row)
                  + f"  10 us {ref[0]:.3f}/{ref[1]:.3f} ({ref[2] * 1e3:4.0f} ms)")
    for k in ("global", "local"):
        if dev[k]:
            d = np.array(dev[k])
            print(f"{k:6s}: |E_p - ref| median {np.median(d[:, 0]):.3f} max {d[:, 0].max():.3f} "
                  f"mm, |E_rms - ref| median {np.median(d[:, 1]):.3f} max {d[:, 1].max():.3f} mm,"
                  f" {time_sum[k]:.2f} s in all")
    print(f"10 us : {time_sum['10 us']:.2f} s in all")


if __name__ == "__main__":
    main()
