"""Convergence study of the integration step (docs/integration.md).

Closed loop on the simulated rig: the stroke-only position loop of the identification run
(``position_loop``, band 2.5 mm) tracks 17.5 sin(pi t) mm about mid-stroke for 10 s, with
sensor noise (seed 3, identical at every step size). Prints E_p and E_rms over the last three
periods for several ``sim.dt`` against a 10 us reference, for both PWM update modes.

    .venv/bin/python benchmarks/convergence.py
"""

from __future__ import annotations

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.rig.identification_run import position_loop
from pneutune.control.rig.simrig import SimRig
from pneutune.control.sim.scenarios import metric_window


def tracking_metrics(dt: float, mode: str = "immediate", duration: float = 10.0,
                     freq: float = 0.5) -> tuple[float, float]:
    """(E_p, E_rms) in mm over the last three periods at integration step ``dt``."""
    cfg = PlantConfig().with_updates({"sim": {"dt": dt}, "rig": {"pwm_update": mode}})
    rig = SimRig(cfg, seed=3)
    mid = 0.5 * (cfg.rig.x_min + cfg.rig.x_max)
    n = round(duration / rig.Ts)
    err = np.zeros(n)
    for k in range(n):
        x_r = mid + 0.0175 * np.sin(2.0 * np.pi * freq * k * rig.Ts)
        y = rig.read()
        err[k] = y[0] - x_r
        rig.write(position_loop(float(y[0]), x_r, 0.0025))
        rig.advance()
    last = err[-metric_window(1.0 / freq, rig.Ts):]
    return float(np.abs(last).max() * 1e3), float(np.sqrt(np.mean(last**2)) * 1e3)


def main() -> None:
    """Print the study."""
    for mode in ("immediate", "latched"):
        ref = tracking_metrics(1.0e-5, mode)
        print(f"pwm_update={mode}: reference dt=10 us: E_p={ref[0]:.4f} mm E_rms={ref[1]:.4f} mm")
        prev = None
        for dt in (1.6e-3, 8.0e-4, 4.0e-4, 2.0e-4, 1.0e-4, 5.0e-5):
            ep, erms = tracking_metrics(dt, mode)
            half = ""
            if prev is not None:
                half = (f"  |vs dt={prev[0] * 1e6:.0f} us: dE_p={abs(prev[1] - ep):.4f} "
                        f"dE_rms={abs(prev[2] - erms):.4f}")
            print(f"  dt={dt * 1e6:6.0f} us  E_p={ep:.4f}  E_rms={erms:.4f}  "
                  f"vs 10 us: dE_p={abs(ep - ref[0]):.4f} dE_rms={abs(erms - ref[1]):.4f}{half}")
            prev = (dt, ep, erms)


if __name__ == "__main__":
    main()
