"""MCAP run log, contract 1 (``pneutune.log/1``): writer and reader.

One run per file. Every topic of the contract is one MCAP channel with message encoding ``json``
and a JSON Schema (schema encoding ``jsonschema``, :data:`TOPIC_SCHEMAS`), so that Foxglove and
any other MCAP reader can open the file. Chunks are zstd-compressed. Two metadata records (string
maps) describe the run: ``rig`` holds every key of :data:`~pneutune.control.constants.RIG_KEYS`
(numbers as decimal strings written with ``repr(float)``, so they read back bit for bit) and
``run`` holds ``schema`` (``pneutune.log/1``), ``created_by``, ``version`` and, for a simulated
run, ``seed``.

Times
    A message's log time is integer nanoseconds since the start of the run,
    ``round(t * 1e9)`` of the time ``t`` [s] given to the writer (rounded to nearest, not
    truncated); publish time equals log time. The reader's index is ``log_time / 1e9`` [s]
    (float64), so a time round-trips to within 0.5 ns. Within one topic, times never decrease
    in file order: the writer refuses such a message and the reader raises
    :class:`~pneutune.control.errors.TimeOrderError`.

Non-finite numbers
    JSON has no NaN or infinity. The writer stores a NaN, ``+inf`` or ``-inf`` as ``null``
    (so a diverged simulation can still be logged and inspected); the JSON Schemas say so in
    their descriptions. The reader rejects ``null`` (and the non-standard tokens ``NaN`` and
    ``Infinity`` written by other tools, and numbers that overflow to infinity) with
    :class:`~pneutune.control.errors.NonFiniteValueError` naming topic, field and log time,
    unless ``allow_nonfinite=True``, in which case they read as NaN.

Strictness
    The reader takes the contract's topics and rejects a message of such a topic that lacks a
    field, carries a field the schema does not know, or holds a value of the wrong type
    (:class:`LogSchemaError`). Topics outside the contract (a rig logger may record more) are
    not decoded; their names are listed in :attr:`RunLog.ignored_topics`. A ``rig`` record with
    a key outside ``RIG_KEYS`` and the optional hints ``RIG_HINT_KEYS`` (``mass``, a positive
    decimal, read into :attr:`RunLog.rig_hints`) is rejected; the ``run`` record may carry
    further keys.

Integrity
    The writer enables every CRC the format has (chunk, data section, summary). The reader scans
    the whole file linearly and checks all of them, the record structure, the trailing magic
    and the statistics record, so a file that was cut short or damaged raises
    :class:`~pneutune.control.errors.TruncatedLogError` rather than yielding partial data; no
    exception of the ``mcap``, ``zstandard`` or ``struct`` modules escapes.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import itertools
import math
import numbers
import os
import re
import struct
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import pandas as pd
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Metadata, Schema, Statistics
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from pneutune.control import __version__
from pneutune.control.constants import LOG_SCHEMA, PWM_UPDATE_MODES, RIG_HINT_KEYS, RIG_KEYS
from pneutune.control.contracts.atomic import atomic_open
from pneutune.control.errors import (
    EmptyLogError,
    LogError,
    LogSchemaError,
    MissingMetadataError,
    MissingTopicError,
    NonFiniteValueError,
    NotMcapError,
    TimeOrderError,
    TruncatedLogError,
)
from pneutune.control.logs.mcap_json import JsonDecoderFactory, decode_json, encode_json

__all__ = [
    "MCAP_MAGIC",
    "REQUIRED_TOPICS",
    "TOPICS",
    "TOPIC_SCHEMAS",
    "LogSchemaError",
    "RunLog",
    "RunLogWriter",
    "read_run_log",
]


#: The 8-byte magic that starts and ends every MCAP file.
MCAP_MAGIC: bytes = b"\x89MCAP0\r\n"
#: Topics that every run log must contain (contract 1).
REQUIRED_TOPICS: tuple[str, ...] = ("/rig/sensors", "/rig/valves")
#: Values of ``/rig/events`` field ``level``.
EVENT_LEVELS: tuple[str, ...] = ("info", "warning", "error")

_NUMBER, _VECTOR6, _STRING, _LEVEL, _OBJECT = "number", "vector6", "string", "level", "object"
_NULL_NOTE = " JSON has no NaN or infinity: a non-finite value is written as null."


@dataclass(frozen=True)
class _Field:
    name: str
    kind: str
    description: str


@dataclass(frozen=True)
class _Topic:
    """One topic of contract 1: its fields, schema and JSON row template."""

    topic: str
    schema_name: str
    description: str
    fields: tuple[_Field, ...]

    @cached_property
    def numeric(self) -> bool:
        """True if every field is a number or a vector of numbers (``write_many`` applies)."""
        return all(f.kind in (_NUMBER, _VECTOR6) for f in self.fields)

    @cached_property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @cached_property
    def width(self) -> int:
        """Numbers per message of a numeric topic."""
        return sum(6 if f.kind == _VECTOR6 else 1 for f in self.fields)

    @cached_property
    def columns(self) -> tuple[str, ...]:
        """DataFrame columns: fields, with a vector expanded to ``name_0`` .. ``name_5``."""
        out: list[str] = []
        for f in self.fields:
            out.extend([f"{f.name}_{k}" for k in range(6)] if f.kind == _VECTOR6 else [f.name])
        return tuple(out)

    @cached_property
    def template(self) -> str:
        """%-format template of one compact JSON message; one ``%r`` per number."""
        parts = []
        for f in self.fields:
            value = "[" + ",".join(["%r"] * 6) + "]" if f.kind == _VECTOR6 else "%r"
            parts.append(f'"{f.name}":{value}')
        return "{" + ",".join(parts) + "}"

    def json_schema(self) -> dict[str, Any]:
        props: dict[str, Any] = {}
        for f in self.fields:
            if f.kind == _NUMBER:
                props[f.name] = {"type": "number", "description": f.description + _NULL_NOTE}
            elif f.kind == _VECTOR6:
                props[f.name] = {
                    "type": "array",
                    "items": {"type": "number"},
                    "minItems": 6,
                    "maxItems": 6,
                    "description": f.description + _NULL_NOTE,
                }
            elif f.kind == _LEVEL:
                props[f.name] = {
                    "type": "string",
                    "enum": list(EVENT_LEVELS),
                    "description": f.description,
                }
            elif f.kind == _OBJECT:
                props[f.name] = {"type": "object", "description": f.description}
            else:
                props[f.name] = {"type": "string", "description": f.description}
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": f"{LOG_SCHEMA} {self.topic}",
            "description": self.description,
            "type": "object",
            "properties": props,
            "required": list(self.names),
            "additionalProperties": False,
        }


def _num(name: str, description: str) -> _Field:
    return _Field(name, _NUMBER, description)


_SPECS: tuple[_Topic, ...] = (
    _Topic(
        "/rig/sensors",
        "pneutune.log.RigSensors",
        "Measured signals, one message per sample.",
        (
            _num("x", "Piston position [m]; x = 0 lies 1.5 mm from the rodless end."),
            _num("p_a", "Pressure in chamber A (rodless side) [Pa, absolute]."),
            _num("p_b", "Pressure in chamber B (rod side) [Pa, absolute]."),
            _num("p_s", "Supply pressure [Pa, absolute]."),
        ),
    ),
    _Topic(
        "/rig/valves",
        "pneutune.log.RigValves",
        "Commanded PWM duty of the four on/off valves, one message per sample.",
        (
            _num("u_a_in", "Commanded duty of valve a_in (charge A), 0..1 [1]."),
            _num("u_a_out", "Commanded duty of valve a_out (exhaust A), 0..1 [1]."),
            _num("u_b_in", "Commanded duty of valve b_in (charge B), 0..1 [1]."),
            _num("u_b_out", "Commanded duty of valve b_out (exhaust B), 0..1 [1]."),
        ),
    ),
    _Topic(
        "/control/reference",
        "pneutune.log.ControlReference",
        "Reference trajectory of a closed-loop run, one message per control step.",
        (
            _num("x_r", "Reference position [m]."),
            _num("v_r", "Reference velocity [m/s]."),
            _num("a_r", "Reference acceleration [m/s^2]."),
        ),
    ),
    _Topic(
        "/control/state",
        "pneutune.log.ControlState",
        "Internal state of the controller (DARC notation of Qian et al. 2014), one message "
        "per control step.",
        (
            _num("e1", "Position tracking error e1 = x - x_r [m]."),
            _num("e2", "Sliding error e2 = de1/dt + k1 e1 [m/s]."),
            _num("e3", "Force error e3 = F_p - F_pd [N]."),
            _num("x_hat", "Estimated position [m]."),
            _num("v_hat", "Estimated velocity [m/s]."),
            _num("a_hat", "Estimated acceleration [m/s^2]."),
            _num("F_pd", "Desired pneumatic force F_pd (Eq. 17) [N]."),
            _num("dF_pd", "Estimated time derivative of F_pd [N/s]."),
            _num("Q_Ld", "Desired load flow Q_Ld (Eq. 26) [N/s]."),
            _Field(
                "theta_hat",
                _VECTOR6,
                "Parameter estimate theta_hat = [M kg, F_n N, b_v N s/m, A_f N, D_an Pa/s, "
                "D_bn Pa/s] (paper Sec. 2.3 order).",
            ),
        ),
    ),
    _Topic(
        "/experiment/segment",
        "pneutune.log.ExperimentSegment",
        "Start of a segment of an experiment protocol, one message per segment.",
        (
            _Field("label", _STRING, "Segment name, unique within the run."),
            _Field("kind", _STRING, "Segment type (e.g. chirp, step, hold)."),
            _Field("params", _OBJECT, "Segment parameters, SI units."),
        ),
    ),
    _Topic(
        "/rig/events",
        "pneutune.log.RigEvents",
        "Something happened (limit hit, sensor timeout, supervisor action).",
        (
            _Field("level", _LEVEL, "Severity."),
            _Field("code", _STRING, "Machine-readable event code."),
            _Field("message", _STRING, "Human-readable description."),
        ),
    ),
    _Topic(
        "/sim/truth",
        "pneutune.log.SimTruth",
        "True plant signals of a simulated run, one message per sample.",
        (
            _num("v", "Piston velocity [m/s]."),
            _num("a", "Piston acceleration [m/s^2]."),
            _num("F_friction", "Friction force F_f of Eq. (1) [N]."),
            _num("F_ext", "External force on the piston [N]."),
            _num("mdot_a", "Net mass flow into chamber A [kg/s]."),
            _num("mdot_b", "Net mass flow into chamber B [kg/s]."),
        ),
    ),
)
_SPEC: dict[str, _Topic] = {s.topic: s for s in _SPECS}
#: The topics of contract 1, in the order of the contract.
TOPICS: tuple[str, ...] = tuple(_SPEC)
#: JSON Schema (draft 2020-12) of every topic of contract 1; stored in the file's schema records.
TOPIC_SCHEMAS: dict[str, dict[str, Any]] = {s.topic: s.json_schema() for s in _SPECS}

_RIG_NUMBER_KEYS = tuple(k for k in RIG_KEYS if k != "pwm_update")
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NS_PER_S = 1_000_000_000
_MAX_NS = 2**63 - 1
_MAX_S = 9.2e9  # largest accepted time [s]: below 2**63 ns


class _JsonNull:
    """Formats as JSON ``null`` under ``%r`` (stands in for a non-finite float)."""

    def __repr__(self) -> str:
        return "null"


_NULL = _JsonNull()


def _fmt_ns(ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond time, e.g. ``1.004000000 s``."""
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    q, r = divmod(abs(ns), _NS_PER_S)
    return f"{sign}{q}.{r:09d} s"


def _spec(topic: str) -> _Topic:
    try:
        return _SPEC[topic]
    except KeyError:
        raise ValueError(f"unknown topic {topic!r}; contract 1 has {', '.join(TOPICS)}") from None


def topic_fields(topic: str) -> tuple[str, ...]:
    """The field names of a contract-1 topic, in order (a vector field is one name).

    Raises
    ------
    ValueError
        A topic outside contract 1.
    """
    return _spec(topic).names


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


def _encode_rows(spec: _Topic, values: np.ndarray) -> list[bytes]:
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
    for key in _RIG_NUMBER_KEYS:
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
            if not _is_real(value) or not (math.isfinite(float(value)) and float(value) > 0):
                raise ValueError(f"rig.{key} must be a positive finite number, got {value!r}")
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
    out.setdefault("version", __version__)
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
    ) -> None:
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
                enable_crcs=True,
                enable_data_crcs=True,
            )
            self._mcap.start(profile="", library=f"pneutune/{__version__}; {LIBRARY_IDENTIFIER}")
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

    def _channel(self, spec: _Topic) -> int:
        cid = self._channels.get(spec.topic)
        if cid is None:
            schema = encode_json(TOPIC_SCHEMAS[spec.topic])
            sid = self._mcap.register_schema(spec.schema_name, "jsonschema", schema)
            cid = self._mcap.register_channel(spec.topic, "json", sid)
            self._channels[spec.topic] = cid
            self._last_ns[spec.topic] = 0
            self._counts[spec.topic] = 0
        return cid

    def _add(self, spec: _Topic, ns: Sequence[int], payloads: Sequence[bytes]) -> None:
        cid = self._channel(spec)
        add = self._mcap.add_message
        seq = self._counts[spec.topic]
        for k, (stamp, data) in enumerate(zip(ns, payloads, strict=True)):
            add(cid, stamp, data, stamp, (seq + k) & 0xFFFFFFFF)
        if len(ns):
            self._last_ns[spec.topic] = int(ns[-1])
        self._counts[spec.topic] = seq + len(ns)

    def _check_fields(self, spec: _Topic, names: Iterable[str]) -> None:
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
        spec = _spec(topic)
        ns = _seconds_to_ns(t, topic)
        names = spec.names
        if len(fields) != len(names) or not all(n in fields for n in names):
            self._check_fields(spec, fields)
        if ns < self._last_ns.get(topic, 0):
            raise ValueError(
                f"{topic}: log time goes backwards: t={_fmt_ns(ns)} after "
                f"{_fmt_ns(self._last_ns[topic])}"
            )
        if spec.numeric:
            cells: list[float | _JsonNull] = []
            for f in spec.fields:
                value = fields[f.name]
                if f.kind == _VECTOR6:
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
                if f.kind == _OBJECT:
                    if not isinstance(value, Mapping):
                        raise TypeError(f"{topic}.{f.name} must be a mapping, got {value!r}")
                    value = dict(value)
                elif not isinstance(value, str):
                    raise TypeError(f"{topic}.{f.name} must be a string, got {value!r}")
                elif f.kind == _LEVEL and value not in EVENT_LEVELS:
                    raise ValueError(
                        f"{topic}.{f.name} must be one of {EVENT_LEVELS}, got {value!r}"
                    )
                message[f.name] = value
            try:
                payload = encode_json(message)
            except ValueError as exc:
                raise ValueError(f"{topic}: {exc} (params must be finite JSON values)") from exc
        cid = self._channels.get(topic) or self._channel(spec)
        seq = self._counts[topic]
        self._mcap.add_message(cid, ns, payload, ns, seq & 0xFFFFFFFF)
        self._counts[topic] = seq + 1
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
        spec = _spec(topic)
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
                f"{topic}: log time goes backwards: t={_fmt_ns(ns[i + 1])} after "
                f"{_fmt_ns(ns[i])} (rows {i}, {i + 1})"
            )
        if n and ns[0] < self._last_ns.get(topic, 0):
            raise ValueError(
                f"{topic}: log time goes backwards: t={_fmt_ns(ns[0])} after "
                f"{_fmt_ns(self._last_ns[topic])} written before"
            )
        values = np.empty((n, spec.width), dtype=np.float64)
        col = 0
        for f in spec.fields:
            arr = np.asarray(columns[f.name])
            shape = (n, 6) if f.kind == _VECTOR6 else (n,)
            if arr.shape != shape:
                raise ValueError(f"{topic}.{f.name} must have shape {shape}, got {arr.shape}")
            if arr.dtype.kind not in "fiu":
                raise TypeError(f"{topic}.{f.name} must be numeric, got dtype {arr.dtype}")
            if f.kind == _VECTOR6:
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


# ------------------------------------------------------------------------------------------
# Reading
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunLog:
    """A run log read by :func:`read_run_log`.

    Attributes
    ----------
    path : str
        The file read.
    topics : dict[str, pandas.DataFrame]
        One frame per contract topic that has messages. Index ``t``: log time [s] (float64,
        ``log_time_ns / 1e9``), in file order; columns: the topic's fields in contract order,
        ``theta_hat`` expanded to ``theta_hat_0`` .. ``theta_hat_5``; numbers are float64,
        strings are strings, ``/experiment/segment`` ``params`` are dicts.
    rig : dict[str, float | str]
        The ``rig`` metadata record (the keys of ``RIG_KEYS``); numbers as floats,
        ``pwm_update`` as a string.
    run : dict[str, str]
        The ``run`` metadata record.
    rig_hints : dict[str, float]
        The optional hints of the ``rig`` record (``RIG_HINT_KEYS``) that the log carries.
    ignored_topics : tuple[str, ...]
        Topics with messages that are not part of contract 1 (not decoded).
    sha256 : str
        SHA-256 of the file's bytes, hex.
    """

    path: str
    topics: dict[str, pd.DataFrame]
    rig: dict[str, float | str]
    run: dict[str, str]
    ignored_topics: tuple[str, ...] = ()
    sha256: str = ""
    rig_hints: dict[str, float] = field(default_factory=dict)

    def has(self, topic: str) -> bool:
        """Return True if ``topic`` has at least one message in the log."""
        return topic in self.topics

    def __getitem__(self, topic: str) -> pd.DataFrame:
        """Return the frame of ``topic``; :class:`KeyError` naming the topics present if absent."""
        try:
            return self.topics[topic]
        except KeyError:
            raise KeyError(
                f"{self.path}: no topic {topic!r}; present: {', '.join(self.topics)}"
            ) from None


@dataclass
class _Scan:
    """Everything a linear scan of the file collects (messages in file order)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    statistics: Statistics | None = None
    msg_channel: list[int] = field(default_factory=list)
    msg_ns: list[int] = field(default_factory=list)
    msg_data: list[bytes] = field(default_factory=list)


class _Corrupt(Exception):
    """Internal: the file's structure is broken (becomes TruncatedLogError)."""


class _CutShort(Exception):
    """Internal: the file ends inside the record that starts at ``args[0]``."""


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
(_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_MESSAGE_INDEX,
 _OP_CHUNK_INDEX, _OP_ATTACHMENT, _OP_ATTACHMENT_INDEX, _OP_STATISTICS, _OP_METADATA,
 _OP_METADATA_INDEX, _OP_SUMMARY_OFFSET, _OP_DATA_END) = range(0x01, 0x10)
_OP_LAST = _OP_DATA_END
_SUMMARY_OPCODES = frozenset({
    _OP_SCHEMA, _OP_CHANNEL, _OP_CHUNK_INDEX, _OP_ATTACHMENT_INDEX, _OP_STATISTICS,
    _OP_METADATA_INDEX, _OP_SUMMARY_OFFSET,
})
_NOT_IN_CHUNK = frozenset(range(0x01, 0x10)) - {_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE}
_MAX_CHUNK = 1 << 31


def _decompress(chunk: Chunk) -> bytes:
    size = chunk.uncompressed_size
    if size > _MAX_CHUNK:
        raise _Corrupt(f"chunk claims {size} uncompressed bytes")
    if chunk.compression == "zstd":
        declared = zstandard.frame_content_size(chunk.data)
        if declared not in (-1, size):
            raise _Corrupt(f"zstd frame holds {declared} bytes, chunk record says {size}")
        buf = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=size)
    elif chunk.compression == "lz4":
        try:
            import lz4.frame  # optional: pneutune itself writes zstd
        except ImportError:
            raise _Corrupt("chunk is lz4-compressed and the lz4 package is not installed") from None
        buf = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        buf = chunk.data
    else:
        raise _Corrupt(f"unknown chunk compression {chunk.compression!r}")
    if len(buf) != size:
        raise _Corrupt(f"chunk decompresses to {len(buf)} bytes, record says {size}")
    if chunk.uncompressed_crc and zlib.crc32(buf) != chunk.uncompressed_crc:
        raise _Corrupt("chunk CRC mismatch")
    return buf


class _StrictBytes(io.BytesIO):
    """A record body: reading past its end is corruption (BytesIO would return short data)."""

    def read(self, size: int | None = -1, /) -> bytes:
        out = super().read(size)
        if size is not None and size >= 0 and len(out) != size:
            raise _Corrupt("a record's fields run past the end of the record")
        return out


def _read_record(record_type: Any, body: bytes) -> Any:
    return record_type.read(ReadDataStream(_StrictBytes(body)))


def _scan_chunk(buf: bytes, scan: _Scan) -> None:
    """Split a decompressed chunk into records; messages go to the scan's flat lists."""
    head = _RECORD_HEAD.unpack_from
    msg_head = _MESSAGE_HEAD.unpack_from
    channel_ids = scan.msg_channel.append
    times = scan.msg_ns.append
    payloads = scan.msg_data.append
    pos, end_of_chunk = 0, len(buf)
    while pos < end_of_chunk:
        if pos + 9 > end_of_chunk:
            raise _Corrupt("chunk ends inside a record header")
        opcode, length = head(buf, pos)
        body = pos + 9
        end = body + length
        if end > end_of_chunk:
            raise _Corrupt("record runs past the end of its chunk")
        if opcode == _OP_MESSAGE:
            if length < _MESSAGE_HEAD.size:
                raise _Corrupt("message record too short")
            cid, _seq, log_time, _pub = msg_head(buf, body)
            channel_ids(cid)
            times(log_time)
            payloads(buf[body + _MESSAGE_HEAD.size : end])
        elif opcode == _OP_CHANNEL:
            _add_channel(scan, _read_record(Channel, buf[body:end]))
        elif opcode == _OP_SCHEMA:
            _add_schema(scan, _read_record(Schema, buf[body:end]))
        elif opcode in _NOT_IN_CHUNK:
            raise _Corrupt(f"record with opcode {opcode:#04x} inside a chunk")
        pos = end


def _add_schema(scan: _Scan, schema: Schema) -> None:
    old = scan.schemas.get(schema.id)
    if old is not None and old != schema:
        raise _Corrupt(f"two different schema records with id {schema.id}")
    scan.schemas[schema.id] = schema


def _add_channel(scan: _Scan, channel: Channel) -> None:
    if channel.schema_id != 0 and channel.schema_id not in scan.schemas:
        raise _Corrupt(f"channel {channel.topic!r} refers to unknown schema {channel.schema_id}")
    old = scan.channels.get(channel.id)
    if old is not None and old != channel:
        raise _Corrupt(f"two different channel records with id {channel.id}")
    scan.channels[channel.id] = channel


def _scan(data: bytes) -> _Scan:
    """Walk every record of the file in order, checking the structure and every CRC.

    The records are located here (opcode, length) and their bodies parsed with the ``mcap``
    package's record classes; message and message-index records, which are most of the file,
    are handled without building objects. Raises :class:`_CutShort` if the file ends before
    the closing magic and :class:`_Corrupt` for any other damage.
    """
    scan = _Scan()
    head = _RECORD_HEAD.unpack_from
    size = len(data)
    pos = len(MCAP_MAGIC)
    in_summary = False
    first = True
    while True:
        if pos + 9 > size:
            raise _CutShort(pos)
        opcode, length = head(data, pos)
        body = pos + 9
        end = body + length
        if end > size:
            raise _CutShort(pos)
        if first:
            if opcode != _OP_HEADER:
                raise _Corrupt(f"first record has opcode {opcode:#04x}, not Header")
            _read_record(Header, data[body:end])
            first = False
        elif opcode == _OP_FOOTER:
            footer = _read_record(Footer, data[body:end])
            break
        elif opcode == _OP_HEADER:
            raise _Corrupt("second Header record")
        elif in_summary:
            if opcode not in _SUMMARY_OPCODES and opcode <= _OP_LAST:
                raise _Corrupt(f"record with opcode {opcode:#04x} in the summary section")
            if opcode == _OP_STATISTICS:
                scan.statistics = _read_record(Statistics, data[body:end])
            elif opcode == _OP_SCHEMA:
                _add_schema(scan, _read_record(Schema, data[body:end]))
            elif opcode == _OP_CHANNEL:
                _add_channel(scan, _read_record(Channel, data[body:end]))
        elif opcode == _OP_CHUNK:
            _scan_chunk(_decompress(_read_record(Chunk, data[body:end])), scan)
        elif opcode == _OP_MESSAGE:
            _scan_chunk(data[pos:end], scan)  # a lone message parses like a one-record chunk
        elif opcode == _OP_SCHEMA:
            _add_schema(scan, _read_record(Schema, data[body:end]))
        elif opcode == _OP_CHANNEL:
            _add_channel(scan, _read_record(Channel, data[body:end]))
        elif opcode == _OP_METADATA:
            scan.metadata.append(_read_record(Metadata, data[body:end]))
        elif opcode == _OP_DATA_END:
            data_end = _read_record(DataEnd, data[body:end])
            if data_end.data_section_crc and zlib.crc32(data[:pos]) != data_end.data_section_crc:
                raise _Corrupt("data section CRC mismatch")
            in_summary = True
        # Anything else (message indexes, attachments, records of later spec versions)
        # carries nothing the run log needs; the CRCs still cover it.
        pos = end

    if not in_summary:
        raise _Corrupt("no DataEnd record before the footer")
    if end + len(MCAP_MAGIC) > size:
        raise _CutShort(end)
    if data[end : end + len(MCAP_MAGIC)] != MCAP_MAGIC:
        raise _Corrupt("the closing magic is wrong")
    if end + len(MCAP_MAGIC) != size:
        raise _Corrupt(f"{size - end - len(MCAP_MAGIC)} bytes after the closing magic")
    if footer.summary_crc:
        # The CRC covers the summary section and the footer up to (excluding) its CRC field.
        start = footer.summary_start or pos
        if not pos >= start >= len(MCAP_MAGIC):
            raise _Corrupt(f"footer's summary_start {footer.summary_start} is out of range")
        if zlib.crc32(data[start : body + 16]) != footer.summary_crc:
            raise _Corrupt("summary CRC mismatch")
    unknown = set(scan.msg_channel) - set(scan.channels)
    if unknown:
        raise _Corrupt(f"messages on undeclared channel ids {sorted(unknown)}")
    stats = scan.statistics
    if stats is not None and stats.message_count != len(scan.msg_ns):
        raise _Corrupt(
            f"statistics record counts {stats.message_count} messages, file holds "
            f"{len(scan.msg_ns)}"
        )
    return scan


def _read_bytes(file: str, path: str | os.PathLike[str]) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise LogError(file, f"cannot read the file: {exc.strerror or exc}") from exc


def _scan_file(file: str, data: bytes) -> _Scan:
    if len(data) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(data):
        raise TruncatedLogError(
            file, f"cut short: {len(data)} bytes, not even the 8-byte MCAP magic"
        )
    if not data.startswith(MCAP_MAGIC):
        raise NotMcapError(
            file, f"not an MCAP file: starts with {data[:8]!r}, expected {MCAP_MAGIC!r}"
        )
    try:
        return _scan(data)
    except _CutShort as exc:
        raise TruncatedLogError(
            file,
            f"cut short: the file ({len(data)} bytes) ends inside the record at byte "
            f"{exc.args[0]}, before the MCAP footer and closing magic",
        ) from exc
    except _Corrupt as exc:
        raise TruncatedLogError(file, f"corrupt MCAP: {exc}") from exc
    except Exception as exc:  # any other failure of the MCAP layer on these bytes is damage
        raise TruncatedLogError(
            file, f"corrupt or cut short MCAP ({type(exc).__name__}: {exc})"
        ) from exc


def _parse_rig_hints(file: str, records: list[Metadata]) -> dict[str, float]:
    """The optional ``rig`` hints (``RIG_HINT_KEYS``), positive finite decimals."""
    raw = next(m for m in records if m.name == "rig").metadata
    out = {}
    for key in RIG_HINT_KEYS:
        if key in raw:
            text = raw[key]
            value = float(text) if _DECIMAL.fullmatch(text) else math.nan
            if not (math.isfinite(value) and value > 0.0):
                raise LogSchemaError(file, f"'rig' metadata key {key} = {text!r} is not a "
                                     "positive decimal number")
            out[key] = value
    return out


def _parse_rig(file: str, records: list[Metadata]) -> dict[str, float | str]:
    rigs = [m for m in records if m.name == "rig"]
    if not rigs:
        raise MissingMetadataError(file, "no 'rig' metadata record (contract 1 requires one)")
    if len(rigs) > 1:
        raise MissingMetadataError(file, f"{len(rigs)} 'rig' metadata records, expected one")
    raw = rigs[0].metadata
    missing = [k for k in RIG_KEYS if k not in raw]
    if missing:
        raise MissingMetadataError(
            file, f"'rig' metadata record lacks key {missing[0]}"
            + (f" (and {', '.join(missing[1:])})" if len(missing) > 1 else "")
        )
    unknown = sorted(k for k in raw if k not in RIG_KEYS and k not in RIG_HINT_KEYS)
    if unknown:
        raise LogSchemaError(file, f"'rig' metadata record has unknown key(s) {', '.join(unknown)}")
    out: dict[str, float | str] = {}
    for key in _RIG_NUMBER_KEYS:
        text = raw[key]
        value = float(text) if _DECIMAL.fullmatch(text) else math.nan
        if not math.isfinite(value):
            raise MissingMetadataError(
                file, f"'rig' metadata key {key} = {text!r} is not a finite decimal number"
            )
        out[key] = value
    mode = raw["pwm_update"]
    if mode not in PWM_UPDATE_MODES:
        raise MissingMetadataError(
            file, f"'rig' metadata key pwm_update = {mode!r}, expected one of {PWM_UPDATE_MODES}"
        )
    out["pwm_update"] = mode
    return {k: out[k] for k in RIG_KEYS}


def _parse_run(file: str, records: list[Metadata]) -> dict[str, str]:
    runs = [m for m in records if m.name == "run"]
    if not runs:
        raise MissingMetadataError(file, "no 'run' metadata record (contract 1 requires one)")
    if len(runs) > 1:
        raise MissingMetadataError(file, f"{len(runs)} 'run' metadata records, expected one")
    run = dict(runs[0].metadata)
    if "schema" not in run:
        raise MissingMetadataError(file, "'run' metadata record lacks key schema")
    if run["schema"] != LOG_SCHEMA:
        raise LogSchemaError(
            file, f"'run' metadata schema is {run['schema']!r}; this reader reads {LOG_SCHEMA!r}"
        )
    return run


_NUMBER_TYPES = frozenset({float, int, type(None)})


def _to_float(value: Any) -> float:
    if value is None:
        return math.nan
    try:
        return float(value)
    except OverflowError:  # an integer literal beyond float range
        return math.inf if value > 0 else -math.inf


#: Bytes of the number tokens the bulk path accepts: digits, sign, point, exponent, null.
_TOKEN_BYTES = b"0123456789.eE+-nul"
_SEPARATOR = 0x1F  # joins messages in the bulk path; JSON text never contains control bytes


def _bulk_numeric(spec: _Topic, payloads: list[bytes]) -> np.ndarray | None:
    """Decode all messages of a numeric topic at once, or return None (use the JSON path).

    This handles the compact layout the writer produces, fields in schema order and no
    whitespace. The messages are joined by a control byte; each literal piece of the topic's
    template (``{"x":``, ``,"p_a":``, ..., ``}``) is replaced by a one-byte marker; numpy then
    checks that the markers come in template order with exactly one non-empty token between
    consecutive pieces and nothing else, so every message is exactly
    ``{"x":<token>,"p_a":<token>,...}``. The tokens (digits, sign, point, exponent or
    ``null``) are parsed by :func:`numpy.loadtxt`, correctly rounded like ``float()``; ``null``
    becomes NaN. Any deviation returns None and the caller decodes each message as JSON,
    which also produces the precise error. (Tokens that are numbers to numpy but not to JSON,
    such as ``+1`` or ``.5``, are accepted here; the writer never produces them.)

    Returns
    -------
    numpy.ndarray or None
        Shape (N, spec.width), float64, numbers in template order.
    """
    n = len(payloads)
    pieces = spec.template.split("%r")
    marker = {p: 1 + k for k, p in enumerate(dict.fromkeys(pieces))}  # codes 1 .. 12
    if len(marker) >= _SEPARATOR:  # pragma: no cover - contract topics have <= 12 pieces
        return None
    separator = bytes([_SEPARATOR])
    text = separator.join(payloads) + separator
    if int(np.count_nonzero(np.frombuffer(text, dtype=np.uint8) < 0x20)) != n:
        return None  # a control byte (e.g. a newline) inside a message: not our layout
    for piece in sorted(marker, key=len, reverse=True):  # ',"p_a":' before ','
        text = text.replace(piece.encode("ascii"), bytes([marker[piece]]))
    raw = np.frombuffer(text, dtype=np.uint8)
    at = np.flatnonzero(raw < 0x20)
    pattern = np.array([marker[p] for p in pieces] + [_SEPARATOR], dtype=np.uint8)
    if at.size != pattern.size * n or not np.array_equal(raw[at], np.tile(pattern, n)):
        return None
    gaps = np.diff(at, prepend=-1) - 1  # bytes between consecutive markers
    number_follows = np.tile(np.r_[False, np.ones(len(pieces) - 1, dtype=bool), False], n)
    if np.any(gaps[number_follows] <= 0) or np.any(gaps[~number_follows] != 0):
        return None
    # One line of comma-separated numbers per message: drop the first and last pieces, turn
    # the others into commas and the separators into newlines.
    table = bytearray(range(256))
    for code in marker.values():
        table[code] = ord(",")
    table[_SEPARATOR] = ord("\n")
    lines = text.translate(bytes(table), bytes([marker[pieces[0]], marker[pieces[-1]]]))
    if lines.translate(None, _TOKEN_BYTES + b",\n"):
        return None
    try:
        values = np.loadtxt(
            io.BytesIO(lines.replace(b"null", b"nan")),
            dtype=np.float64, delimiter=",", comments=None, ndmin=2,
        )
    except ValueError:
        return None
    if values.shape != (n, spec.width):  # pragma: no cover - guaranteed by the gap check
        return None
    return values


class _TopicDecoder:
    """Decode the messages of one topic into columns, with errors naming topic and time."""

    def __init__(self, file: str, spec: _Topic, ns: np.ndarray) -> None:
        self.file = file
        self.spec = spec
        self.ns = ns

    def fail(self, i: int, what: str) -> LogSchemaError:
        return LogSchemaError(
            self.file, f"{self.spec.topic}: message at t={_fmt_ns(self.ns[i])}: {what}"
        )

    def objects(self, payloads: list[bytes]) -> list[dict[str, Any]]:
        try:
            objs = [decode_json(p) for p in payloads]
        except (ValueError, RecursionError):
            for i, p in enumerate(payloads):
                try:
                    decode_json(p)
                except (ValueError, RecursionError) as exc:
                    raise self.fail(i, f"not valid UTF-8 JSON ({exc})") from exc
            raise  # pragma: no cover - the loop above finds the culprit
        names = set(self.spec.names)
        for i, obj in enumerate(objs):
            if type(obj) is not dict or obj.keys() != names:
                if not isinstance(obj, dict):
                    raise self.fail(i, f"expected a JSON object, got {type(obj).__name__}")
                missing = [n for n in self.spec.names if n not in obj]
                unknown = sorted(set(obj) - names)
                raise self.fail(
                    i,
                    (f"missing field(s) {', '.join(missing)}" if missing else "")
                    + ("; " if missing and unknown else "")
                    + (f"unknown field(s) {', '.join(unknown)}" if unknown else ""),
                )
        return objs

    def numbers(self, name: str, values: list[Any], per_message: int = 1) -> np.ndarray:
        if not set(map(type, values)) <= _NUMBER_TYPES:
            i = next(k for k, v in enumerate(values) if type(v) not in _NUMBER_TYPES)
            raise self.fail(i // per_message, f"{name} = {values[i]!r} is not a number")
        try:
            return np.array(values, dtype=np.float64)
        except OverflowError:
            return np.array([_to_float(v) for v in values], dtype=np.float64)

    def decode(self, payloads: list[bytes]) -> dict[str, Any]:
        if self.spec.numeric:
            values = _bulk_numeric(self.spec, payloads)
            if values is not None:
                return dict(zip(self.spec.columns, values.T, strict=True))
        objs = self.objects(payloads)
        cols: dict[str, Any] = {}
        for f in self.spec.fields:
            values = [obj[f.name] for obj in objs]
            if f.kind == _NUMBER:
                cols[f.name] = self.numbers(f.name, values)
            elif f.kind == _VECTOR6:
                for i, v in enumerate(values):
                    if type(v) is not list or len(v) != 6:
                        raise self.fail(i, f"{f.name} = {v!r} is not a list of 6 numbers")
                flat = self.numbers(f.name, list(itertools.chain.from_iterable(values)), 6)
                matrix = flat.reshape(len(values), 6)
                for k in range(6):
                    cols[f"{f.name}_{k}"] = matrix[:, k]
            elif f.kind == _OBJECT:
                for i, v in enumerate(values):
                    if type(v) is not dict:
                        raise self.fail(i, f"{f.name} = {v!r} is not a JSON object")
                arr = np.empty(len(values), dtype=object)
                arr[:] = values
                cols[f.name] = arr
            else:
                for i, v in enumerate(values):
                    if type(v) is not str:
                        raise self.fail(i, f"{f.name} = {v!r} is not a string")
                    if f.kind == _LEVEL and v not in EVENT_LEVELS:
                        raise self.fail(i, f"{f.name} = {v!r} is not one of {EVENT_LEVELS}")
                cols[f.name] = values
        return cols

    def check_finite(self, cols: dict[str, Any], allow_nonfinite: bool) -> None:
        for name in self.spec.columns:
            col = cols.get(name)
            if not isinstance(col, np.ndarray) or col.dtype != np.float64:
                continue
            bad = ~np.isfinite(col)
            if not bad.any():
                continue
            if allow_nonfinite:
                col[bad] = np.nan
                continue
            i = int(np.argmax(bad))
            label = name
            if name.startswith("theta_hat_"):
                label = f"theta_hat[{name[-1]}]"
            raise NonFiniteValueError(
                self.file,
                f"{self.spec.topic}: {label} is not finite ({col[i]!r}; null in the file) at "
                f"t={_fmt_ns(self.ns[i])}, {int(bad.sum())} such value(s) in this field; "
                "pass allow_nonfinite=True to read them as NaN",
            )


def _check_time_order(file: str, topic: str, ns: np.ndarray) -> None:
    back = np.flatnonzero(ns[1:] < ns[:-1])
    if back.size:
        i = int(back[0])
        raise TimeOrderError(
            file,
            f"{topic}: log time goes backwards from t={_fmt_ns(ns[i])} to "
            f"t={_fmt_ns(ns[i + 1])} (messages {i} and {i + 1} of the topic, file order)",
        )


def read_run_log(
    path: str | os.PathLike[str],
    required_topics: Sequence[str] = REQUIRED_TOPICS,
    allow_nonfinite: bool = False,
) -> RunLog:
    """Read and check a run log (contract 1).

    Parameters
    ----------
    path : path-like
        The ``.mcap`` file.
    required_topics : Sequence[str], optional
        Topics that must have at least one message; default ``/rig/sensors`` and
        ``/rig/valves``. Each must be a topic of contract 1.
    allow_nonfinite : bool, optional
        Read ``null`` (and NaN, infinities) in numeric fields as NaN instead of raising.

    Returns
    -------
    RunLog
        Frames per topic, the ``rig`` and ``run`` metadata, the file's SHA-256.

    Raises
    ------
    NotMcapError
        The file does not start with the MCAP magic.
    TruncatedLogError
        The file is cut short or damaged (structure, CRC, compression, trailing bytes).
    EmptyLogError
        The file holds no messages.
    MissingMetadataError
        The ``rig`` or ``run`` record is missing, ``rig`` lacks a key of ``RIG_KEYS`` or holds
        a value that does not parse; the message names the key.
    MissingTopicError
        A required topic has no messages.
    LogSchemaError
        A channel or message of a contract topic does not match its schema.
    TimeOrderError
        Log times of a topic go backwards (file order); names the topic and both times.
    NonFiniteValueError
        A numeric field is ``null``, NaN or infinite and ``allow_nonfinite`` is False; names
        topic, field and log time.
    LogError
        The file cannot be read at all (``OSError``).
    ValueError
        ``required_topics`` names a topic outside contract 1 (a programming error).
    """
    required = tuple(required_topics)
    for topic in required:
        _spec(topic)
    file = os.fspath(path)
    data = _read_bytes(file, path)
    scan = _scan_file(file, data)

    n_messages = len(scan.msg_ns)
    if n_messages == 0:
        raise EmptyLogError(file, "the log holds no messages")
    rig = _parse_rig(file, scan.metadata)
    run = _parse_run(file, scan.metadata)

    channel_ids = np.fromiter(scan.msg_channel, dtype=np.int64, count=n_messages)
    log_ns = np.fromiter(scan.msg_ns, dtype=np.uint64, count=n_messages)
    if int(log_ns.max()) > _MAX_NS:
        raise LogSchemaError(file, f"a log time exceeds {_MAX_NS} ns")
    log_ns = log_ns.astype(np.int64)
    counts = np.bincount(channel_ids, minlength=max(scan.channels, default=0) + 1)
    present: dict[str, list[int]] = {}
    for cid, channel in sorted(scan.channels.items()):
        if counts[cid]:
            present.setdefault(channel.topic, []).append(cid)

    missing = [t for t in required if t not in present]
    if missing:
        raise MissingTopicError(
            file,
            f"required topic {missing[0]} has no messages"
            + (f" (nor {', '.join(missing[1:])})" if len(missing) > 1 else "")
            + f"; present: {', '.join(sorted(present)) or 'none'}",
        )

    factory = JsonDecoderFactory()
    topics: dict[str, pd.DataFrame] = {}
    for topic in TOPICS:
        cids = present.get(topic)
        if not cids:
            continue
        for cid in cids:
            channel = scan.channels[cid]
            schema = scan.schemas.get(channel.schema_id)
            if factory.decoder_for(channel.message_encoding, schema) is None:
                raise LogSchemaError(
                    file,
                    f"{topic}: channel has message encoding {channel.message_encoding!r} and "
                    f"schema encoding {schema.encoding if schema else None!r}; contract 1 "
                    "wants json with a jsonschema schema",
                )
        if len(cids) == 1:
            index = np.flatnonzero(channel_ids == cids[0])
        else:
            index = np.flatnonzero(np.isin(channel_ids, cids))
        ns = log_ns[index]
        _check_time_order(file, topic, ns)
        payloads = [scan.msg_data[i] for i in index.tolist()]
        decoder = _TopicDecoder(file, _SPEC[topic], ns)
        cols = decoder.decode(payloads)
        decoder.check_finite(cols, allow_nonfinite)
        topics[topic] = pd.DataFrame(
            cols, index=pd.Index(ns / 1e9, name="t"), columns=list(_SPEC[topic].columns)
        )

    ignored = tuple(sorted(t for t in present if t not in _SPEC))
    return RunLog(
        path=file,
        topics=topics,
        rig=rig,
        run=run,
        ignored_topics=ignored,
        sha256=hashlib.sha256(data).hexdigest(),
        rig_hints=_parse_rig_hints(file, scan.metadata),
    )
