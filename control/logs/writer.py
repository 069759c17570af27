"""Write an MCAP run log (contract 1, :mod:`pneutune.control.logs.topics`) atomically.

Layout
    zstd-compressed chunks; every CRC the format has (chunk, data section, summary); a summary
    with the schemas, channels, statistics and the metadata index. By default the summary also
    indexes every chunk and every message (what an MCAP viewer uses to seek). A message index
    costs 16 uncompressed bytes per message, more than a compressed sample of ``/rig/sensors``
    (about 10 bytes): ``indexed=False`` leaves the chunk and message indexes out, and viewers
    read the file linearly (Foxglove does so for any file without chunk indexes; the ``mcap``
    package's readers too). ``simulate --experiment`` writes its logs so (through
    :meth:`Recording.save <pneutune.control.logs.recording.Recording.save>`): without indexes
    data/run.mcap is about half the size (docs/architecture.md, "Run logs"). Chunk indexes
    alone (no message indexes) would cost next to nothing but are not an option: ``@mcap/core``'s
    indexed reader, which Foxglove uses whenever a file has chunk indexes, refuses a chunk index
    without message indexes.

Compression level
    The ``mcap`` package compresses chunks with ``zstandard.compress``, zstd's level 3, and
    has no setting. ``compression_level`` picks another level for one writer: each of the
    writer's calls into the package runs inside
    :func:`~pneutune.control.logs.compression.zstd_level`, which hands the package a
    ``zstandard`` that compresses at that level for the calling thread only, and gives it the
    module back when the call returns. The bytes stay standard zstd frames that every reader
    decompresses; level 19 makes data/run.mcap 20 % smaller and takes about five times as
    long to write.

Sequence numbers
    Every message's ``sequence`` is 0 (the MCAP spec's optional publisher counter; 0 is the
    ``mcap`` package's default). No publisher assigns one here, and a counter written here
    would only repeat the message's position in its topic, which the file order gives. It cost
    2 MB of the 13 MB of data/run.mcap: an incrementing binary field in every message header
    compresses badly.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import os
from collections.abc import Iterable, Mapping, Sequence
from types import TracebackType
from typing import Any

import numpy as np
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer

from pneutune.control.constants import (
    LOG_SCHEMA,
    PWM_UPDATE_MODES,
    RIG_HINT_KEYS,
    RIG_HINT_RANGES,
    RIG_KEYS,
    VERSION,
)
from pneutune.control.contracts.atomic import atomic_open
from pneutune.control.logs.compression import ZSTD_LEVELS, zstd_level
from pneutune.control.logs.mcap_json import encode_json
from pneutune.control.logs.topics import (
    EVENT_LEVELS,
    LEVEL,
    OBJECT,
    RIG_NUMBER_KEYS,
    TOPIC_SCHEMAS,
    VECTOR6,
    TopicSpec,
    format_ns,
    topic_spec,
)

__all__ = ["ZSTD_LEVELS", "RunLogWriter"]

_MAX_S = 9.2e9  # largest accepted time [s]: below 2**63 ns
#: The summary's indexes of an ``indexed=False`` log: no chunk or message indexes.
_UNINDEXED = IndexType.ATTACHMENT | IndexType.METADATA


class _JsonNull:
    """Formats as JSON ``null`` under ``%r`` (stands in for a non-finite float)."""

    def __repr__(self) -> str:
        return "null"


_NULL = _JsonNull()


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _seconds_to_ns(t: Any, what: str) -> int:
    if type(t) is not float:
        if not _is_real(t):
            raise TypeError(f"{what}: time must be a real number of seconds, got {t!r}")
        t = float(t)
    if not 0.0 <= t <= _MAX_S:  # also false for NaN
        raise ValueError(f"{what}: time must be finite and in [0, {_MAX_S:.0f}] s, got t={t!r}")
    return round(t * 1e9)


def _cell(topic: str, name: str, value: Any) -> float | _JsonNull:
    """A number of a single message as a Python float, or the ``null`` stand-in."""
    if type(value) is not float:
        if not _is_real(value):
            raise TypeError(f"{topic}.{name} must be a real number, got {value!r}")
        value = float(value)  # also turns numpy scalars into floats, whose repr is plain
    return value if math.isfinite(value) else _NULL


def _encode_rows(spec: TopicSpec, values: np.ndarray) -> list[bytes]:
    """Compact JSON messages of a numeric topic, one per row of ``values`` (N, width).

    All rows are formatted by one ``%`` on a joined template (numbers with ``repr(float)``,
    which round-trips exactly); non-finite numbers become ``null``.
    """
    n = values.shape[0]
    if n == 0:
        return []
    flat = values.ravel()
    cells: list[Any] = flat.tolist()
    for i in np.flatnonzero(~np.isfinite(flat)).tolist():
        cells[i] = _NULL
    text = "\n".join([spec.template] * n) % tuple(cells)
    return text.encode("ascii").split(b"\n")


def _rig_metadata(rig: Mapping[str, Any]) -> dict[str, str]:
    if not isinstance(rig, Mapping):
        raise TypeError(f"rig must be a mapping, got {type(rig).__name__}")
    missing = [k for k in RIG_KEYS if k not in rig]
    unknown = sorted(str(k) for k in rig if k not in RIG_KEYS and k not in RIG_HINT_KEYS)
    if missing or unknown:
        raise ValueError(
            "rig must hold exactly the keys of RIG_KEYS (and optionally RIG_HINT_KEYS)"
            + (f"; missing: {', '.join(missing)}" if missing else "")
            + (f"; unknown: {', '.join(unknown)}" if unknown else "")
        )
    out: dict[str, str] = {}
    for key in RIG_NUMBER_KEYS:
        value = rig[key]
        if not _is_real(value) or not math.isfinite(float(value)):
            raise ValueError(f"rig.{key} must be a finite number, got {value!r}")
        out[key] = repr(float(value))
    mode = rig["pwm_update"]
    if mode not in PWM_UPDATE_MODES:
        raise ValueError(f"rig.pwm_update must be one of {PWM_UPDATE_MODES}, got {mode!r}")
    out["pwm_update"] = str(mode)
    for key in RIG_HINT_KEYS:
        if key in rig:
            value = rig[key]
            lo, hi, unit = RIG_HINT_RANGES[key]
            if not _is_real(value) or not (math.isfinite(float(value))
                                           and lo <= float(value) <= hi):
                raise ValueError(f"rig.{key} must be a number of {unit} within "
                                 f"[{lo:g}, {hi:g}], got {value!r}")
            out[key] = repr(float(value))
    return out


def _run_metadata(run: Mapping[str, str]) -> dict[str, str]:
    if not isinstance(run, Mapping):
        raise TypeError(f"run must be a mapping, got {type(run).__name__}")
    for key, value in run.items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise TypeError(
                f"run metadata is a string map, got {key!r}: {value!r} "
                f"(write numbers such as the seed with str())"
            )
    out = dict(run)
    if out.setdefault("schema", LOG_SCHEMA) != LOG_SCHEMA:
        raise ValueError(f"run.schema must be {LOG_SCHEMA!r}, got {out['schema']!r}")
    out.setdefault("created_by", "pneutune")
    out.setdefault("version", VERSION)
    return out


class _Aborted(Exception):
    """Thrown into the atomic file's context to make it discard the temporary file."""


class RunLogWriter:
    """Write a run log (contract 1) atomically.

    The file is written to a temporary file beside ``path`` and renamed to ``path`` by
    :meth:`close`. Used as a context manager, an exception inside the ``with`` block discards
    the temporary file and leaves no file at ``path`` (an older file there stays untouched).

    Parameters
    ----------
    path : path-like
        Destination ``.mcap`` file. Its folder is created if needed.
    rig : Mapping[str, float | str]
        Exactly the keys of ``RIG_KEYS``: finite numbers in SI units, ``pwm_update`` one of
        ``PWM_UPDATE_MODES``. Stored as the ``rig`` metadata record, numbers as
        ``repr(float(value))``.
    run : Mapping[str, str]
        The ``run`` metadata record (string map). ``schema`` (``pneutune.log/1``),
        ``created_by`` (``pneutune``) and ``version`` (the package version) are added when
        absent; contract 1 expects ``seed`` for a simulated run.
    chunk_size : int, optional
        Uncompressed chunk size [bytes] at which a chunk is closed and compressed.
    indexed : bool, optional
        Index every chunk and message in the summary (default). False leaves these indexes
        out, which halves a log of many small messages; readers then read it linearly.
    compression_level : int, optional
        zstd level of the chunks, 1-22 (default: the ``mcap`` package's, 3).

    Raises
    ------
    ValueError
        ``rig`` lacks a key of ``RIG_KEYS``, has an unknown key or a non-finite number;
        ``run["schema"]`` is not ``pneutune.log/1``.
    TypeError
        A ``run`` key or value is not a string, or a ``rig`` value has the wrong type.

    Examples
    --------
    >>> with RunLogWriter("run.mcap", rig, {"seed": "1"}) as log:  # doctest: +SKIP
    ...     log.write_many("/rig/sensors", t, {"x": x, "p_a": p_a, "p_b": p_b, "p_s": p_s})
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        rig: Mapping[str, float | str],
        run: Mapping[str, str],
        *,
        chunk_size: int = 1024 * 1024,
        indexed: bool = True,
        compression_level: int | None = None,
    ) -> None:
        if compression_level is not None and compression_level not in ZSTD_LEVELS:
            raise ValueError(f"compression_level must be in 1..22, got {compression_level!r}")
        self._level = compression_level
        self.path = os.fspath(path)
        rig_md = _rig_metadata(rig)
        run_md = _run_metadata(run)
        self._channels: dict[str, int] = {}
        self._last_ns: dict[str, int] = {}
        self._counts: dict[str, int] = {}
        self._closed = False
        self._file_cm = atomic_open(self.path, "wb")
        fh = self._file_cm.__enter__()
        try:
            self._mcap = Writer(
                fh,
                chunk_size=chunk_size,
                compression=CompressionType.ZSTD,
                index_types=IndexType.ALL if indexed else _UNINDEXED,
                enable_crcs=True,
                enable_data_crcs=True,
            )
            self._mcap.start(profile="", library=f"pneutune/{VERSION}; {LIBRARY_IDENTIFIER}")
            self._mcap.add_metadata("rig", rig_md)
            self._mcap.add_metadata("run", run_md)
        except BaseException as exc:
            self._discard(exc)
            raise

    # -- context manager -------------------------------------------------------------------
    def __enter__(self) -> RunLogWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
        else:
            self._discard(exc)

    # -- writing ---------------------------------------------------------------------------
    @property
    def message_counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return dict(self._counts)

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self.path}: run log is closed")

    def _channel(self, spec: TopicSpec) -> int:
        cid = self._channels.get(spec.topic)
        if cid is None:
            schema = encode_json(TOPIC_SCHEMAS[spec.topic])
            sid = self._mcap.register_schema(spec.schema_name, "jsonschema", schema)
            cid = self._mcap.register_channel(spec.topic, "json", sid)
            self._channels[spec.topic] = cid
            self._last_ns[spec.topic] = 0
            self._counts[spec.topic] = 0
        return cid

    def _add(self, spec: TopicSpec, ns: Sequence[int], payloads: Sequence[bytes]) -> None:
        cid = self._channel(spec)
        add = self._mcap.add_message
        seq = self._counts[spec.topic]
        with zstd_level(self._level):
            for stamp, data in zip(ns, payloads, strict=True):
                add(cid, stamp, data, stamp, 0)
        if len(ns):
            self._last_ns[spec.topic] = int(ns[-1])
        self._counts[spec.topic] = seq + len(ns)

    def _check_fields(self, spec: TopicSpec, names: Iterable[str]) -> None:
        given = set(names)
        missing = [n for n in spec.names if n not in given]
        unknown = sorted(str(n) for n in given - set(spec.names))
        if missing or unknown:
            raise ValueError(
                f"{spec.topic} has fields {', '.join(spec.names)}"
                + (f"; missing: {', '.join(missing)}" if missing else "")
                + (f"; unknown: {', '.join(unknown)}" if unknown else "")
            )

    def write(self, topic: str, t: float, fields: Mapping[str, Any]) -> None:
        """Write one message.

        Parameters
        ----------
        topic : str
            A topic of contract 1 (:data:`TOPICS`).
        t : float
            Time since the start of the run [s], finite, >= 0, not before the topic's
            previous message. Stored as ``round(t * 1e9)`` ns.
        fields : Mapping[str, Any]
            Exactly the topic's fields: real numbers (NaN and infinities are written as
            ``null``), ``theta_hat`` a sequence of 6 numbers, strings, ``params`` a mapping
            of JSON values.

        Raises
        ------
        ValueError
            Unknown topic, missing or unknown field, bad time, time going backwards, bad
            ``level``, non-finite number inside ``params``.
        TypeError
            A field has the wrong type.
        """
        self._check_open()
        spec = topic_spec(topic)
        ns = _seconds_to_ns(t, topic)
        names = spec.names
        if len(fields) != len(names) or not all(n in fields for n in names):
            self._check_fields(spec, fields)
        if ns < self._last_ns.get(topic, 0):
            raise ValueError(
                f"{topic}: log time goes backwards: t={format_ns(ns)} after "
                f"{format_ns(self._last_ns[topic])}"
            )
        if spec.numeric:
            cells: list[float | _JsonNull] = []
            for f in spec.fields:
                value = fields[f.name]
                if f.kind == VECTOR6:
                    if isinstance(value, (str, bytes, Mapping)) or len(value) != 6:
                        raise TypeError(f"{topic}.{f.name} must hold 6 numbers, got {value!r}")
                    cells.extend(_cell(topic, f.name, item) for item in value)
                else:
                    cells.append(_cell(topic, f.name, value))
            payload = (spec.template % tuple(cells)).encode("ascii")
        else:
            message: dict[str, Any] = {}
            for f in spec.fields:
                value = fields[f.name]
                if f.kind == OBJECT:
                    if not isinstance(value, Mapping):
                        raise TypeError(f"{topic}.{f.name} must be a mapping, got {value!r}")
                    value = dict(value)
                elif not isinstance(value, str):
                    raise TypeError(f"{topic}.{f.name} must be a string, got {value!r}")
                elif f.kind == LEVEL and value not in EVENT_LEVELS:
                    raise ValueError(
                        f"{topic}.{f.name} must be one of {EVENT_LEVELS}, got {value!r}"
                    )
                message[f.name] = value
            try:
                payload = encode_json(message)
            except ValueError as exc:
                raise ValueError(f"{topic}: {exc} (params must be finite JSON values)") from exc
        cid = self._channels.get(topic) or self._channel(spec)
        with zstd_level(self._level):
            self._mcap.add_message(cid, ns, payload, ns, 0)
        self._counts[topic] += 1
        self._last_ns[topic] = ns

    def write_many(
        self, topic: str, t: np.ndarray, columns: Mapping[str, np.ndarray]
    ) -> None:
        """Write N messages of a numeric topic at once (the fast path for bulk data).

        Parameters
        ----------
        topic : str
            A topic whose fields are all numbers: ``/rig/sensors``, ``/rig/valves``,
            ``/control/reference``, ``/control/state``, ``/sim/truth``.
        t : numpy.ndarray
            Times since the start of the run [s], shape (N,), finite, >= 0, non-decreasing
            and not before the topic's previous message.
        columns : Mapping[str, numpy.ndarray]
            Exactly the topic's fields; each of shape (N,), ``theta_hat`` of shape (N, 6).
            Integer or float arrays; NaN and infinities are written as ``null``.

        Raises
        ------
        ValueError
            Unknown or non-numeric topic, missing or unknown field, wrong shape, bad or
            decreasing times.
        TypeError
            A column is not numeric.
        """
        self._check_open()
        spec = topic_spec(topic)
        if not spec.numeric:
            raise ValueError(f"{topic} has string fields; write its messages with write()")
        self._check_fields(spec, columns)
        t_arr = np.asarray(t)
        if t_arr.ndim != 1 or t_arr.dtype.kind not in "fiu":
            raise ValueError(
                f"{topic}: t must be a 1-D numeric array, got {t_arr.dtype} {t_arr.shape}"
            )
        n = t_arr.shape[0]
        t_arr = t_arr.astype(np.float64)
        if not np.all(np.isfinite(t_arr)) or (n and t_arr.min() < 0.0):
            raise ValueError(f"{topic}: times must be finite and >= 0 s")
        if n and t_arr.max() > _MAX_S:
            raise ValueError(f"{topic}: times must be <= {_MAX_S:.0f} s")
        ns = np.rint(t_arr * 1e9).astype(np.int64)
        back = np.flatnonzero(np.diff(ns) < 0)
        if back.size:
            i = int(back[0])
            raise ValueError(
                f"{topic}: log time goes backwards: t={format_ns(ns[i + 1])} after "
                f"{format_ns(ns[i])} (rows {i}, {i + 1})"
            )
        if n and ns[0] < self._last_ns.get(topic, 0):
            raise ValueError(
                f"{topic}: log time goes backwards: t={format_ns(ns[0])} after "
                f"{format_ns(self._last_ns[topic])} written before"
            )
        values = np.empty((n, spec.width), dtype=np.float64)
        col = 0
        for f in spec.fields:
            arr = np.asarray(columns[f.name])
            shape = (n, 6) if f.kind == VECTOR6 else (n,)
            if arr.shape != shape:
                raise ValueError(f"{topic}.{f.name} must have shape {shape}, got {arr.shape}")
            if arr.dtype.kind not in "fiu":
                raise TypeError(f"{topic}.{f.name} must be numeric, got dtype {arr.dtype}")
            if f.kind == VECTOR6:
                values[:, col : col + 6] = arr
                col += 6
            else:
                values[:, col] = arr
                col += 1
        if n:  # no channel for a topic without messages
            self._add(spec, ns.tolist(), _encode_rows(spec, values))

    # -- finishing -------------------------------------------------------------------------
    def close(self) -> None:
        """Finish the MCAP file (summary, footer) and move it to ``path`` atomically.

        Calling it again does nothing. If finishing fails, the temporary file is removed and
        the exception propagates.
        """
        if self._closed:
            return
        try:
            with zstd_level(self._level):
                self._mcap.finish()
        except BaseException as exc:
            self._discard(exc)
            raise
        self._closed = True
        self._file_cm.__exit__(None, None, None)

    def abort(self) -> None:
        """Discard the log: remove the temporary file; nothing appears at ``path``."""
        self._discard(_Aborted("run log aborted"))

    def _discard(self, exc: BaseException) -> None:
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(BaseException):
            self._file_cm.__exit__(type(exc), exc, exc.__traceback__)
