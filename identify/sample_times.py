"""Readings of channels sampled at different instants, brought to their messages' times.

A rig whose ADC is multiplexed, or whose fieldbus polls the transmitters in turn, delivers the
four readings of one ``/rig/sensors`` message from four instants. Identification reads the
force-motion lag (a fraction of a millisecond carries the mass) and the valves' response times
from these signals, so a skew of a fraction of a sample between the position and the pressures
biases what it reads: a position sampled 0.25 ms before the pressures looks like 0.9 kg more
mass on a rig whose b_v is 3500 N s/m. Where the log says when each channel was sampled
(``/rig/sensor_age``, written by ``record`` and ``deploy --log`` from the driver's per-channel
sample times), each channel is interpolated, linearly in time between its own samples, to the
messages' times. A channel whose reading is held over several messages (its sample time does
not move) is interpolated between the samples it did take.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pneutune.control.logs.topics import AGE_RESOLUTION, topic_fields

__all__ = ["align_channels"]

#: The channels, as ``/rig/sensors`` and ``/rig/sensor_age`` name them.
_CHANNELS: tuple[str, ...] = topic_fields("/rig/sensor_age")


def _ages_at(sensors: pd.DataFrame, ages: pd.DataFrame) -> np.ndarray:
    """The ages of ``ages`` at each row of ``sensors`` (matched on log time; 0 where a sensor
    message has no age message at its time)."""
    ts = sensors.index.to_numpy()
    ta = ages.index.to_numpy()
    values = ages[list(_CHANNELS)].to_numpy(dtype=float)
    if ts.shape == ta.shape and np.array_equal(ts, ta):
        return values
    out = np.zeros((ts.size, len(_CHANNELS)))
    k = np.clip(np.searchsorted(ta, ts), 0, max(ta.size - 1, 0))
    if ta.size:
        hit = np.abs(ta[k] - ts) <= 0.5e-9  # the same nanosecond log time
        out[hit] = values[k[hit]]
    return out


def align_channels(sensors: pd.DataFrame, ages: pd.DataFrame | None) -> tuple[pd.DataFrame, str]:
    """``sensors`` with every channel interpolated to its messages' times, and a note.

    Parameters
    ----------
    sensors : DataFrame
        ``/rig/sensors``, indexed by log time [s].
    ages : DataFrame or None
        ``/rig/sensor_age`` (each reading's age at its message's time [s]); None when the log
        has none, and then ``sensors`` is returned as it is.

    Returns
    -------
    DataFrame, str
        The aligned readings (same index and columns) and a note of the shift applied to each
        channel ("" when every age is within the clock's rounding,
        :data:`~pneutune.control.logs.topics.AGE_RESOLUTION`).

    Raises
    ------
    ValueError
        A negative age (a reading sampled after its message's time), naming the field and
        the log time.
    """
    if ages is None or sensors.shape[0] < 2:
        return sensors, ""
    t = sensors.index.to_numpy(dtype=float)
    age = _ages_at(sensors, ages)
    bad = age < -AGE_RESOLUTION
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise ValueError(f"/rig/sensor_age.{_CHANNELS[col]} is {age[row, col]:.6g} s at log "
                         f"time {t[row]:.6f} s; an age is the message's time minus the time the "
                         "channel was sampled, never negative (a reading cannot be sampled after "
                         "its message)")
    out = sensors.copy()
    said = []
    for j, col in enumerate(_CHANNELS):
        a = age[:, j]
        if not np.any(np.abs(a) > AGE_RESOLUTION):
            continue
        tau = t - a
        values = sensors[col].to_numpy(dtype=float)
        # one point per sample the channel took: a held reading repeats its sample time
        order = np.argsort(tau, kind="stable")
        tau_s, val_s = tau[order], values[order]
        fresh = np.r_[True, np.diff(tau_s) > AGE_RESOLUTION]
        out[col] = np.interp(t, tau_s[fresh], val_s[fresh])
        said.append(f"{col} {np.median(a) * 1e3:.3g} ms")
    if not said:
        return sensors, ""
    return out, ("sample times: /rig/sensor_age puts the readings behind their messages' times "
                 f"by (median) {', '.join(said)}; each such channel is interpolated to the "
                 "messages' times")
