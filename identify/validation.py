"""Validation: the identified model simulated on the held-out part of the log.

The held-out samples are cut into windows (default 2 s). Each window starts from the measured
state (position, velocity from the Savitzky-Golay estimate, both pressures) and is driven by
the logged duties through the full simulated rig (:mod:`pneutune.control.plant.dynamics`: valve
switching with the identified delays, Stribeck friction, end stops) built from the identified
model. NRMSE = rms(simulated - measured) / range(measured), per signal, over all windows: the
``fit`` block of model.yaml.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import S_STUCK, S_T, S_V, pack_plant

from .dataset import Dataset, IdentificationError


@dataclass(frozen=True)
class Validation:
    """Simulated vs measured signals on the held-out samples."""

    t: np.ndarray
    measured: np.ndarray  # (n, 3): x, p_a, p_b
    simulated: np.ndarray  # (n, 3)
    nrmse: dict[str, float]


def nrmse(sim: np.ndarray, meas: np.ndarray) -> float:
    """rms(sim - meas) / (max(meas) - min(meas)); 0 for a constant signal matched exactly."""
    span = float(np.ptp(meas))
    err = float(np.sqrt(np.mean((sim - meas) ** 2)))
    return err / span if span > 0 else err


def validate(data: Dataset, held_out: np.ndarray, plant_cfg: PlantConfig,
             window: float = 2.0) -> Validation:
    """Simulate ``plant_cfg`` on the held-out samples with the logged duties.

    Parameters
    ----------
    data : Dataset
        The log.
    held_out : ndarray of bool
        Samples to validate on (contiguous runs are cut into windows).
    plant_cfg : PlantConfig
        The identified model as a simulated rig (sensor noise off).
    window : float
        Window length [s].
    """
    pp = pack_plant(plant_cfg.with_updates(
        {"sensors": {"x_noise": 0.0, "x_step": 0.0, "p_noise": 0.0}}))
    p = pp.vec
    Ts = data.Ts
    w = max(2, round(window / Ts))
    idx = np.flatnonzero(held_out)
    if idx.size < 2:
        raise IdentificationError(data.path, f"only {idx.size} held-out samples: the log is too "
                                  f"short to validate the model on (--holdout)")
    pa_s = savgol_filter(data.p_a, 9, 2)
    pb_s = savgol_filter(data.p_b, 9, 2)
    ts, meas, sim = [], [], []
    # contiguous runs of held-out samples
    breaks = np.flatnonzero(np.diff(idx) > 1)
    runs = np.split(idx, breaks + 1)
    sensors = np.zeros(4)
    noise = np.zeros(4)
    for run in runs:
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
                meas.append((data.x[k], data.p_a[k], data.p_b[k]))
                ts.append(data.t[k])
                plant.set_duties(p, s, float(s[S_T]), data.u[k])
                plant.advance(p, s, float(data.t[k]) + Ts, float(data.p_s[k]), pp.force_steps)
    m = np.asarray(meas)
    si = np.asarray(sim)
    scores = {name: nrmse(si[:, i], m[:, i]) for i, name in enumerate(("x", "p_a", "p_b"))}
    return Validation(t=np.asarray(ts), measured=m, simulated=si, nrmse=scores)
