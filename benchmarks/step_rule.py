"""The step rule's factor: how long a sliding RK4 step may be on a light, heavily damped plant.

While sliding, the integrator keeps ``h * k / M`` at most a factor (``P_STEPK``, from
:data:`pneutune.control.plant.params.STEP_STIFFNESS`), k the stiffest |dF_f/dv| the step
passes through, at least b_v (docs/integration.md, "Steep friction"). RK4 is stable up to 2.79;
the smaller the factor, the shorter the steps of the plants it binds on (small M / b_v, steep
Stribeck branches) and the dearer their runs. This prints, for each model, controller and
factor, the tracking metrics' distance from a fine fixed step and the wall time:

* every draw of ``tune``'s objective (``TuneObjective(model, --seed)``: the nominal plant, two
  corners, a Latin hypercube) x every scenario, run with the controller at ``sim.dt`` (the
  default 0.4 ms, shortened by the rule) for each factor of ``--factors``, and at a fixed
  ``--ref-dt`` (default 10 us, where no factor binds on these plants);
* median and largest |E_p - E_p,ref| and |E_rms - E_rms,ref| [mm] over the runs, the runs
  where the factor shortens the step at all (``binds``), and the summed wall time of the runs.

The controller is the paper's gains with the model's θ box (the study's trial 0) unless
``--controllers`` gives one controller.yaml per model (for instance the tuned one). Runs whose
loop stick-slips erratically move E_p by tenths of a millimetre between any two steps; compare
the factors by their medians, over the same runs.

    .venv/bin/python benchmarks/step_rule.py --model A.yaml[,B.yaml...]
        [--controllers CA.yaml,CB.yaml] [--factors 1.4,2.0] [--ref-dt 1e-5] [--seed 1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.model import load_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.layout import pack
from pneutune.control.plant import params
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.objective import ObjectiveSettings, TuneObjective
from pneutune.tune.space import controller_from_params


def binds(plant: PlantConfig, factor: float) -> bool:
    """Whether ``factor`` shortens any sliding step of ``plant`` below ``sim.dt``."""
    saved = params.STEP_STIFFNESS
    params.STEP_STIFFNESS = factor
    try:
        vec = params.pack_plant(plant).vec
    finally:
        params.STEP_STIFFNESS = saved
    h_visc = factor * vec[params.P_M] / vec[params.P_BV]
    return bool(vec[params.P_DTMIN] < vec[params.P_DT] or h_visc < vec[params.P_DT])


def run_all(objective: TuneObjective, controller: object, factor: float | None,
            ref_dt: float | None = None) -> tuple[np.ndarray, float]:
    """(E_p, E_rms) [mm] of every draw x scenario, and the summed wall time [s].

    ``factor`` sets :data:`~pneutune.control.plant.params.STEP_STIFFNESS` for the runs (None:
    as it is); ``ref_dt`` replaces ``sim.dt``.
    """
    saved = params.STEP_STIFFNESS
    if factor is not None:
        params.STEP_STIFFNESS = factor
    vec = pack(controller)
    rows, wall = [], 0.0
    try:
        for draw in objective.draws:
            plant = draw.plant
            if ref_dt is not None:
                plant = plant.with_updates({"sim": {"dt": ref_dt}})
            for scenario in objective.scenarios:
                t0 = time.perf_counter()
                m = simulate_scenario(controller, scenario, plant, cfg_vec=vec).metrics
                wall += time.perf_counter() - t0
                rows.append((m.E_p_mm, m.E_rms_mm))
    finally:
        params.STEP_STIFFNESS = saved
    return np.array(rows), wall


def main() -> None:
    """Command line (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="truth",
                    help="model.yaml files, comma-separated (default: the truth model of the "
                         "default plant)")
    ap.add_argument("--controllers", default="",
                    help="one controller.yaml per model, comma-separated (default: the paper's "
                         "gains on each model)")
    ap.add_argument("--factors", default="1.4,2.0", help="step factors to compare")
    ap.add_argument("--ref-dt", type=float, default=1.0e-5, help="reference fixed step [s]")
    ap.add_argument("--seed", type=int, default=1, help="the objective's seed (draws, noise)")
    args = ap.parse_args()
    models = args.model.split(",")
    ctls = args.controllers.split(",") if args.controllers else [""] * len(models)
    if len(ctls) != len(models):
        ap.error("--controllers needs one file per model")
    factors = [float(f) for f in args.factors.split(",")]
    print(f"factor now: {params.STEP_STIFFNESS:g}; reference: fixed {args.ref_dt * 1e6:g} us")
    for path, ctl_path in zip(models, ctls, strict=True):
        model = model_from_plant(PlantConfig()) if path == "truth" else load_model(path)
        objective = TuneObjective(model, args.seed, ObjectiveSettings(), jobs=1)
        ctl = (load_controller(ctl_path) if ctl_path else
               controller_from_params(model, objective.space.paper_params()))
        who = ctl_path or "paper's gains"
        ref, ref_wall = run_all(objective, ctl, None, args.ref_dt)
        print(f"\n{path} ({who}): {len(ref)} runs, reference {ref_wall:.1f} s")
        for factor in factors:
            n_bind = sum(binds(d.plant, factor) for d in objective.draws)
            got, wall = run_all(objective, ctl, factor)
            err = np.abs(got - ref)
            print(f"  factor {factor:g}: |dE_p| median {np.median(err[:, 0]):.4f} max "
                  f"{err[:, 0].max():.4f} mm, |dE_rms| median {np.median(err[:, 1]):.4f} max "
                  f"{err[:, 1].max():.4f} mm; binds on {n_bind} of {len(objective.draws)} "
                  f"draws; wall {wall:.2f} s")


if __name__ == "__main__":
    main()
