"""How the lag estimate of the moving mass depends on the sensor logging period.

``identify`` estimates the mass from the lag M/b_v of the position behind the integrated
pressure force (:class:`pneutune.identify.mass.LagMassIdentifier`). The force between samples
is interpolated, so the logging period matters. For each period this script simulates the
identification run (control period 4 ms, the same protocol) on the default plant and on the
four plant variants that tests/test_identify.py recovers
(:data:`pneutune.control.sim.plant_variants.PLANT_VARIANTS`), runs the whole of ``identify``
and prints the mass, its interval and the error against the plant's.

    .venv/bin/python benchmarks/mass_sampling.py              # about 10 min on 2 cores
    .venv/bin/python benchmarks/mass_sampling.py --quick      # default plant only, 2 seeds

The figures go into docs/identifiability.md.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.rig.identification_run import simulate_identification
from pneutune.control.sim.plant_variants import PLANT_VARIANTS, variant_plant
from pneutune.identify.pipeline import identify


def _plants(quick: bool) -> dict[str, PlantConfig]:
    plants = {"default": PlantConfig()}
    if not quick:
        plants.update({name: variant_plant(name) for name in PLANT_VARIANTS})
    return plants


def main() -> None:
    """Print one line per (plant, period, seed)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="default plant only, two seeds")
    ap.add_argument("--periods", default="0.0005,0.001,0.002,0.004",
                    help="comma-separated logging periods [s]")
    args = ap.parse_args()
    periods = [float(p) for p in args.periods.split(",")]
    seeds = (1, 2) if args.quick else (1, 2, 3)
    print(f"{'plant':28s} {'period':>7s} {'seed':>4s} {'M true':>7s} {'M':>7s} {'err':>7s} "
          f"{'interval':>17s}  basis")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for name, plant in _plants(args.quick).items():
            for h in periods:
                for seed in seeds:
                    path = Path(tmp) / "run.mcap"
                    simulate_identification(plant, seed=seed, sample_period=h).save(
                        path, rig=plant.rig_metadata(), run={"seed": str(seed)})
                    r = identify(path, seed=0)
                    lo, hi = r.model.mass_range
                    M, Mt = r.model.mass, plant.total_mass
                    ok = "in" if lo <= Mt <= hi else "MISSES"
                    basis = "lag" if "lag" in r.mass_basis else r.mass_basis.split(" (")[0]
                    print(f"{name:28s} {h * 1e3:5.1f}ms {seed:4d} {Mt:7.3f} {M:7.3f} "
                          f"{(M / Mt - 1) * 100:+6.1f}% [{lo:6.3f}, {hi:6.3f}] {ok:6s} {basis}",
                          flush=True)
    print(f"wall {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
