"""How well can the moving mass be fitted from 4 ms samples, given the rest of the plant?

The experiment behind docs/identifiability.md, section "Prediction-error fit". The mass shows in
a 4 ms log only as the lag M/b_v (0.3 ms on the default plant) between force and velocity.
A prediction-error fit of the whole compiled plant, which knows the force inside each sample,
can see that lag. This script measures how far that carries:

1. the mass from position innovations (:func:`pneutune.identify.prediction.position_innovations`)
   with every other parameter *true*, on a noise-free and on a normally noisy identification run
   of the default plant;
2. how the estimate moves when the valve delays are off by ±20 µs (the lag is a timing);
3. how well the delays themselves come out of one-sample pressure predictions
   (:func:`pneutune.identify.prediction.pressure_residuals`) on the noisy run, per valve.

    .venv/bin/python benchmarks/mass_identifiability.py        # about 1 min

It prints its figures; nothing here is used by ``identify``. What ``identify`` does instead, on
an identification run logged every 0.5 ms, is measured by ``benchmarks/mass_sampling.py``.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import minimize_scalar

from pneutune.control.constants import VALVES
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant.params import (
    P_BV,
    P_DOFF,
    P_DON,
    P_M,
    P_MINP,
    pack_plant,
    set_step_limits,
)
from pneutune.control.rig.identification_run import simulate_identification
from pneutune.identify.dataset import Dataset, load_dataset
from pneutune.identify.prediction import position_innovations, pressure_residuals

#: Samples count once the piston has slid faster than this for SETTLE samples [m/s].
V_SCORE, SETTLE, LEAD_IN, GAIN = 0.02, 5, 25, 0.3


def _scored(v: np.ndarray) -> np.ndarray:
    fast = np.abs(v) > V_SCORE
    ok = fast.copy()
    for k in range(1, SETTLE + 1):
        ok[k:] &= fast[:-k] & (np.sign(v[:-k]) == np.sign(v[k:]))
    ok[:SETTLE] = False
    return ok


def _stretches(scored: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    idx = np.flatnonzero(scored)
    br = np.flatnonzero(np.diff(idx) > LEAD_IN + 1)
    first = np.concatenate([[idx[0]], idx[br + 1]])
    last = np.concatenate([idx[br], [idx[-1]]])
    return np.maximum(first - LEAD_IN, 0).astype(np.int64), (last + 1).astype(np.int64)


def fit_mass(d: Dataset, base: np.ndarray) -> float:
    """Mass minimising the observer's squared position innovations, all else as in ``base``."""
    scored = _scored(d.v)
    starts, ends = _stretches(scored)
    u = np.ascontiguousarray(d.u)

    def cost(M: float) -> float:
        p = base.copy()
        p[P_M] = M
        set_step_limits(p)
        out = np.zeros((1, d.n))
        position_innovations(p[None, :], np.zeros((0, 2)), d.t, d.x, d.p_a, d.p_b, d.p_s, u,
                             starts, ends, GAIN, out)
        return float(np.mean(out[0, scored] ** 2))

    # the cost has small steps (stick events that come or go with M): bracket on a grid first
    grid = np.linspace(0.5, 2.0, 16)
    c = [cost(M) for M in grid]
    i = int(np.argmin(c))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    return float(minimize_scalar(cost, bounds=(lo, hi), method="bounded",
                                 options={"xatol": 1e-3}).x)


def delay_errors(d: Dataset, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-valve minimisers of the one-sample pressure error, minus the truth [s]."""
    u = np.ascontiguousarray(d.u)
    sw = (u > 0.0) & (u < 1.0)
    act = sw.copy()
    act[1:] |= sw[:-1]
    act[2:] |= sw[:-2]
    grid = np.linspace(-1.5e-4, 1.5e-4, 13)
    found = []
    for which in (P_DON, P_DOFF):
        P = np.repeat(base[None, :], len(grid), axis=0)
        for g, dl in enumerate(grid):
            P[g, which:which + 4] += dl
            P[g, P_MINP:P_MINP + 4] = np.minimum(P[g, P_MINP:P_MINP + 4], P[g, P_DON:P_DON + 4])
        ra, rb = np.zeros((len(grid), d.n)), np.zeros((len(grid), d.n))
        pressure_residuals(P, np.zeros((0, 2)), d.t, d.x, d.p_a, d.p_b, d.p_s, u, ra, rb)
        est = np.empty(4)
        for i in range(4):
            c = np.mean((ra if i < 2 else rb)[:, act[:, i]] ** 2, axis=1)
            j = int(np.clip(np.argmin(c), 2, len(grid) - 3))
            a, b, _ = np.polyfit(grid[j - 2:j + 3], c[j - 2:j + 3], 2)
            est[i] = -b / (2.0 * a) if a > 0 else grid[j]
        found.append(est)
    return found[0], found[1]


def main() -> None:
    """Print the figures."""
    import tempfile
    from pathlib import Path

    t0 = time.perf_counter()
    plant = PlantConfig()
    quiet = plant.with_updates({"sensors": {"x_noise": 0.0, "x_step": 0.0, "p_noise": 0.0}})
    true = pack_plant(plant).vec
    M_true = plant.total_mass
    with tempfile.TemporaryDirectory() as tmp:
        logs = {}
        for name, cfg in (("noise-free", quiet), ("noisy (seed 1)", plant)):
            path = Path(tmp) / f"{name.split()[0]}.mcap"
            # at the control rate: this is the 4 ms experiment (the default logs at 0.5 ms)
            simulate_identification(cfg, seed=1, sample_period=cfg.rig.Ts).save(
                path, rig=cfg.rig_metadata(), run={"seed": "1"})
            logs[name] = load_dataset(path)
    print(f"default plant: M = {M_true} kg, b_v = {true[P_BV]:.0f} N s/m, "
          f"lag M/b_v = {M_true / true[P_BV] * 1e3:.2f} ms, Ts = {plant.rig.Ts * 1e3:g} ms")
    print("1. mass from position innovations, every other parameter true:")
    for name, d in logs.items():
        M = fit_mass(d, true)
        print(f"   {name:15s} M = {M:.3f} kg ({(M / M_true - 1) * 100:+.1f} %)")
    print("2. the same on the noisy log with all valve delays shifted:")
    d = logs["noisy (seed 1)"]
    for shift in (-2.0e-5, 2.0e-5):
        p = true.copy()
        p[P_DON:P_DON + 4] += shift
        p[P_DOFF:P_DOFF + 4] += shift
        M = fit_mass(d, p)
        print(f"   delays {shift * 1e6:+.0f} µs: M = {M:.3f} kg ({(M / M_true - 1) * 100:+.1f} %);"
              f" b_v x shift = {true[P_BV] * shift:+.3f} kg")
    print("3. valve delays from one-sample pressure predictions (true plant), error in µs:")
    for name, d in logs.items():
        on, off = delay_errors(d, true)
        cells = ", ".join(f"{v} {a * 1e6:+.0f}/{b * 1e6:+.0f}"
                          for v, a, b in zip(VALVES, on, off, strict=True))
        print(f"   {name:15s} on/off: {cells}")
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
