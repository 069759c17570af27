"""Where the square wave loses: the tracking error of square-0.5hz split by phase of the edge.

This asks why ``square-0.5hz`` stays above 0.2 mm before tuning harder. The smooth square
(:func:`pneutune.control.sim.scenarios.smooth_square`) moves for 0.8 s (a quintic edge) and holds
for 0.2 s, every half period. This runs the scenario on the true plant with ``/sim/truth`` and
splits the metric window (the last three periods, as the paper's E_p) into phases of the
half period τ:

* ``start``   0 <= τ < 0.15 s: the reference starts to move; the piston must break away;
* ``middle``  0.15 <= τ < 0.65 s: cruising at up to 82 mm/s;
* ``arrive``  0.65 <= τ < 0.8 s: decelerating into the new level;
* ``hold``    0.8 <= τ < 1.0 s: the level, where the piston should stand still.

For each phase it prints max |e| and rms e [mm], and counts the stick events (the true speed
below 0.5 mm/s for at least 4 ms while the reference moves faster than 2 mm/s) and the
reversals of the true velocity during holds (hunting). E_p is the max over all phases.

    .venv/bin/python benchmarks/square_wave.py [--controller C.yaml ...] [--plant P.yaml]
        [--seed 1]
"""

from __future__ import annotations

import argparse

import numpy as np

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import load_plant
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import EDGE, SCENARIOS, metric_window

#: Phase edges within the half period [s] (module docstring).
PHASES = (("start", 0.0, 0.15), ("middle", 0.15, EDGE - 0.15), ("arrive", EDGE - 0.15, EDGE),
          ("hold", EDGE, 1.0))
#: A stick: true |v| below this [m/s] ...
STICK_SPEED = 5.0e-4
#: ... for at least this long [s] while |v_r| exceeds REF_MOVING.
STICK_MIN = 4.0e-3
REF_MOVING = 2.0e-3


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the True runs of a boolean array."""
    d = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def analyse(controller_path: str, plant_path: str | None, seed: int) -> None:
    """Run square-0.5hz and print the per-phase table (module docstring)."""
    sc = SCENARIOS["square-0.5hz"]
    res = simulate_scenario(load_controller(controller_path), sc, load_plant(plant_path),
                            seed=seed, record_truth=True)
    n = res.sensors.shape[0]
    window = min(n, metric_window(sc.period, res.Ts))
    sl = slice(n - window, n)
    t = res.t[sl]
    e = (res.sensors[sl, 0] - res.reference[sl, 0]) * 1e3
    v = res.truth[sl, 0]
    v_r = res.reference[sl, 1]
    tau = np.mod(t, 0.5 * sc.period)
    print(f"{controller_path}: E_p {res.metrics.E_p_mm:.3f} mm, E_rms {res.metrics.E_rms_mm:.3f} "
          f"mm (metric window {window * res.Ts:.1f} s)")
    print(f"  {'phase':<7} {'max|e| mm':>9} {'rms e mm':>9} {'sticks':>6} {'hunting':>7} "
          f"{'time share':>10}")
    for name, lo, hi in PHASES:
        m = (tau >= lo) & (tau < hi)
        sticks = sum(1 for a, b in _runs(m & (np.abs(v) < STICK_SPEED) & (np.abs(v_r) > REF_MOVING))
                     if (b - a) * res.Ts >= STICK_MIN)
        hunting = 0
        if name == "hold":
            for a, b in _runs(m):
                s = np.sign(v[a:b][np.abs(v[a:b]) > STICK_SPEED])
                hunting += int(np.count_nonzero(np.diff(s)))
        print(f"  {name:<7} {np.abs(e[m]).max():9.3f} {np.sqrt(np.mean(e[m] ** 2)):9.3f} "
              f"{sticks:6d} {hunting:7d} {m.mean():10.0%}")
    k = int(np.argmax(np.abs(e)))
    print(f"  max |e| at τ = {tau[k]:.3f} s into the half period (e = {e[k]:+.3f} mm, "
          f"v_r = {v_r[k] * 1e3:+.1f} mm/s)")


def main() -> int:
    """Print the analysis for each controller."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--controller", nargs="+", default=["data/controller-paper.yaml"],
                    help="controller.yaml files (default data/controller-paper.yaml)")
    ap.add_argument("--plant", help="plant.yaml (default: the paper's rig)")
    ap.add_argument("--seed", type=int, default=1, help="sensor-noise seed (default 1)")
    args = ap.parse_args()
    for c in args.controller:
        analyse(c, args.plant, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
