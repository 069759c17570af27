"""How close identified PWM curves are to each true valve's curve: its own against the shared one.

For every identified model of a ``fleet.py`` run (``OUT/plantNN/K/identify/model.yaml``), each
valve's true curve is computed from the fleet plant's timing
(:func:`~pneutune.control.physics.pwm.effective_open_fraction`, the plant's own switching) on
201 duties, and compared with the model's curve for that valve (``valves.<v>.pwm``, else the
top-level ``pwm``) and with the top-level ``pwm`` alone (what every valve was inverted on before
contract 4 had a curve per valve). Printed: the mean absolute difference over the duties, the
mean over the four valves and the worst valve, per model and per log kind.

    .venv/bin/python benchmarks/pwm_curves.py /tmp/fleet8 [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from fleet import fleet_plant

from pneutune.control.contracts.model import load_model
from pneutune.control.physics.pwm import effective_open_fraction

DUTIES = np.linspace(0.0, 1.0, 201)


def curve_errors(model_path: Path, plant_index: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Per valve, the mean |model curve - true curve| of its own curve and of the shared one."""
    plant = fleet_plant(plant_index, seed, effects=False)
    model = load_model(model_path)
    shared = np.interp(DUTIES, model.pwm.duty, model.pwm.ratio)
    own, common = [], []
    for mv, tv in zip(model.valves.ordered(), plant.valves.ordered(), strict=True):
        true = effective_open_fraction(DUTIES, plant.rig.pwm_period, tv.delay_on, tv.delay_off,
                                       tv.min_pulse)
        curve = mv.pwm if mv.pwm is not None else model.pwm
        own.append(np.mean(np.abs(np.interp(DUTIES, curve.duty, curve.ratio) - true)))
        common.append(np.mean(np.abs(shared - true)))
    return np.array(own), np.array(common)


def main() -> int:
    """Print one line per identified model and a summary per log kind."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="a fleet.py --out directory")
    ap.add_argument("--seed", type=int, default=0, help="fleet seed of that run (default 0)")
    args = ap.parse_args()
    by_kind: dict[str, list[tuple[float, float]]] = {}
    paths = sorted(args.out.glob("plant[0-9][0-9]/*/identify/model.yaml"))
    if not paths:
        print(f"error: no plantNN/K/identify/model.yaml under {args.out}", file=sys.stderr)
        return 2
    print("mean |curve - true| over 201 duties: valves' mean (worst valve)")
    for path in paths:
        plant_index, kind = int(path.parts[-4][5:]), path.parts[-3]
        own, common = curve_errors(path, plant_index, args.seed)
        by_kind.setdefault(kind, []).append((own.mean(), common.mean()))
        print(f"plant {plant_index:2d} log {kind}: own curves {own.mean():.4f} ({own.max():.4f})"
              f" | shared curve {common.mean():.4f} ({common.max():.4f})")
    for kind, rows in sorted(by_kind.items()):
        a = np.array(rows)
        print(f"log {kind}: own {a[:, 0].mean():.4f}, shared {a[:, 1].mean():.4f}; own closer on "
              f"{int(np.sum(a[:, 0] < a[:, 1]))} of {len(a)} models")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
