"""What a run records, sample by sample, and how it becomes an MCAP run log (contract 1)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.constants import LOG_SCHEMA, VALVES, VERSION
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.logs.topics import AGE_RESOLUTION, topic_fields
from pneutune.control.logs.writer import RunLogWriter

SENSOR_FIELDS = topic_fields("/rig/sensors")
TRUTH_FIELDS = topic_fields("/sim/truth")
#: The named fields of /control/state; the last field, theta_hat, is a vector of 6.
CONTROL_STATE_FIELDS = topic_fields("/control/state")[:-1]


def plant_meta(plant: str | None) -> dict[str, str]:
    """The plant as ``run`` metadata: the path as given and its content hash (not the absolute
    path, so that the same plant gives the same log bytes wherever it lies)."""
    if plant is None:
        return {"plant": "<defaults>"}
    return {"plant": plant, "plant_sha256": sha256_file(plant)}


@dataclass
class Recording:
    """Per-sample arrays of one run, filled in place.

    Parameters
    ----------
    n : int
        Number of samples.
    Ts : float
        Sampling period [s]; sample k is at ``k * Ts``.
    truth, reference, control_state : bool
        Whether ``/sim/truth``, ``/control/reference`` and ``/control/state`` are recorded.

    Notes
    -----
    ``ages_`` holds each reading's age (the sample's time minus the time the rig says the
    channel was sampled, :meth:`sample_ages`); it is written as ``/rig/sensor_age`` only when
    some reading is not of its sample's instant, so a rig that samples every channel at once
    writes no such topic.
    """

    n: int
    Ts: float
    truth: bool = False
    reference: bool = False
    control_state: bool = False
    sensors_: np.ndarray = field(init=False)
    duties_: np.ndarray = field(init=False)
    ages_: np.ndarray = field(init=False)
    truth_: np.ndarray | None = field(init=False, default=None)
    reference_: np.ndarray | None = field(init=False, default=None)
    state_: np.ndarray | None = field(init=False, default=None)
    segments_: list[tuple[float, str, str, dict[str, Any]]] = field(init=False)
    events_: list[tuple[float, str, str, str]] = field(init=False)

    def __post_init__(self) -> None:
        self.sensors_ = np.full((self.n, 4), np.nan)
        self.duties_ = np.full((self.n, 4), np.nan)
        self.ages_ = np.zeros((self.n, 4))
        if self.truth:
            self.truth_ = np.full((self.n, len(TRUTH_FIELDS)), np.nan)
        if self.reference:
            self.reference_ = np.full((self.n, 3), np.nan)
        if self.control_state:
            self.state_ = np.full((self.n, len(CONTROL_STATE_FIELDS) + 6), np.nan)
        self.segments_ = []
        self.events_ = []

    @property
    def t(self) -> np.ndarray:
        """Sample times [s]."""
        return np.arange(self.n) * self.Ts

    def sample_ages(self, k: int, t: float, sample_times: np.ndarray | None) -> None:
        """Record sample ``k``'s reading ages from the rig's per-channel sample times.

        Parameters
        ----------
        k : int
            Sample index.
        t : float
            The sample's time on the rig's clock [s].
        sample_times : (4,) array or None
            When each channel of ``[x, p_a, p_b, p_s]`` was sampled, on the same clock [s]
            (``rig.sample_times()``); None (a rig that does not tell) leaves the ages at 0, and
            so does a NaN (a channel never delivered, which the supervisor faults on).
        """
        if sample_times is not None:
            age = t - np.asarray(sample_times, dtype=np.float64)
            self.ages_[k] = np.where(np.isfinite(age), age, 0.0)

    def segment(self, t: float, label: str, kind: str, params: Mapping[str, Any]) -> None:
        """Record the start of an experiment segment."""
        self.segments_.append((float(t), label, kind, dict(params)))

    def event(self, t: float, level: str, code: str, message: str) -> None:
        """Record a rig event (``info``, ``warning`` or ``error``)."""
        self.events_.append((float(t), level, code, message))

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` samples (a run that stopped early), and the segments that
        start within them."""
        self.n = n
        for name in ("sensors_", "duties_", "ages_", "truth_", "reference_", "state_"):
            arr = getattr(self, name)
            if arr is not None:
                setattr(self, name, arr[:n])
        end = (n - 0.5) * self.Ts  # segment starts lie on sample instants
        self.segments_ = [s for s in self.segments_ if s[0] < end]

    def save(self, path: str | os.PathLike[str], rig: Mapping[str, float | str],
             run: Mapping[str, str], *, indexed: bool = True, truth_every: int = 1,
             compression_level: int | None = None) -> None:
        """Write the run as an MCAP log (contract 1), atomically.

        Parameters
        ----------
        path : path-like
            Destination ``.mcap`` file.
        rig : mapping
            The ``rig`` metadata (every key of the rig block).
        run : mapping
            Extra ``run`` metadata (``seed``, ...); schema, created_by and version are added.
        indexed : bool, optional
            Index chunks and messages in the summary (:class:`RunLogWriter`'s ``indexed``).
            False makes a log of many small messages about half as large; viewers then read it
            linearly.
        truth_every : int, optional
            Write ``/sim/truth`` at every ``truth_every``-th sample only (samples 0, k, 2k,
            ...), e.g. at the control period of a run logged faster. Nothing else changes.
        compression_level : int, optional
            zstd level of the chunks (:class:`RunLogWriter`'s ``compression_level``).

        Raises
        ------
        ValueError
            ``truth_every`` is not a positive integer.
        """
        if isinstance(truth_every, bool) or not isinstance(truth_every, int) or truth_every < 1:
            raise ValueError(f"truth_every must be a positive integer, got {truth_every!r}")
        # sample_period: the logging period, which an identification run makes shorter than
        # the control period rig.Ts (identification_run.IDENT_SAMPLE_PERIOD)
        meta = {"schema": LOG_SCHEMA, "created_by": "pneutune", "version": VERSION,
                "sample_period": repr(float(self.Ts))}
        meta.update({k: str(v) for k, v in run.items()})
        t = self.t
        # Values are stored rounded far below any sensor's resolution (position to 1 nm,
        # pressure to 1 mPa, duty to 1e-9): shorter JSON, smaller logs, nothing lost.
        sensors = np.column_stack([np.round(self.sensors_[:, 0], 9),
                                   np.round(self.sensors_[:, 1:], 3)])
        duties = np.round(self.duties_, 9)
        with RunLogWriter(path, rig=rig, run=meta, indexed=indexed,
                          compression_level=compression_level) as w:
            for t_seg, label, kind, params in self.segments_:
                w.write("/experiment/segment", t_seg,
                        {"label": label, "kind": kind, "params": params})
            w.write_many("/rig/sensors", t, dict(zip(SENSOR_FIELDS, sensors.T, strict=True)))
            if self.ages_.size and np.abs(self.ages_).max() > AGE_RESOLUTION:
                w.write_many("/rig/sensor_age", t,
                             dict(zip(SENSOR_FIELDS, np.round(self.ages_, 9).T, strict=True)))
            w.write_many("/rig/valves", t,
                         {f"u_{v}": col for v, col in zip(VALVES, duties.T, strict=True)})
            if self.truth_ is not None:
                # v to 1 nm/s, a to 1 um/s^2, forces to 1 uN, mass flows to 1e-12 kg/s
                truth = np.column_stack([np.round(col, d) for col, d in
                                         zip(self.truth_[::truth_every].T, (9, 6, 6, 6, 12, 12),
                                             strict=True)])
                w.write_many("/sim/truth", t[::truth_every],
                             dict(zip(TRUTH_FIELDS, truth.T, strict=True)))
            if self.reference_ is not None:
                ok = np.isfinite(self.reference_[:, 0])
                w.write_many("/control/reference", t[ok],
                             dict(zip(("x_r", "v_r", "a_r"), self.reference_[ok].T, strict=True)))
            if self.state_ is not None:
                cols = {name: self.state_[:, i] for i, name in enumerate(CONTROL_STATE_FIELDS)}
                cols["theta_hat"] = self.state_[:, len(CONTROL_STATE_FIELDS):]
                w.write_many("/control/state", t, cols)
            for t_ev, level, code, message in self.events_:
                w.write("/rig/events", t_ev, {"level": level, "code": code, "message": message})
