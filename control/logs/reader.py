"""Read and check an MCAP run log (contract 1, :mod:`pneutune.control.logs.topics`).

Strictness
    The reader takes the contract's topics and rejects a message of such a topic that lacks a
    field, carries a field the schema does not know, or holds a value of the wrong type
    (:class:`~pneutune.control.errors.LogSchemaError`). Topics outside the contract (a rig
    logger may record more) are not decoded; their names are listed in
    :attr:`RunLog.ignored_topics`. A ``rig`` record with a key outside ``RIG_KEYS`` and the
    optional hints ``RIG_HINT_KEYS`` (``mass``, a positive decimal, read into
    :attr:`RunLog.rig_hints`) is rejected; the ``run`` record may carry further keys.
    ``null`` in a numeric field (and the non-standard tokens ``NaN`` and ``Infinity`` written
    by other tools, and numbers that overflow to infinity) raises
    :class:`~pneutune.control.errors.NonFiniteValueError` naming topic, field and log time,
    unless ``allow_nonfinite=True``, in which case they read as NaN. Log times of a topic that
    go backwards raise :class:`~pneutune.control.errors.TimeOrderError`.

Integrity
    The whole file is read linearly by the ``mcap`` package's
    :class:`~mcap.stream_reader.StreamReader` with ``validate_crcs=True``, which parses every
    record and checks the data-section CRC; each chunk is decompressed and its CRC checked by
    the package's ``get_chunk_data_stream``. Three checks the package does not make are made
    here: the summary CRC, no bytes after the closing magic, and the statistics record's
    message count; besides, the record order (one Header first, a DataEnd before the
    footer, only summary records after it) and that every message's channel and every
    channel's schema is declared. A file that was cut short or damaged raises
    :class:`~pneutune.control.errors.TruncatedLogError` rather than yielding partial data; no
    exception of the ``mcap``, ``zstandard`` or ``struct`` modules escapes. Message-index
    records are skipped unparsed (:class:`_RecordReader`; their layout is checked and the CRC
    covers them): parsed by the package they cost about 1 s on a log of a million messages.

    One part stays hand-written because it pays: the records inside a decompressed chunk
    are split here (:func:`_scan_chunk`), and a message becomes three list entries instead of
    an :class:`mcap.records.Message` object. On ``data/run.mcap`` the package's
    ``breakup_chunk`` takes several times as long (benchmarks/identify_speed.py,
    docs/identification.md).
"""

from __future__ import annotations

import hashlib
import io
import itertools
import math
import os
import re
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import UnsupportedCompressionError
from mcap.opcode import Opcode
from mcap.records import (
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import CRCValidationError, StreamReader, get_chunk_data_stream
from numba import njit

from pneutune.control.constants import LOG_SCHEMA, PWM_UPDATE_MODES, RIG_HINT_KEYS, RIG_KEYS
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
from pneutune.control.logs.mcap_json import JsonDecoderFactory, decode_json
from pneutune.control.logs.topics import (
    EVENT_LEVELS,
    LEVEL,
    NUMBER,
    OBJECT,
    REQUIRED_TOPICS,
    RIG_NUMBER_KEYS,
    TOPIC_SPECS,
    TOPICS,
    VECTOR6,
    TopicSpec,
    format_ns,
    topic_spec,
)

__all__ = ["MCAP_MAGIC", "RunLog", "read_run_log"]

#: The 8-byte magic that starts and ends every MCAP file.
MCAP_MAGIC: bytes = b"\x89MCAP0\r\n"
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_MAX_NS = 2**63 - 1


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
    """Internal: the file ends inside the read that starts at byte ``args[0]``."""


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_MESSAGE_HEAD_SIZE = _MESSAGE_HEAD.size
_MESSAGE_OPCODE = int(Opcode.MESSAGE)
#: Bytes of the footer record: opcode, length, summary_start, summary_offset_start, summary_crc.
#: Like the ``mcap`` package's seeking reader, the footer is taken to be exactly this long.
_FOOTER_SIZE = _RECORD_HEAD.size + 8 + 8 + 4
#: Records a summary section may hold (records of later spec versions are skipped).
_SUMMARY_RECORDS = (Schema, Channel, ChunkIndex, AttachmentIndex, Statistics, MetadataIndex,
                    SummaryOffset)
#: Opcodes of the spec that a chunk must not hold (it holds schemas, channels and messages).
_NOT_IN_CHUNK = frozenset(Opcode) - {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE}
#: Largest uncompressed chunk accepted [bytes]: a damaged size must not allocate gigabytes.
_MAX_CHUNK = 1 << 31


class _FileBytes(io.BytesIO):
    """The file as the StreamReader's input: a read that comes back short, or a negative
    length (a record whose fields run past its end), is damage, never partial data."""

    def read(self, size: int | None = -1, /) -> bytes:
        if size is None or size < 0:
            raise _Corrupt("a record's fields run past the end of the record")
        at = self.tell()
        out = super().read(size)
        if len(out) != size:
            raise _CutShort(at)
        return out


class _StrictBytes(io.BytesIO):
    """A record body: reading past its end is corruption (BytesIO would return short data)."""

    def read(self, size: int | None = -1, /) -> bytes:
        out = super().read(size)
        if size is not None and size >= 0 and len(out) != size:
            raise _Corrupt("a record's fields run past the end of the record")
        return out


_MESSAGE_INDEX_HEAD = struct.Struct("<HI")  # channel id, byte length of the entries
_MESSAGE_INDEX_ENTRY = 16  # log time, offset (uint64 each)


class _RecordReader(StreamReader):
    """The ``mcap`` package's StreamReader, except that a MessageIndex record is not parsed.

    The package reads a message index entry by entry, four Python calls per message, which
    made the StreamReader switch cost about 1 s more on ``data/run.mcap`` as it was (956k
    messages, one index entry each; benchmarks/identify_speed.py, docs/architecture.md). The
    run log does not use message indexes, so their body is read in one piece (the data-section
    CRC still covers it) and only its layout is checked: a channel id, an entry length that is
    a whole number of 16-byte entries and fits in the record. If a later ``mcap`` release
    renames the hook ``_read_record``, the package parses the indexes again: slower, still
    correct.
    """

    def _read_record(self, opcode: int, length: int) -> Any:
        if opcode != Opcode.MESSAGE_INDEX:
            return super()._read_record(opcode, length)
        body = self._stream.read(length)  # the CRC-computing stream: the data CRC covers it
        if length < _MESSAGE_INDEX_HEAD.size:
            raise _Corrupt("message index record too short")
        _cid, entries = _MESSAGE_INDEX_HEAD.unpack_from(body)
        if entries % _MESSAGE_INDEX_ENTRY or _MESSAGE_INDEX_HEAD.size + entries > len(body):
            raise _Corrupt(f"message index record holds {entries} bytes of entries in a "
                           f"{length}-byte record (16 bytes per entry)")
        return None


def _read_record(record_type: Any, body: bytes) -> Any:
    return record_type.read(ReadDataStream(_StrictBytes(body)))


def _decompress(chunk: Chunk) -> bytes:
    """The records of a chunk: decompressed and CRC-checked by the ``mcap`` package.

    The package's ``get_chunk_data_stream`` trusts the sizes in a damaged record (a zstd frame
    header that claims gigabytes is allocated) and reads an unknown compression as none; those
    cases are refused first.
    """
    size = chunk.uncompressed_size
    if size > _MAX_CHUNK:
        raise _Corrupt(f"chunk claims {size} uncompressed bytes")
    if chunk.compression == "zstd":
        declared = zstandard.frame_content_size(chunk.data)
        if declared not in (-1, size):
            raise _Corrupt(f"zstd frame holds {declared} bytes, chunk record says {size}")
    elif chunk.compression not in ("lz4", ""):
        raise _Corrupt(f"unknown chunk compression {chunk.compression!r}")
    try:
        stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    except UnsupportedCompressionError:  # lz4 is optional: pneutune itself writes zstd
        raise _Corrupt("chunk is lz4-compressed and the lz4 package is not installed") from None
    if length != size:
        raise _Corrupt(f"chunk decompresses to {length} bytes, record says {size}")
    return stream.read(length)


@njit(cache=True)
def _walk_chunk(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                           np.ndarray, int]:  # pragma: no cover - compiled
    """The records of a decompressed chunk, in order, up to the first that does not fit.

    Parameters
    ----------
    buf : ndarray of uint8
        The chunk's records.

    Returns
    -------
    (ndarray, ndarray, ndarray, ndarray, ndarray, int)
        Per record: opcode, body start, body end (byte offsets); for a message whose body
        holds its header, its channel id and log time (0 otherwise); and 0 if every record
        fits, 1 if the chunk ends inside a record header, 2 if a record runs past its end
        (the records before it are returned).
    """
    n = buf.size
    cap = n // 9 + 1
    opcodes = np.empty(cap, np.uint8)
    starts = np.empty(cap, np.int64)
    ends = np.empty(cap, np.int64)
    channels = np.zeros(cap, np.int64)
    times = np.zeros(cap, np.uint64)
    k = 0
    pos = 0
    status = 0
    while pos < n:
        if pos + 9 > n:
            status = 1
            break
        length = np.uint64(0)
        for i in range(8):
            length |= np.uint64(buf[pos + 1 + i]) << np.uint64(8 * i)
        body = pos + 9
        if length > np.uint64(n - body):
            status = 2
            break
        end = body + np.int64(length)
        op = buf[pos]
        opcodes[k] = op
        starts[k] = body
        ends[k] = end
        if op == _MESSAGE_OPCODE and end - body >= _MESSAGE_HEAD_SIZE:
            # a message: channel id (u16), sequence (u32), log time (u64), publish time
            channels[k] = np.int64(buf[body]) | (np.int64(buf[body + 1]) << 8)
            t = np.uint64(0)
            for i in range(8):
                t |= np.uint64(buf[body + 6 + i]) << np.uint64(8 * i)
            times[k] = t
        k += 1
        pos = end
    return opcodes[:k], starts[:k], ends[:k], channels[:k], times[:k], status


def _scan_chunk(buf: bytes, scan: _Scan) -> None:
    """Split a decompressed chunk into records; messages go to the scan's flat lists.

    The record boundaries come from :func:`_walk_chunk` (compiled: a chunk of an
    identification run holds some 15k messages); schemas, channels and anything wrong are
    handled here, in file order, so the first damaged record is the one reported.
    """
    opcodes, starts, ends, channels, times, status = _walk_chunk(
        np.frombuffer(buf, dtype=np.uint8))
    is_msg = opcodes == Opcode.MESSAGE
    short = is_msg & (ends - starts < _MESSAGE_HEAD.size)
    for j in np.flatnonzero(~is_msg | short).tolist():
        opcode, body, end = int(opcodes[j]), int(starts[j]), int(ends[j])
        if opcode == Opcode.MESSAGE:
            raise _Corrupt("message record too short")
        if opcode == Opcode.CHANNEL:
            _add_channel(scan, _read_record(Channel, buf[body:end]))
        elif opcode == Opcode.SCHEMA:
            _add_schema(scan, _read_record(Schema, buf[body:end]))
        elif opcode in _NOT_IN_CHUNK:
            raise _Corrupt(f"record with opcode {opcode:#04x} inside a chunk")
    if status == 1:
        raise _Corrupt("chunk ends inside a record header")
    if status == 2:
        raise _Corrupt("record runs past the end of its chunk")
    scan.msg_channel.extend(channels[is_msg].tolist())
    scan.msg_ns.extend(times[is_msg].tolist())
    first = (starts[is_msg] + _MESSAGE_HEAD.size).tolist()
    scan.msg_data.extend([buf[a:b] for a, b in zip(first, ends[is_msg].tolist(), strict=True)])


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
    """Read every record of the file in order, checking the structure and every CRC.

    The ``mcap`` package's StreamReader walks the file and checks the data-section CRC;
    chunks come out whole (``emit_chunks``) and are split by :func:`_scan_chunk`. Raises
    :class:`_CutShort` if the file ends before the closing magic, :class:`_Corrupt` or the
    ``mcap`` package's errors for any other damage.
    """
    scan = _Scan()
    stream = _FileBytes(data)
    # no record size limit: a length beyond the end of the file is a short read (cut short)
    reader = _RecordReader(stream, emit_chunks=True, validate_crcs=True,
                           record_size_limit=None)
    footer: Footer | None = None
    in_summary = False
    first = True
    for record in reader.records:
        kind = type(record)
        if first:  # the reader skips unknown opcodes, so look at the bytes after the magic
            if kind is not Header or data[len(MCAP_MAGIC)] != Opcode.HEADER:
                raise _Corrupt(f"first record has opcode {data[len(MCAP_MAGIC)]:#04x}, not Header")
            first = False
        elif kind is Footer:
            footer = record
        elif kind is Header:
            raise _Corrupt("second Header record")
        elif in_summary:
            if not isinstance(record, _SUMMARY_RECORDS):
                raise _Corrupt(f"{kind.__name__} record in the summary section")
            if kind is Statistics:
                scan.statistics = record
            elif kind is Schema:
                _add_schema(scan, record)
            elif kind is Channel:
                _add_channel(scan, record)
        elif kind is Chunk:
            _scan_chunk(_decompress(record), scan)
        elif kind is Message:
            scan.msg_channel.append(record.channel_id)
            scan.msg_ns.append(record.log_time)
            scan.msg_data.append(record.data)
        elif kind is Schema:
            _add_schema(scan, record)
        elif kind is Channel:
            _add_channel(scan, record)
        elif kind is Metadata:
            scan.metadata.append(record)
        elif kind is DataEnd:
            in_summary = True
        # Anything else (message indexes, attachments) carries nothing the run log needs;
        # the CRCs still cover it.

    if footer is None or not in_summary:  # the reader stops only after a footer
        raise _Corrupt("no DataEnd record before the footer")
    size = stream.tell()
    if size != len(data):
        raise _Corrupt(f"{len(data) - size} bytes after the closing magic")
    if footer.summary_crc:
        # The CRC covers the summary section and the footer up to (excluding) its CRC field.
        at = size - len(MCAP_MAGIC) - _FOOTER_SIZE
        if _RECORD_HEAD.unpack_from(data, at) != (Opcode.FOOTER, _FOOTER_SIZE - 9):
            raise _Corrupt("the footer is not the 29-byte record of the MCAP spec")
        start = footer.summary_start or at
        if not at >= start >= len(MCAP_MAGIC):
            raise _Corrupt(f"footer's summary_start {footer.summary_start} is out of range")
        if zlib.crc32(data[start : size - len(MCAP_MAGIC) - 4]) != footer.summary_crc:
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
            f"cut short: the file ({len(data)} bytes) ends inside a record (a read at byte "
            f"{exc.args[0]} runs past its end), before the MCAP footer and closing magic",
        ) from exc
    except (_Corrupt, CRCValidationError) as exc:
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
    for key in RIG_NUMBER_KEYS:
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


#: The correctly rounded float parser of ``pandas.read_csv`` (the same floats as ``float()``):
#: its default from pandas 3 on (which deprecates the option), ``round_trip`` before.
_EXACT_FLOATS: dict[str, str] = (
    {} if int(pd.__version__.split(".")[0]) >= 3 else {"float_precision": "round_trip"})
#: Bytes of the number tokens the bulk path accepts: digits, sign, point, exponent, null.
_TOKEN_BYTES = b"0123456789.eE+-nul"
_SEPARATOR = 0x1F  # joins messages in the bulk path; JSON text never contains control bytes


def _bulk_numeric(spec: TopicSpec, payloads: list[bytes]) -> np.ndarray | None:
    """Decode all messages of a numeric topic at once, or return None (use the JSON path).

    This handles the compact layout the writer produces, fields in schema order and no
    whitespace. The messages are joined by a control byte; each literal piece of the topic's
    template (``{"x":``, ``,"p_a":``, ..., ``}``) is replaced by a one-byte marker; numpy then
    checks that the markers come in template order with exactly one non-empty token between
    consecutive pieces and nothing else, so every message is exactly
    ``{"x":<token>,"p_a":<token>,...}``. The tokens (digits, sign, point, exponent or
    ``null``) are parsed by :func:`pandas.read_csv` (its C parser, correctly rounded like
    ``float()``; seven times as fast as :func:`numpy.loadtxt` on an identification run);
    ``null`` becomes NaN. Any deviation returns None and the caller decodes each message as JSON,
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
        values = pd.read_csv(
            io.BytesIO(lines), header=None, dtype=np.float64, engine="c",
            keep_default_na=False, na_values=["null"], **_EXACT_FLOATS,
        ).to_numpy()
    except (ValueError, pd.errors.ParserError):
        return None
    if values.shape != (n, spec.width):  # pragma: no cover - guaranteed by the gap check
        return None
    return values


class _TopicDecoder:
    """Decode the messages of one topic into columns, with errors naming topic and time."""

    def __init__(self, file: str, spec: TopicSpec, ns: np.ndarray) -> None:
        self.file = file
        self.spec = spec
        self.ns = ns

    def fail(self, i: int, what: str) -> LogSchemaError:
        return LogSchemaError(
            self.file, f"{self.spec.topic}: message at t={format_ns(self.ns[i])}: {what}"
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
            if f.kind == NUMBER:
                cols[f.name] = self.numbers(f.name, values)
            elif f.kind == VECTOR6:
                for i, v in enumerate(values):
                    if type(v) is not list or len(v) != 6:
                        raise self.fail(i, f"{f.name} = {v!r} is not a list of 6 numbers")
                flat = self.numbers(f.name, list(itertools.chain.from_iterable(values)), 6)
                matrix = flat.reshape(len(values), 6)
                for k in range(6):
                    cols[f"{f.name}_{k}"] = matrix[:, k]
            elif f.kind == OBJECT:
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
                    if f.kind == LEVEL and v not in EVENT_LEVELS:
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
                f"t={format_ns(self.ns[i])}, {int(bad.sum())} such value(s) in this field; "
                "pass allow_nonfinite=True to read them as NaN",
            )


def _check_time_order(file: str, topic: str, ns: np.ndarray) -> None:
    back = np.flatnonzero(ns[1:] < ns[:-1])
    if back.size:
        i = int(back[0])
        raise TimeOrderError(
            file,
            f"{topic}: log time goes backwards from t={format_ns(ns[i])} to "
            f"t={format_ns(ns[i + 1])} (messages {i} and {i + 1} of the topic, file order)",
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
        topic_spec(topic)
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
        decoder = _TopicDecoder(file, TOPIC_SPECS[topic], ns)
        cols = decoder.decode(payloads)
        decoder.check_finite(cols, allow_nonfinite)
        topics[topic] = pd.DataFrame(
            cols, index=pd.Index(ns / 1e9, name="t"), columns=list(TOPIC_SPECS[topic].columns)
        )

    ignored = tuple(sorted(t for t in present if t not in TOPIC_SPECS))
    return RunLog(
        path=file,
        topics=topics,
        rig=rig,
        run=run,
        ignored_topics=ignored,
        sha256=hashlib.sha256(data).hexdigest(),
        rig_hints=_parse_rig_hints(file, scan.metadata),
    )
