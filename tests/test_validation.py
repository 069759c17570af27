"""The validation's simulation (identify/validation.py): the compiled loop over the held-out
windows gives what the plant's functions give called one sample at a time from Python."""

from __future__ import annotations

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import S_STUCK, S_T, S_V, pack_plant
from pneutune.identify.dataset import Dataset
from pneutune.identify.validation import validate


def _log(cfg: PlantConfig, n: int = 1500) -> Dataset:
    """A log-shaped Dataset with rough signals (the simulation only starts from them)."""
    rig = cfg.rig
    rng = np.random.default_rng(3)
    t = 1.0 + np.arange(n) * rig.Ts
    x = rig.x_min + (rig.x_max - rig.x_min) * (0.5 + 0.4 * np.sin(np.arange(n) / 40.0))
    p_a = rng.uniform(rig.p0, rig.p_s, n)
    p_b = rng.uniform(rig.p0, rig.p_s, n)
    p_s = np.full(n, rig.p_s)
    u = np.repeat(rng.choice([0.0, 0.3, 0.7, 1.0], (n // 10 + 1, 4)), 10, axis=0)[:n]
    v = np.gradient(x, rig.Ts)
    return Dataset(path="synthetic", sha256="", rig=rig, t=t, x=x, p_a=p_a, p_b=p_b, p_s=p_s,
                   u=u, v=v)


def test_compiled_windows_are_the_plant_stepped_from_python():
    """Windows of the held-out runs (one shorter than a window, one cut into several), each
    started from the log: the same floats as stepping the plant sample by sample."""
    cfg = PlantConfig()
    data = _log(cfg)
    held = np.zeros(data.n, dtype=bool)
    held[100:130] = True
    held[400:1300] = True
    val = validate(data, held, cfg, window=1.0)

    from scipy.signal import savgol_filter

    pp = pack_plant(cfg.with_updates({"sensors": {"x_noise": 0.0, "x_step": 0.0,
                                                  "p_noise": 0.0}}))
    p = pp.vec
    pa_s, pb_s = savgol_filter(data.p_a, 9, 2), savgol_filter(data.p_b, 9, 2)
    w = round(1.0 / data.Ts)
    sim, sensors, noise = [], np.zeros(4), np.zeros(4)
    for run in (np.arange(100, 130), np.arange(400, 1300)):
        for start in range(0, len(run) - 1, w):
            ks = run[start:start + w]
            k0 = ks[0]
            s = plant.initial_state(p, float(data.x[k0]), float(pa_s[k0]), float(pb_s[k0]),
                                    t0=float(data.t[k0]))
            if abs(data.v[k0]) > 2e-3:
                s[S_V] = float(data.v[k0])
                s[S_STUCK] = 0.0
            for k in ks:
                plant.measure(p, s, float(data.p_s[k]), noise, sensors)
                sim.append(sensors[:3].copy())
                plant.set_duties(p, s, float(s[S_T]), data.u[k])
                plant.advance(p, s, float(data.t[k]) + data.Ts, float(data.p_s[k]),
                              pp.force_steps)
    ks = np.flatnonzero(held)
    assert np.array_equal(val.simulated, np.asarray(sim))
    assert np.array_equal(val.t, data.t[ks])
    assert np.array_equal(val.measured, np.column_stack([data.x[ks], data.p_a[ks],
                                                         data.p_b[ks]]))
    assert np.ptp(val.simulated[:, 0]) > 0.0  # the piston moved: the test sees the motion
