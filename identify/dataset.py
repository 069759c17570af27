"""A run log made ready for identification: data checks first, then aligned arrays.

:func:`load_dataset` reads an MCAP run log (contract 1), checks it (required topics and
metadata, finite values, monotonic time — by the reader; regular sampling, plausible units,
excitation — here) and returns a :class:`Dataset` of aligned per-sample arrays in SI units.
Nothing here uses ``/sim/truth`` or ``/experiment/segment``: a real rig's closed-loop log has
neither. The segment labels are kept only for :mod:`.coverage`: what a protocol run cut short
lacks (the notes), and whether it may enter the mass's lag estimate.

Several logs of one rig (``identify A.mcap B.mcap``) are loaded one by one
(:func:`load_datasets`, which checks that their ``rig`` blocks agree) and put side by side by
:func:`pool`: one :class:`Dataset` at a common sampling period, the logs separated by gaps that
no fit window can straddle (:class:`Pool`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from pneutune.control.constants import RIG_KEYS, VALVES
from pneutune.control.contracts.plant import RigConfig
from pneutune.control.errors import LogError, MissingTopicError, NonFiniteValueError
from pneutune.control.logs.reader import RunLog, read_run_log, run_stop_note
from pneutune.control.logs.topics import REQUIRED_TOPICS

from .run_record import run_record
from .sample_times import align_channels

#: Plausible absolute pressures [Pa]: about 0.5 to 12 bar (catches gauge pressures or bar).
P_MIN_PLAUSIBLE, P_MAX_PLAUSIBLE = 0.5e5, 12.0e5
#: How far outside the stroke a position reading may be before it is implausible [m].
X_MARGIN = 2.0e-3
#: :func:`regular_samples` fills runs of at most this many missing sensor samples, when the
#: missing and duplicated samples together are at most :data:`REPAIR_SHARE` of the log.
MAX_FILL, REPAIR_SHARE = 3, 0.01
#: The longest stretch without a ``/rig/valves`` message, in control periods (rig.Ts), that
#: :func:`check_valve_coverage` accepts (duties are written once per control period or more
#: often; the margin takes timing jitter).
VALVE_GAP = 1.5
#: A chamber pressure whose readings span less than this over a whole log in which a valve of
#: its chamber was commanded at least :data:`STUCK_DUTY` is stuck [Pa] (0.01 bar: a duty of
#: one half opens a valve for 8 ms a PWM period, which moves a chamber by tenths of a bar).
STUCK_SPAN, STUCK_DUTY = 1.0e3, 0.5
#: Chamber readings more than this above the highest supply reading [Pa], in more than
#: :data:`ABOVE_SUPPLY_SHARE` of the samples, show a wrong supply reading (a chamber fed
#: through the valves stays below the supply, but for compression by the load).
ABOVE_SUPPLY, ABOVE_SUPPLY_SHARE = 0.3e5, 0.01
#: The rig metadata's supply pressure and the supply reading may differ by this fraction of
#: the gauge supply before identify notes it (:func:`supply_note`).
SUPPLY_MISMATCH = 0.05
#: Period of the fit / held-out interleave [s] (Dataset.split): at least a 2 s validation
#: window held out in each.
HOLDOUT_BLOCK = 10.0
#: Savitzky-Golay order and window [s] for velocity estimates (11 samples at the paper's 4 ms).
SG_ORDER, SG_SPAN = 3, 0.044


class IdentificationError(LogError):
    """The log cannot support identification (implausible units, too little excitation)."""


class RigMismatchError(IdentificationError):
    """Two logs given to one ``identify`` come from different rigs (their ``rig`` blocks
    differ)."""


@dataclass(frozen=True)
class Dataset:
    """Aligned per-sample arrays of a run log, SI units.

    Attributes
    ----------
    path, sha256 : str
        The log and its content hash.
    rig : RigConfig
        The ``rig`` metadata, validated.
    t : ndarray (N,)
        Sample times [s], from the log's first sensor sample (log time minus that sample's).
    x, p_a, p_b, p_s : ndarray (N,)
        Sensors [m, Pa abs].
    u : ndarray (N, 4)
        Commanded duties of a_in, a_out, b_in, b_out, held from each sample to the next.
    v : ndarray (N,)
        Velocity [m/s] by a Savitzky-Golay derivative of x over :data:`SG_SPAN` (non-causal,
        no phase lag).
    sample_period : float
        Logging period [s]: the run metadata's ``sample_period``, else ``rig.Ts``. An
        identification run logs faster than its control period ``rig.Ts``.
    mass_hint : float or None
        The log's ``rig.mass`` hint [kg] (contract 1's optional rig key), if any.
    scenario : str
        The scenario the run record names (``deploy --log`` writes it), or "".
    segments : tuple of (float, str, str)
        ``/experiment/segment`` as (start time [s], label, kind), or () for a log without
        labels. Only :mod:`.coverage` reads them.
    experiment : str
        The excitation protocol the run record names (``record`` and ``simulate
        --experiment`` write it: ``identification`` or ``commissioning``), or "".
    run_status : str
        How the run ended, as its run record says (``record`` writes ``ok``, ``fault`` or
        ``interrupted``), or "".
    stopped_in : str
        The segment a fault or an interrupt stopped (``record`` writes it), or "".
    selection : str
        The ``record --segments`` selection the run was made of, or "" for a whole protocol.
    run_record : dict or None
        model.yaml's ``source.run`` of the log
        (:func:`~pneutune.identify.run_record.run_record`), or None (a pool of logs).
    repairs : str
        What was done to the sensor samples: the channels brought to their messages' times
        (:func:`~pneutune.identify.sample_times.align_channels`, where the log has
        ``/rig/sensor_age``) and the slips :func:`regular_samples` repaired (dropped
        duplicates, filled missing samples); "" when nothing was needed.
    stop_note : str
        What the run record says of a run that stopped early and what to do, "; ..."
        (:func:`~pneutune.control.logs.reader.run_stop_note`), or "".
    """

    path: str
    sha256: str
    rig: RigConfig
    t: np.ndarray
    x: np.ndarray
    p_a: np.ndarray
    p_b: np.ndarray
    p_s: np.ndarray
    u: np.ndarray
    v: np.ndarray
    sample_period: float = 0.0
    scenario: str = ""
    mass_hint: float | None = None
    segments: tuple[tuple[float, str, str], ...] = ()
    experiment: str = ""
    run_status: str = ""
    stopped_in: str = ""
    selection: str = ""
    run_record: dict[str, Any] | None = None
    repairs: str = ""
    stop_note: str = ""

    @property
    def n(self) -> int:
        """Number of samples."""
        return self.t.shape[0]

    @property
    def Ts(self) -> float:
        """Sampling period of these arrays [s] (``rig.Ts`` is the control period)."""
        return self.sample_period or self.rig.Ts

    def at_control_rate(self) -> Dataset:
        """The samples at the control instants when the log is sampled faster than ``rig.Ts``.

        The valve, PWM-curve and friction fits and the validation were built for samples at the
        control period, with the duties held from one sample to the next. A log sampled k times
        per control period whose duties change only on one phase of every k samples is cut
        down to those samples, exactly; any other log is returned as it is.

        Returns
        -------
        Dataset
        """
        k = round(self.rig.Ts / self.Ts)
        if k <= 1 or abs(k * self.Ts - self.rig.Ts) > 1e-6 * self.rig.Ts:
            return self
        changes = np.flatnonzero(np.any(np.diff(self.u, axis=0) != 0.0, axis=1)) + 1
        phases = np.unique(changes % k)
        if phases.size > 1:
            return self
        k0 = int(phases[0]) if phases.size else 0
        sl = slice(k0, None, k)
        x = self.x[sl]
        return Dataset(path=self.path, sha256=self.sha256, rig=self.rig, t=self.t[sl], x=x,
                       p_a=self.p_a[sl], p_b=self.p_b[sl], p_s=self.p_s[sl], u=self.u[sl],
                       v=_velocity(x, self.rig.Ts), sample_period=self.rig.Ts,
                       mass_hint=self.mass_hint, scenario=self.scenario,
                       segments=self.segments, experiment=self.experiment,
                       run_status=self.run_status, stopped_in=self.stopped_in,
                       selection=self.selection, run_record=self.run_record,
                       repairs=self.repairs, stop_note=self.stop_note)

    @property
    def duration(self) -> float:
        """Length of the log [s]."""
        return float(self.t[-1] - self.t[0]) + self.Ts if self.n else 0.0

    @property
    def F_p(self) -> np.ndarray:
        """Pressure force A_a p_a - A_b p_b - p0 A_r [N] (Eq. 8 with the p0 A_r correction)."""
        r = self.rig
        return r.A_a * self.p_a - r.A_b * self.p_b - r.p0 * (r.A_a - r.A_b)

    def volumes(self) -> tuple[np.ndarray, np.ndarray]:
        """Chamber volumes V_a, V_b of Eq. (6) [m^3]."""
        r = self.rig
        x = np.clip(self.x, r.x_min, r.x_max)
        return r.V0a + r.A_a * (x - r.x_min), r.V0b + r.A_b * (r.x_max - x)

    def split(self, holdout: float, block: float = HOLDOUT_BLOCK) -> tuple[np.ndarray, np.ndarray]:
        """Boolean masks (fit, held out): the last ``holdout`` of every ``block`` seconds.

        Interleaved, so that both parts see every kind of motion of the log: holding out the
        end of an identification run took its fastest ramps away from the friction fit, and
        F_C then came out 11 % low on one noise seed of the default plant (3 % interleaved).
        A log shorter than ``block`` holds out its last ``holdout`` fraction.

        Parameters
        ----------
        holdout : float
            Fraction held out, 0 < holdout < 1.
        block : float
            Period of the interleave [s].

        Returns
        -------
        (ndarray of bool, ndarray of bool)
            The fit and the held-out masks, complementary.
        """
        block = min(block, self.duration)
        phase = np.mod(self.t - self.t[0], block)
        held = phase >= block * (1.0 - holdout) - 0.5 * self.Ts
        return ~held, held


def _rig_from_log(log: RunLog) -> RigConfig:
    from pydantic import ValidationError

    from pneutune.control.contracts.yamlio import validation_error

    try:
        return RigConfig.model_validate(dict(log.rig))
    except ValidationError as exc:
        err = validation_error(log.path, exc, prefix="metadata rig")
        raise IdentificationError(log.path, f"{err.key}: {err.message}") from None


def sample_period(log: RunLog, rig: RigConfig) -> float:
    """The log's sampling period [s]: run metadata ``sample_period``, else ``rig.Ts``.

    Raises
    ------
    IdentificationError
        If ``sample_period`` is not a positive decimal of seconds at most ``rig.Ts``.
    """
    raw = log.run.get("sample_period")
    if raw is None:
        return rig.Ts
    try:
        h = float(raw)
    except ValueError:
        h = float("nan")
    if not (np.isfinite(h) and 0.0 < h <= rig.Ts * (1.0 + 1e-9)):
        raise IdentificationError(log.path, f"metadata run.sample_period is {raw!r}; expected "
                                  f"the logging period in seconds, a decimal in (0, rig.Ts = "
                                  f"{rig.Ts:g}]")
    return h


def _velocity(x: np.ndarray, h: float) -> np.ndarray:
    """Savitzky-Golay velocity over about SG_SPAN seconds of samples ``h`` apart."""
    win = max(SG_ORDER + 2, round(SG_SPAN / h) | 1)
    win = min(win, len(x) - (1 - len(x) % 2))
    return savgol_filter(x, win, SG_ORDER, deriv=1, delta=h)


def check_plausible(log: RunLog, sensors: pd.DataFrame, rig: RigConfig, period: float) -> None:
    """Unit and range checks that the reader does not do, on ``sensors`` (the log's
    ``/rig/sensors`` as :func:`regular_samples` repaired it) and the log's ``/rig/valves``.

    Raises
    ------
    IdentificationError
        Pressures outside about 0.5-12 bar absolute (gauge pressure or bar instead of Pa?),
        positions outside the stroke (mm instead of m?), duties outside 0..1, irregular
        sampling, sensors and valves not on the same samples, a chamber pressure that never
        moves although its valves open, chambers above the supply reading.
    """
    s = sensors
    v = log["/rig/valves"]
    name = log.path
    for col in ("p_a", "p_b", "p_s"):
        lo, hi = float(s[col].min()), float(s[col].max())
        if lo < P_MIN_PLAUSIBLE or hi > P_MAX_PLAUSIBLE:
            raise IdentificationError(
                name, f"/rig/sensors.{col} spans {lo:.6g}..{hi:.6g} Pa; expected absolute "
                f"pressures in Pa between {P_MIN_PLAUSIBLE:.3g} and {P_MAX_PLAUSIBLE:.3g} "
                f"(gauge pressures or bar instead of Pa absolute?)")
    xlo, xhi = float(s["x"].min()), float(s["x"].max())
    if xlo < rig.x_min - X_MARGIN or xhi > rig.x_max + X_MARGIN:
        raise IdentificationError(
            name, f"/rig/sensors.x spans {xlo:.6g}..{xhi:.6g} m, outside the stroke "
            f"[{rig.x_min}, {rig.x_max}] m of the rig metadata (mm instead of m?)")
    for col in v.columns:
        lo, hi = float(v[col].min()), float(v[col].max())
        if lo < -1e-9 or hi > 1.0 + 1e-9:
            raise IdentificationError(
                name, f"/rig/valves.{col} spans {lo:.6g}..{hi:.6g}; duties must be within 0..1")
    t = s.index.to_numpy()
    if len(t) < 100:
        raise IdentificationError(name, f"/rig/sensors has {len(t)} samples; identification "
                                  f"needs at least 100 (0.4 s at Ts = 4 ms), ideally a whole "
                                  f"identification run")
    dt = np.diff(t)
    if np.any(np.abs(dt - period) > 0.25 * period):
        k = int(np.argmax(np.abs(dt - period) > 0.25 * period))
        what = "rig.Ts" if period == rig.Ts else "run.sample_period"
        raise IdentificationError(
            name, f"/rig/sensors is not sampled every {what} = {period} s: samples at "
            f"t = {t[k]:.6f} s and {t[k + 1]:.6f} s are {dt[k]:.6g} s apart (gaps or a "
            f"different sampling period; identify fills runs of up to {MAX_FILL} missing "
            f"samples and drops duplicates when they are at most {REPAIR_SHARE:.0%} of the "
            "log: cut a longer gap out by splitting the log in two, which identify reads "
            "together)")
    check_valve_coverage(name, t, v.index.to_numpy(), rig.Ts)
    check_pressures_respond(name, s, v)


def check_pressures_respond(name: str, s: pd.DataFrame, v: pd.DataFrame) -> None:
    """The chamber readings move when their valves open, and stay below the supply reading.

    Raises
    ------
    IdentificationError
        A chamber pressure spans less than :data:`STUCK_SPAN` over the log although a valve
        of its chamber was commanded at :data:`STUCK_DUTY` or more (a stuck, disconnected or
        swapped-out sensor); or the chambers read more than :data:`ABOVE_SUPPLY` above the
        highest supply reading in more than :data:`ABOVE_SUPPLY_SHARE` of the samples.
    """
    for col, ch in (("p_a", "a"), ("p_b", "b")):
        p = s[col].to_numpy(dtype=float)
        span = float(p.max() - p.min())
        duty = float(max(v[f"u_{ch}_in"].max(), v[f"u_{ch}_out"].max()))
        if span < STUCK_SPAN and duty >= STUCK_DUTY:
            raise IdentificationError(
                name, f"/rig/sensors.{col} stays within {span:.3g} Pa of "
                f"{float(np.median(p)) / 1e5:.4g} bar over the whole log although chamber "
                f"{ch.upper()}'s valves are commanded up to duty {duty:.2g}: a stuck, "
                "disconnected or mislabelled pressure sensor")
    ps_max = float(s["p_s"].max())
    chamber = np.maximum(s["p_a"].to_numpy(dtype=float), s["p_b"].to_numpy(dtype=float))
    above = chamber > ps_max + ABOVE_SUPPLY
    if above.mean() > ABOVE_SUPPLY_SHARE:
        raise IdentificationError(
            name, f"the chambers read up to {chamber.max() / 1e5:.4g} bar, more than "
            f"{ABOVE_SUPPLY / 1e5:g} bar above the highest supply reading /rig/sensors.p_s "
            f"({ps_max / 1e5:.4g} bar) in {above.mean():.0%} of the samples; chambers fed "
            "through the valves stay below the supply, so the supply reading is wrong (a "
            "stuck or disconnected sensor, another signal, or gauge pressure)")


def supply_note(data: Dataset, name: str | None = None) -> str | None:
    """A note when the rig metadata's ``p_s`` and the supply reading disagree.

    The fits use the measured supply; model.yaml keeps ``rig.p_s`` from the metadata, which
    the controller and the tuner's simulations use. A gap of more than
    :data:`SUPPLY_MISMATCH` of the gauge supply is worth a look (gauge instead of absolute
    pressure in the metadata, or a regulator set since).

    Returns
    -------
    str or None
    """
    measured = float(np.median(data.p_s))
    rig = data.rig
    if abs(measured - rig.p_s) <= SUPPLY_MISMATCH * max(rig.p_s - rig.p0, 1.0):
        return None
    where = f" in {name}" if name else ""
    return (f"supply: the rig metadata gives p_s = {rig.p_s / 1e5:.4g} bar absolute but the "
            f"supply reading{where} has a median of {measured / 1e5:.4g} bar; the fits use the "
            f"reading, model.yaml keeps the metadata's p_s for the controller and the tuner "
            f"(gauge pressure in the metadata, or a regulator set since the log?)")


def check_valve_coverage(name: str, t_sensors: np.ndarray, t_valves: np.ndarray,
                         Ts: float) -> None:
    """The duties are known at every sensor sample: ``/rig/valves`` has a message at least
    once per control period from the first sensor sample to the last.

    Each sample takes the duties of the last valve message (zero-order hold), so valves
    logged every sample or every control period both work; a valve topic that stops early,
    starts late or skips control periods would hold stale commands there.

    Raises
    ------
    IdentificationError
        A stretch of more than :data:`VALVE_GAP` control periods without a valve message,
        naming where.
    """
    limit = VALVE_GAP * Ts
    start, end = float(t_sensors[0]), float(t_sensors[-1])
    k = np.searchsorted(t_valves, t_sensors + 1e-9, side="right") - 1
    since = np.where(k >= 0, t_valves[np.clip(k, 0, None)], start)
    age = t_sensors - since
    if not np.any(age > limit):
        return
    a = float(since[int(np.argmax(age > limit))])
    later = t_valves[t_valves > a + 1e-9]
    b = float(later[0]) if later.size and later[0] <= end else end
    raise IdentificationError(
        name, f"/rig/valves has no message from t = {a:.6f} s to {b:.6f} s ({b - a:.6g} s) "
        f"while /rig/sensors runs from {start:.6f} s to {end:.6f} s; the commanded duties "
        f"must be logged at least once per control period (rig.Ts = {Ts:g} s), or the "
        "commands there are unknown (a valve topic cut short, or logged only on change?)")


def regular_samples(s: pd.DataFrame, period: float) -> tuple[pd.DataFrame, str]:
    """``/rig/sensors`` with the few slips of a real logger repaired, and what was done.

    A sample logged twice (the next less than a quarter period later) keeps its later copy; a
    run of up to :data:`MAX_FILL` missing samples (a step of a whole number of periods) is
    filled by linear interpolation in time. Both are done only when the samples dropped and
    filled add up to at most :data:`REPAIR_SHARE` of the log, and every other step is within
    a quarter period of ``period``; otherwise ``s`` is returned as it is, for
    :func:`check_plausible` to refuse.

    Parameters
    ----------
    s : DataFrame
        ``/rig/sensors``, indexed by time [s].
    period : float
        The sampling period [s].

    Returns
    -------
    DataFrame, str
        The samples, and a note of the repairs ("" when none were needed or possible).
    """
    t = s.index.to_numpy()
    if t.size < 3:
        return s, ""
    dup = np.diff(t) < 0.25 * period
    if dup.any():
        kept = s.iloc[np.flatnonzero(np.r_[~dup, True])]
    else:
        kept = s
    tk = kept.index.to_numpy()
    dt = np.diff(tk)
    k = np.rint(dt / period)
    if np.any(k < 1) or np.any(np.abs(dt - k * period) > 0.25 * period):
        return s, ""
    missing = (k - 1).astype(int)
    n_dup, n_missing = int(dup.sum()), int(missing.sum())
    if (n_dup == 0 and n_missing == 0) or missing.max() > MAX_FILL \
            or n_dup + n_missing > REPAIR_SHARE * t.size:
        return s, ""
    # each step of k periods gives its start and k - 1 evenly spaced times after it
    j = np.arange(MAX_FILL + 1)[None, :]
    steps = tk[:-1, None] + dt[:, None] * (j / k[:, None])
    times = np.r_[steps[j < k[:, None]], tk[-1]]
    values = {c: np.interp(times, tk, kept[c].to_numpy(dtype=float)) for c in kept.columns}
    out = pd.DataFrame(values, index=pd.Index(times, name=s.index.name))
    gaps = np.flatnonzero(missing)
    said = []
    if n_missing:
        said.append(f"{n_missing} missing sample(s) in {gaps.size} gap(s) (the first after "
                    f"t = {tk[gaps[0]]:.6f} s) filled by linear interpolation")
    if n_dup:
        first = t[int(np.argmax(dup))]
        said.append(f"{n_dup} duplicated sample(s) dropped, the later copy kept (the first "
                    f"at t = {first:.6f} s)")
    return out, "sampling: /rig/sensors " + "; ".join(said) + " (a logger's slips; the fits " \
        "see the repaired samples)"


def _align(s: pd.DataFrame, v: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor times of ``s`` (``/rig/sensors``) and the duties of ``v`` (``/rig/valves``) in
    force at each sensor sample (zero-order hold)."""
    ts = s.index.to_numpy()
    tv = v.index.to_numpy()
    cols = [f"u_{n}" for n in VALVES]
    uv = v[cols].to_numpy(dtype=float)
    k = np.searchsorted(tv, ts + 1e-9, side="right") - 1
    u = np.where(k[:, None] >= 0, uv[np.clip(k, 0, None)], 0.0)
    return ts, s[["x", "p_a", "p_b", "p_s"]].to_numpy(dtype=float), u


def load_dataset(path: str | os.PathLike[str] | RunLog) -> Dataset:
    """Read and check a run log for identification.

    Parameters
    ----------
    path : path-like or RunLog
        The log's file, or the log as :func:`~pneutune.control.logs.reader.read_run_log`
        read it (then the required topics and their finite values are checked again here).

    Raises
    ------
    LogError
        Any bad-file case of contract 1 (typed, from the reader) or an
        :class:`IdentificationError` from the checks above.
    """
    log = path if isinstance(path, RunLog) else read_run_log(Path(path))
    if isinstance(path, RunLog):
        _check_read_log(log)
    path = log.path
    rig = _rig_from_log(log)
    h = sample_period(log, rig)
    try:
        sensors, aligned = align_channels(log["/rig/sensors"],
                                          log.topics.get("/rig/sensor_age"))
    except ValueError as exc:
        raise IdentificationError(path, str(exc)) from None
    sensors, repairs = regular_samples(sensors, h)
    repairs = "; ".join(n for n in (aligned, repairs) if n)
    check_plausible(log, sensors, rig, h)
    t, sens, u = _align(sensors, log["/rig/valves"])
    # times from the first sensor sample: a log stamped in Unix time (as MCAP recorders do)
    # would otherwise carry 1.7e9 s into the simulations, whose clocks then resolve only
    # 0.2 us (a no-op for a log that starts at 0)
    t0 = float(t[0])
    t = t - t0
    x = sens[:, 0]
    return Dataset(path=str(path), sha256=log.sha256, rig=rig, t=t, x=x, p_a=sens[:, 1],
                   p_b=sens[:, 2], p_s=sens[:, 3], u=u, v=_velocity(x, h), sample_period=h,
                   mass_hint=log.rig_hints.get("mass"),
                   scenario=str(log.run.get("scenario", "")), segments=_segments(log, t0),
                   experiment=str(log.run.get("experiment", "")),
                   run_status=str(log.run.get("status", "")),
                   stopped_in=str(log.run.get("stopped_in", "")),
                   selection=str(log.run.get("segments", "")), run_record=run_record(log),
                   repairs=repairs, stop_note=run_stop_note(log.run))


def _check_read_log(log: RunLog) -> None:
    """A log read elsewhere (maybe with ``allow_nonfinite``) holds what identification reads."""
    for topic in REQUIRED_TOPICS:
        if not log.has(topic):
            raise MissingTopicError(log.path, f"no messages on {topic}; identify needs "
                                    f"{' and '.join(REQUIRED_TOPICS)}")
        frame = log[topic].select_dtypes("number")
        bad = ~np.isfinite(frame.to_numpy(dtype=float))
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise NonFiniteValueError(log.path, f"{topic}: field {frame.columns[col]} is not "
                                      f"finite at log time {frame.index[row]:.6f} s")


def _segments(log: RunLog, t0: float = 0.0) -> tuple[tuple[float, str, str], ...]:
    """``/experiment/segment`` as (t - ``t0``, label, kind), or () when the log has none."""
    if not log.has("/experiment/segment"):
        return ()
    seg = log["/experiment/segment"]
    return tuple((float(t) - t0, str(label), str(kind)) for t, label, kind in
                 zip(seg.index.to_numpy(), seg["label"], seg["kind"], strict=True))


def check_same_rig(datasets: Sequence[Dataset]) -> None:
    """The logs of one identification must come from one rig: equal ``rig`` blocks.

    Every key of :data:`~pneutune.control.constants.RIG_KEYS` (geometry, supply, the control
    period ``Ts``, ``pwm_hz``, ``pwm_update``, ...) must agree, and so must a ``rig.mass`` hint
    that two logs both carry. The sampling period (run metadata ``sample_period``) may differ:
    an identification run logged every 0.5 ms and a closed-loop log at the 4 ms control rate of
    the same rig have the same ``rig.Ts``.

    Raises
    ------
    RigMismatchError
        Naming both files and the first key that differs.
    """
    if not datasets:
        return
    first = datasets[0]
    ref = first.rig.model_dump()
    for d in datasets[1:]:
        other = d.rig.model_dump()
        for key in RIG_KEYS:
            a, b = ref[key], other[key]
            same = (a == b if isinstance(a, str) or isinstance(b, str)
                    else math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=0.0))
            if not same:
                raise RigMismatchError(
                    d.path, f"rig.{key} is {b!r} but {first.path} has {a!r}; the logs of one "
                    f"identification must come from one rig (equal rig metadata)")
        if (first.mass_hint is not None and d.mass_hint is not None
                and not math.isclose(first.mass_hint, d.mass_hint, rel_tol=1e-9)):
            raise RigMismatchError(
                d.path, f"rig.mass is {d.mass_hint!r} but {first.path} has "
                f"{first.mass_hint!r}; the logs of one identification must come from one rig "
                f"with one moving mass")


def load_datasets(paths: Sequence[str | os.PathLike[str] | RunLog]) -> list[Dataset]:
    """Read and check several run logs of one rig (:func:`load_dataset`, :func:`check_same_rig`).

    Raises
    ------
    LogError
        A bad log (as :func:`load_dataset`), or logs of different rigs
        (:class:`RigMismatchError`).
    """
    out: list[Dataset] = []
    for p in paths:
        out.append(load_dataset(p))
        check_same_rig(out)
    return out


def display_names(paths: Sequence[str]) -> tuple[str, ...]:
    """Short names of the logs for notes and bases: the file names, or the paths as given
    where two logs share a file name."""
    names = [Path(p).name for p in paths]
    if len(set(names)) < len(names):
        return tuple(str(p) for p in paths)
    return tuple(names)


#: Samples either side of a junction of two pooled logs that no fit uses, as time [s]: longer
#: than the smoothing any fit applies across samples (the supply pressure's 37-sample
#: Savitzky-Golay window of the valve fit is 74 ms at 4 ms).
JUNCTION_MARGIN = 0.08
#: ... and at least this many samples.
JUNCTION_MARGIN_SAMPLES = 20


def true_runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Start and end (exclusive) of every run of True in ``flags``, in order.

    Parameters
    ----------
    flags : ndarray of bool
        The samples.

    Returns
    -------
    list of (int, int)
        Empty for none.
    """
    padded = np.concatenate([[0], np.asarray(flags, dtype=np.int8), [0]])
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist(), strict=True))


def carrier_block(Ts: float, pwm_hz: float, max_samples: int = 2000) -> int:
    """Fewest samples ``Ts`` apart that make a whole number of PWM periods (1 if none does
    within ``max_samples``, to 0.1 % of a period).

    Pooled logs start at multiples of it, so that the carrier phase of each log at its first
    sample is the one it had in its own log (the valve timing stage searches one phase for all).
    """
    for b in range(1, max_samples + 1):
        cycles = b * Ts * pwm_hz
        if abs(cycles - round(cycles)) < 1e-3 and round(cycles) >= 1:
            return b
    return 1


@dataclass(frozen=True)
class Pool:
    """Several logs of one rig side by side in one :class:`Dataset`.

    The logs' samples are concatenated at their common sampling period, each log starting at a
    multiple of :func:`carrier_block` samples after a gap of samples with every valve shut (at
    least a PWM period and the valve delays, so that each log's valves start closed, as in its
    own log). Samples within :data:`JUNCTION_MARGIN` of a junction and the gaps are left out of
    every fit (``valid``), so that no window, filter or valve state straddles two logs. With
    one log the pool is that log itself and ``valid`` is all True: nothing changes.

    Attributes
    ----------
    data : Dataset
        The pooled arrays. ``path`` names every pooled log; ``t`` runs on across the gaps.
    spans : tuple of (int, int)
        ``[start, stop)`` of each pooled log in ``data``.
    valid : ndarray of bool
        Samples a fit may use.
    names : tuple of str
        Short names of the pooled logs (:func:`display_names`), in ``spans`` order.
    parts : tuple of Dataset
        The pooled logs themselves, in ``spans`` order.
    """

    data: Dataset
    spans: tuple[tuple[int, int], ...]
    valid: np.ndarray
    names: tuple[str, ...]
    parts: tuple[Dataset, ...]

    def masks(self, holdout: float) -> tuple[np.ndarray, np.ndarray]:
        """Fit and held-out masks: :meth:`Dataset.split` of each log, so that every log has
        the end of each of its 10 s held out, and only ``valid`` samples."""
        fit = np.zeros(self.data.n, dtype=bool)
        held = np.zeros(self.data.n, dtype=bool)
        for d, (a, b) in zip(self.parts, self.spans, strict=True):
            f, h = d.split(holdout)
            fit[a:b], held[a:b] = f, h
        return fit & self.valid, held & self.valid

    def names_where(self, mask: np.ndarray) -> tuple[str, ...]:
        """The pooled logs with at least one True sample of ``mask``."""
        return tuple(name for name, (a, b) in zip(self.names, self.spans, strict=True)
                     if np.any(mask[a:b]))


def pool(datasets: Sequence[Dataset], names: Sequence[str] | None = None) -> Pool:
    """Put logs of one rig at one sampling period side by side (:class:`Pool`).

    Parameters
    ----------
    datasets : sequence of Dataset
        Logs with equal ``Ts`` and equal rigs (:func:`check_same_rig`).
    names : sequence of str, optional
        Their short names (default :func:`display_names` of their paths).

    Returns
    -------
    Pool

    Raises
    ------
    ValueError
        No dataset, or sampling periods that differ.
    """
    if not datasets:
        raise ValueError("pool() needs at least one dataset")
    names = tuple(names) if names is not None else display_names([d.path for d in datasets])
    if len(datasets) == 1:
        d = datasets[0]
        return Pool(d, ((0, d.n),), np.ones(d.n, dtype=bool), names, (d,))
    h = datasets[0].Ts
    if any(not math.isclose(d.Ts, h, rel_tol=1e-9) for d in datasets):
        raise ValueError(f"pool() needs one sampling period, got "
                         f"{sorted({d.Ts for d in datasets})}")
    rig = datasets[0].rig
    block = carrier_block(h, rig.pwm_hz)
    margin = max(JUNCTION_MARGIN_SAMPLES, math.ceil(JUNCTION_MARGIN / h))
    # valves shut for a PWM period plus the longest valve delay, and the margins
    min_gap = max(math.ceil((1.0 / rig.pwm_hz + 0.05) / h) + 1, 2)
    spans: list[tuple[int, int]] = []
    pieces: list[tuple[np.ndarray, ...]] = []
    valid: list[np.ndarray] = []
    k = 0
    for j, d in enumerate(datasets):
        if j > 0:
            start = -(-(k + min_gap) // block) * block
            g = start - k
            prev = datasets[j - 1]
            first = g // 2
            # the gap holds the last sample of the log before, then the first of the next: the
            # filters that run across it see no step
            rows = [np.r_[np.repeat(a[-1], first), np.repeat(b[0], g - first)]
                    for a, b in ((prev.x, d.x), (prev.p_a, d.p_a), (prev.p_b, d.p_b),
                                 (prev.p_s, d.p_s))]
            pieces.append((*rows, np.zeros((g, 4)), np.zeros(g)))
            valid.append(np.zeros(g, dtype=bool))
            k = start
        pieces.append((d.x, d.p_a, d.p_b, d.p_s, d.u, d.v))
        ok = np.ones(d.n, dtype=bool)
        if j > 0:
            ok[:margin] = False
        if j < len(datasets) - 1:
            ok[max(d.n - margin, 0):] = False
        valid.append(ok)
        spans.append((k, k + d.n))
        k += d.n
    cols = [np.concatenate([p[i] for p in pieces]) for i in range(6)]
    t0 = datasets[0].t[0]
    t = t0 + np.arange(k) * h
    data = Dataset(path=", ".join(d.path for d in datasets), sha256="", rig=rig, t=t,
                   x=cols[0], p_a=cols[1], p_b=cols[2], p_s=cols[3], u=cols[4], v=cols[5],
                   sample_period=h, scenario="",
                   mass_hint=next((d.mass_hint for d in datasets if d.mass_hint is not None),
                                  None))
    return Pool(data, tuple(spans), np.concatenate(valid), names, tuple(datasets))
