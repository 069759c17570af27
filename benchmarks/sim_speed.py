"""Plant simulation speed and numba compile times.

Prints:
* simulated seconds per wall second for a 20 s run of the default plant under a PWM pattern
  (a 1 Hz sinusoidal duty switching between modes 1 and 2), after warm-up, best of 5, one core;
* the numba compile time of the plant, cold (empty cache) and cached (second process).

Target: at least 1000x real time.

    .venv/bin/python benchmarks/sim_speed.py
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

PROBE = r"""
import time
t0 = time.perf_counter()
import numpy as np
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant.params import pack_plant
from pneutune.control.plant import dynamics as plant
t1 = time.perf_counter()
pp = pack_plant(PlantConfig())
s = plant.initial_state(pp.vec, 0.0235, 2.0e5, 2.0e5)
n = 10
plant.run_open_loop(pp.vec, s, np.full((n, 4), 0.3), np.full(n, 6.0e5), pp.force_steps,
                    np.zeros((n, 4)), 0.004, np.zeros((n, 4)), np.zeros((n, 6)))
t2 = time.perf_counter()
print(f"{t1 - t0:.3f} {t2 - t1:.3f}")
"""


def compile_times() -> tuple[float, float]:
    """(cold, cached) seconds from import to the first finished call, in fresh processes."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        out = []
        for _ in range(2):
            res = subprocess.run([sys.executable, "-c", PROBE], env=env, check=True,
                                 capture_output=True, text=True)
            _, first_call = (float(v) for v in res.stdout.split())
            out.append(first_call)
    return out[0], out[1]


def speed(duration: float = 20.0, repeats: int = 5) -> tuple[float, float]:
    """(simulated s per wall s, wall ms per 20 s run) of the plant under a PWM pattern."""
    from pneutune.control.contracts.plant import PlantConfig
    from pneutune.control.plant import dynamics as plant
    from pneutune.control.plant.params import pack_plant

    pp = pack_plant(PlantConfig())
    Ts = pp.config.rig.Ts
    n = round(duration / Ts)
    t = np.arange(n) * Ts
    u = 0.3 * np.sin(2.0 * np.pi * 1.0 * t)
    duties = np.zeros((n, 4))
    duties[:, 0] = duties[:, 3] = np.clip(u, 0.0, 1.0)
    duties[:, 1] = duties[:, 2] = np.clip(-u, 0.0, 1.0)
    p_s = np.full(n, pp.p_s)
    noise = np.random.default_rng(1).standard_normal((n, 4))
    sensors, truth = np.zeros((n, 4)), np.zeros((n, 6))
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    best = np.inf
    for _ in range(repeats + 1):  # the first run is the warm-up
        s = plant.initial_state(pp.vec, 0.0235, pa, pb)
        t0 = time.perf_counter()
        plant.run_open_loop(pp.vec, s, duties, p_s, pp.force_steps, noise, Ts, sensors, truth)
        best = min(best, time.perf_counter() - t0)
    return duration / best, best * 1e3


def main() -> None:
    """Print the figures."""
    ratio, wall_ms = speed()
    cold, cached = compile_times()
    print(f"plant, 20 s under a PWM pattern: {ratio:,.0f} simulated s per wall s "
          f"({wall_ms:.1f} ms wall; target >= 1000)")
    print(f"numba compile, cold cache: {cold:.2f} s; cached: {cached:.2f} s")


if __name__ == "__main__":
    main()
