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
from pneutune.control.numba_cache import njit
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
    # contiguous runs of held-out samples, cut into windows of at most w samples
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts, lengths = [], []
    for run in np.split(idx, breaks + 1):
        for start in range(0, len(run) - 1, w):
            starts.append(run[start])
            lengths.append(min(w, len(run) - start))
    first = np.asarray(starts, dtype=np.int64)
    count = np.asarray(lengths, dtype=np.int64)
    ks = np.concatenate([np.arange(k0, k0 + n) for k0, n in zip(first, count, strict=True)])
    si = np.empty((ks.size, 3))
    _simulate_windows(p, pp.force_steps, first, count, _f64(data.x), _f64(pa_s), _f64(pb_s),
                      _f64(data.v), _f64(data.t), _f64(data.p_s), _f64(data.u), float(Ts), si)
    m = np.column_stack([data.x[ks], data.p_a[ks], data.p_b[ks]]).astype(np.float64)
    scores = {name: nrmse(si[:, i], m[:, i]) for i, name in enumerate(("x", "p_a", "p_b"))}
    return Validation(t=np.asarray(data.t[ks], dtype=np.float64), measured=m, simulated=si,
                      nrmse=scores)


def _f64(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous float64 array (no copy when it is one)."""
    return np.ascontiguousarray(a, dtype=np.float64)


@njit(cache=True)
def _simulate_windows(p: np.ndarray, force_steps: np.ndarray, first: np.ndarray,
                      count: np.ndarray, x: np.ndarray, pa: np.ndarray, pb: np.ndarray,
                      v: np.ndarray, t: np.ndarray, p_s: np.ndarray, u: np.ndarray, Ts: float,
                      out: np.ndarray) -> None:
    """The plant run through windows of the log: the sensors x, p_a, p_b at each sample.

    Window j covers samples ``first[j] .. first[j] + count[j] - 1``; it starts at rest from
    the log's position and (smoothed) pressures ``pa``, ``pb`` at its first sample, moving
    with the log's velocity when that is over 2 mm/s. At each sample the sensors are read
    (noise-free), then the logged duties are written and the plant advances one ``Ts``.
    ``out`` gets the rows of all windows in order.
    """
    noise = np.zeros(4)
    sensors = np.zeros(4)
    row = 0
    for j in range(first.shape[0]):
        k0 = first[j]
        s = plant.initial_state(p, x[k0], pa[k0], pb[k0], t[k0])
        if abs(v[k0]) > 2e-3:
            s[S_V] = v[k0]
            s[S_STUCK] = 0.0
        for k in range(k0, k0 + count[j]):
            plant.measure(p, s, p_s[k], noise, sensors)
            out[row, 0] = sensors[0]
            out[row, 1] = sensors[1]
            out[row, 2] = sensors[2]
            row += 1
            plant.set_duties(p, s, s[S_T], u[k])
            plant.advance(p, s, t[k] + Ts, p_s[k], force_steps)
