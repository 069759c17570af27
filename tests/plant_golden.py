"""The plant's outputs with every real-rig effect off, kept bit for bit.

``tests/data/plant_golden.npz`` holds what :func:`golden_outputs` returned before the real-rig
effects (valve lag, lines, heat transfer, LuGre, sensor lags, IO delay, supply droop) were
added to the simulator; with them all off the simulator must still return exactly these arrays.
Regenerate only for a deliberate change of the paper's model, and say so in the commit:

    .venv/bin/python tests/plant_golden.py --write
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant import dynamics
from pneutune.control.plant.params import pack_plant
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS, Scenario

GOLDEN = Path(__file__).resolve().parent / "data" / "plant_golden.npz"
ROOT = Path(__file__).resolve().parents[1]

#: A second plant that exercises the latched PWM, a steep Stribeck branch and the seal leak.
LATCHED = {"rig": {"pwm_update": "latched"}, "friction": {"F_S": 120.0, "v_s": 0.002},
           "leak": {"C": 1.0e-10}}


def golden_outputs() -> dict[str, np.ndarray]:
    """3 s of three Table-1 scenarios under the paper's controller on two plants (seed 3), and
    500 samples of random duties in open loop with a force step (sensors and truth)."""
    ctl = load_controller(ROOT / "data" / "controller-paper.yaml")
    out: dict[str, np.ndarray] = {}
    for name in ("sine-0.5hz", "square-0.5hz", "disturbance-0.5hz"):
        base = SCENARIOS[name]
        sc = Scenario(name + "-3s", base.description, 3.0, base.period, base.reference)
        for mode, upd in (("paper", {}), ("latched", LATCHED)):
            r = simulate_scenario(ctl, sc, PlantConfig().with_updates(upd), seed=3)
            out[f"{name}/{mode}/sensors"] = r.sensors
            out[f"{name}/{mode}/duties"] = r.duties
    pp = pack_plant(PlantConfig().with_updates({"disturbance": {"force_steps": [[0.3, 50.0]]}}))
    rng = np.random.default_rng(0)
    n = 500
    duties = rng.uniform(0.0, 1.0, (n, 4)) * (rng.uniform(0.0, 1.0, (n, 1)) > 0.3)
    s = dynamics.initial_state(pp.vec, 0.02, 2.0e5, 2.0e5)
    sensors = np.zeros((n, 4))
    truth = np.zeros((n, 6))
    dynamics.run_open_loop(pp.vec, s, duties, np.full(n, 6.0e5), pp.force_steps,
                           rng.standard_normal((n, 4)), 0.004, sensors, truth)
    out["open-loop/sensors"] = sensors
    out["open-loop/truth"] = truth
    return out


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/plant_golden.py --write")
    np.savez_compressed(GOLDEN, **golden_outputs())
    print(GOLDEN)
