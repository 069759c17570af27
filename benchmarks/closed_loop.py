"""Closed-loop simulation speed, step-size accuracy and controller step latency.

Prints:
* simulated seconds per wall second for a 20 s closed-loop run (modified DARC of
  data/controller-paper.yaml tracking 17.5 sin(pi t) mm on the default plant), after warm-up,
  best of 5, one core (target: >= 1000);
* E_p and E_rms of that run at the default step against a 10 us run (target: within 0.005 mm);
* the latency of one controller step called from Python (`darc.step`), p50 and p99 over
  20,000 calls (target: p99 <= 20 us), and of the compiled `step_into` inside the loop;
* the cost of each real-rig effect (:mod:`pneutune.control.sim.rig_effects`, typical
  magnitudes): the same 20 s run with that effect alone and with all of them (and with the
  pressure transmitters at the valves' side of the lines), simulated seconds
  per wall second (best of 3) against the plant without effects measured beside it (skip with
  ``--no-effects``).

    .venv/bin/python benchmarks/closed_loop.py [--no-effects]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law import darc
from pneutune.control.law.layout import pack
from pneutune.control.sim import rig_effects
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS, Scenario

PAPER = Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml"


def main() -> None:
    """Print the figures."""
    controller = load_controller(PAPER)
    cfg = pack(controller)
    base = SCENARIOS["sine-0.5hz"]
    sc = Scenario("sine-0.5hz-20s", base.description, 20.0, base.period, base.reference)
    simulate_scenario(controller, sc, seed=1, cfg_vec=cfg)  # warm-up (compile or load)
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        res = simulate_scenario(controller, sc, seed=1, cfg_vec=cfg)
        best = min(best, time.perf_counter() - t0)
    print(f"closed loop, 20 s sine-0.5hz: {sc.duration / best:,.0f} simulated s per wall s "
          f"({best * 1e3:.1f} ms wall, {best / res.sensors.shape[0] * 1e6:.2f} us per 4 ms "
          f"sample; target >= 1000)")

    ref = simulate_scenario(controller, sc, PlantConfig().with_updates({"sim": {"dt": 1e-5}}),
                            seed=1, cfg_vec=cfg).metrics
    m = res.metrics
    print(f"step accuracy: default dt E_p={m.E_p_mm:.4f} E_rms={m.E_rms_mm:.4f} mm; 10 us "
          f"E_p={ref.E_p_mm:.4f} E_rms={ref.E_rms_mm:.4f} mm; difference "
          f"{abs(m.E_p_mm - ref.E_p_mm):.4f} / {abs(m.E_rms_mm - ref.E_rms_mm):.4f} mm "
          f"(target <= 0.005)")

    state = darc.init_state(cfg, 0.0235, 2.0e5, 2.0e5)
    rng = np.random.default_rng(0)
    n = 20000
    meas = [darc.make_meas(k * 0.004, 0.0235 + 1e-4 * rng.standard_normal(),
                           2.0e5 + 1e3 * rng.standard_normal(), 2.0e5, 6.0e5,
                           0.0235 + 0.0175 * np.sin(np.pi * k * 0.004),
                           0.0175 * np.pi * np.cos(np.pi * k * 0.004),
                           -0.0175 * np.pi**2 * np.sin(np.pi * k * 0.004)) for k in range(n)]
    for k in range(200):
        darc.step(state, meas[k], cfg)
    lat = np.empty(n)
    clock = time.perf_counter_ns
    for k in range(n):
        t0 = clock()
        darc.step(state, meas[k], cfg)
        lat[k] = clock() - t0
    p50, p99 = np.percentile(lat, [50, 99]) / 1e3
    print(f"controller step from Python (darc.step): p50 {p50:.2f} us, p99 {p99:.2f} us, "
          f"max {lat.max() / 1e3:.1f} us (target p99 <= 20 us)")
    if "--no-effects" not in sys.argv[1:]:
        effect_costs(controller, cfg, sc)


def effect_costs(controller: object, cfg: np.ndarray, sc: Scenario) -> None:
    """Print the closed loop's speed with each real-rig effect alone and with all of them."""
    m = rig_effects.typical()
    cases = {"none": PlantConfig()}
    for name in rig_effects.EFFECTS:
        cases[name] = PlantConfig().with_updates(rig_effects.plant_updates(m, (name,)))
    cases["all"] = PlantConfig().with_updates(rig_effects.plant_updates(m))
    # the transmitters at the valves read nothing new without a line conductance
    at_valves = {"sensors": {"p_at": "valves"}}
    cases["lines, transmitters at the valves"] = cases["lines"].with_updates(at_valves)
    cases["all, transmitters at the valves"] = cases["all"].with_updates(at_valves)
    best = {}
    for name, plant in cases.items():
        simulate_scenario(controller, sc, plant, seed=1, cfg_vec=cfg)  # compile or load
        walls = []
        for _ in range(3):
            t0 = time.perf_counter()
            simulate_scenario(controller, sc, plant, seed=1, cfg_vec=cfg)
            walls.append(time.perf_counter() - t0)
        best[name] = min(walls)
    print("cost of each real-rig effect at its typical magnitude (20 s sine-0.5hz, best of 3):")
    for name, wall in best.items():
        print(f"  {name:14s} {sc.duration / wall:8,.0f} simulated s per wall s "
              f"({wall / best['none']:.2f} x the time without effects)")


if __name__ == "__main__":
    main()
