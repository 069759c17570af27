"""``simulate``: run the simulated rig and write an MCAP run log."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence

from tqdm import tqdm

from .cli_common import info, make_parser, print_json, run_cli
from .errors import ExperimentError
from .plant_config import load_plant

DESCRIPTION = """\
Run the simulated rig (the paper's Sec. 2 model with valve switching, stiction, end stops and
noisy sensors) and write the run as an MCAP log (contract pneutune.log/1) that `identify`,
Foxglove or any MCAP reader opens.

experiments:
  identification   the identification run: each valve charging/discharging its chamber with the
                   piston on an end stop (full duty and a duty sweep), ramps at several speeds
                   in both directions, sines of rising frequency, rest. No tuned controller is
                   needed: a proportional loop designed from the stroke alone moves the piston.
"""

EPILOG = """\
examples:
  simulate --experiment identification --seed 3 --out /tmp/r.mcap
  simulate --experiment identification --plant my-rig.yaml --out data/my-run.mcap --json

plant.yaml is merged over the paper's rig; see DESIGN.md, contract 2. The same seed gives the
same log, bit for bit, in any process.
"""


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``simulate``."""
    parser = make_parser("simulate", DESCRIPTION, EPILOG)
    parser.add_argument("--experiment", choices=["identification"], required=True,
                        help="the experiment to run")
    parser.add_argument("--out", required=True, metavar="F.mcap", help="the log to write")
    parser.add_argument("--plant", metavar="P.yaml", help="plant.yaml (default: the paper's rig)")
    parser.add_argument("--seed", type=int, metavar="N",
                        help="sensor-noise seed (default: sim.seed of the plant, 1)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object describing the log on stdout")
    args = parser.parse_args(argv)

    plant_cfg = load_plant(args.plant)
    if args.seed is not None and args.seed < 0:
        raise ExperimentError(f"--seed must be >= 0, got {args.seed}")
    seed = plant_cfg.sim.seed if args.seed is None else args.seed
    plant_cfg = plant_cfg.with_updates({"sim": {"seed": seed}})

    from .identification_run import simulate_identification

    bar = tqdm(total=1, unit="sample", desc="identification run", disable=None, leave=False)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    rec = simulate_identification(plant_cfg, seed=seed, progress=progress)
    bar.close()
    run_meta = {"seed": str(seed), "experiment": "identification",
                "plant": os.path.abspath(args.plant) if args.plant else "<defaults>"}
    rec.save(args.out, rig=plant_cfg.rig_metadata(), run=run_meta)
    size = os.path.getsize(args.out)
    summary = {
        "out": args.out, "experiment": "identification", "seed": seed,
        "duration_s": rec.n * rec.Ts, "samples": rec.n, "segments": len(rec.segments_),
        "topics": ["/rig/sensors", "/rig/valves", "/control/reference", "/experiment/segment",
                   "/sim/truth"],
        "bytes": size, "sha256": _sha256(args.out),
    }
    if args.json:
        print_json(summary)
    else:
        info(f"wrote {args.out}: identification run, {summary['duration_s']:.1f} s, "
             f"{rec.n} samples, {len(rec.segments_)} segments, {size / 1e6:.2f} MB, seed {seed}")
        info("topics: " + ", ".join(summary["topics"]))
    return 0


def entry() -> None:  # pragma: no cover - console script
    """Console-script wrapper."""
    run_cli(main)
