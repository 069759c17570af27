"""The best controller ever tuned for each fleet plant: how far the E_p target is.

Re-scores every ``DIR/plantNN/<kind>/tune/controller.yaml`` under the given fleet output
folders (``benchmarks/fleet.py --out DIR``, any kinds, trials, tune seeds or ``--draws``) on
the current true plant :func:`fleet.fleet_plant` (noise seed 1000 + plant, as fleet.py scores),
and prints per plant how many controllers there are, the smallest, 10th-percentile and median
*largest* E_p over the five scored scenarios, and the best controller's distance to the target:

    ratio = max(largest Table-1 E_p / 0.20 mm, disturbance E_p / 0.30 mm)

(<= 1 is on target). A plant whose best ratio stays above 1 over many tunes of every kind is one
where tuning the paper's controller does not reach the target (docs/tuning.md, "How far the
target is").

    .venv/bin/python benchmarks/fleet_best.py DIR [DIR ...] [--seed 0] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from fleet import QUALITY_DISTURBANCE_MM, QUALITY_MM, fleet_plant, score

DISTURBANCE = "disturbance-0.5hz"
PATTERN = re.compile(r"plant(\d+)/([^/]+)/tune/controller\.yaml$")


def target_ratio(e_p: dict[str, float]) -> float:
    """max(largest Table-1 E_p / QUALITY_MM, disturbance E_p / QUALITY_DISTURBANCE_MM)."""
    table1 = max(v for k, v in e_p.items() if k != DISTURBANCE) / QUALITY_MM
    return max(table1, e_p[DISTURBANCE] / QUALITY_DISTURBANCE_MM)


def _job(args: tuple[str, int, int]) -> tuple[str, int, dict[str, float] | None, str]:
    path, plant, seed = args
    try:
        e_p, _, _ = score(Path(path), fleet_plant(plant, seed, effects=False),
                          (1000 + plant,))
    except Exception as exc:  # an old controller.yaml the current contract refuses
        return path, plant, None, f"{type(exc).__name__}: {str(exc)[:120]}"
    return path, plant, {k: float(v) for k, v in e_p.items()}, ""


def main() -> int:
    """Score every controller found and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", metavar="DIR", help="fleet.py --out folders")
    ap.add_argument("--seed", type=int, default=0, help="fleet seed of those runs (default 0)")
    ap.add_argument("--processes", type=int, default=2, help="scoring processes (default 2)")
    ap.add_argument("--json", metavar="OUT.json", help="also write every score here")
    args = ap.parse_args()
    jobs = []
    for d in args.dirs:
        for p in sorted(Path(d).glob("plant*/*/tune/controller.yaml")):
            m = PATTERN.search(p.as_posix())
            if m:
                jobs.append((str(p), int(m.group(1)), args.seed))
    if not jobs:
        print(f"error: no plantNN/<kind>/tune/controller.yaml under {', '.join(args.dirs)}",
              file=sys.stderr)
        return 2
    with Pool(max(1, args.processes)) as pool:
        results = pool.map(_job, jobs, chunksize=4)
    failed = [(p, why) for p, _, e, why in results if e is None]
    by_plant: dict[int, list[tuple[float, float, str]]] = {}
    for path, plant, e_p, _ in results:
        if e_p is not None:
            by_plant.setdefault(plant, []).append((max(e_p.values()), target_ratio(e_p), path))
    print("| plant | controllers | largest E_p [mm]: best / 10 % / median | best ratio to the "
          "target | on target | best controller |")
    print("|---|---|---|---|---|---|")
    for plant in sorted(by_plant):
        rows = by_plant[plant]
        largest = np.array([r[0] for r in rows])
        best = min(rows, key=lambda r: r[1])
        print(f"| {plant} | {len(rows)} | {largest.min():.2f} / {np.percentile(largest, 10):.2f} "
              f"/ {np.median(largest):.2f} | {best[1]:.2f} | {sum(r[1] <= 1.0 for r in rows)} | "
              f"{best[2]} |")
    reached = sum(min(r[1] for r in rows) <= 1.0 for rows in by_plant.values())
    print(f"\n{len(results) - len(failed)} controllers scored on {len(by_plant)} plants; the "
          f"target reached on {reached} plant(s) by at least one controller"
          + (f"; {len(failed)} could not be scored (first: {failed[0][0]}: {failed[0][1]})"
             if failed else ""))
    if args.json:
        Path(args.json).write_text(json.dumps(
            [{"path": p, "plant": i, "e_p": e, "error": why} for p, i, e, why in results],
            indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
