"""Walk the records of an MCAP run log and check its structure (the reader's container layer).

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

The messages come out undecoded (:class:`Scan`); :mod:`pneutune.control.logs.metadata` and
:mod:`pneutune.control.logs.decode` read them, :mod:`pneutune.control.logs.reader` composes
the three.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
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

from pneutune.control.errors import LogError, NotMcapError, TruncatedLogError
from pneutune.control.numba_cache import njit

__all__ = ["MCAP_MAGIC", "Scan", "read_bytes", "scan_file"]

#: The 8-byte magic that starts and ends every MCAP file.
MCAP_MAGIC: bytes = b"\x89MCAP0\r\n"


@dataclass
class Scan:
    """Everything a linear scan of the file collects (messages in file order).

    Attributes
    ----------
    schemas : dict[int, mcap.records.Schema]
        Schema records by id.
    channels : dict[int, mcap.records.Channel]
        Channel records by id.
    metadata : list[mcap.records.Metadata]
        Metadata records in file order.
    statistics : mcap.records.Statistics or None
        The summary's statistics record, if the file has one.
    msg_channel : list[int]
        Channel id of every message.
    msg_ns : list[int]
        Log time of every message [ns].
    msg_data : list[bytes]
        Payload of every message, undecoded.
    """

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


def _scan_chunk(buf: bytes, scan: Scan) -> None:
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


def _add_schema(scan: Scan, schema: Schema) -> None:
    old = scan.schemas.get(schema.id)
    if old is not None and old != schema:
        raise _Corrupt(f"two different schema records with id {schema.id}")
    scan.schemas[schema.id] = schema


def _add_channel(scan: Scan, channel: Channel) -> None:
    if channel.schema_id != 0 and channel.schema_id not in scan.schemas:
        raise _Corrupt(f"channel {channel.topic!r} refers to unknown schema {channel.schema_id}")
    old = scan.channels.get(channel.id)
    if old is not None and old != channel:
        raise _Corrupt(f"two different channel records with id {channel.id}")
    scan.channels[channel.id] = channel


def _scan(data: bytes) -> Scan:
    """Read every record of the file in order, checking the structure and every CRC.

    The ``mcap`` package's StreamReader walks the file and checks the data-section CRC;
    chunks come out whole (``emit_chunks``) and are split by :func:`_scan_chunk`. Raises
    :class:`_CutShort` if the file ends before the closing magic, :class:`_Corrupt` or the
    ``mcap`` package's errors for any other damage.
    """
    scan = Scan()
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


def read_bytes(file: str, path: str | os.PathLike[str]) -> bytes:
    """Read the whole file.

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    path : path-like
        The file to read.

    Returns
    -------
    bytes
        The file's bytes.

    Raises
    ------
    LogError
        The file cannot be read (``OSError``).
    """
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise LogError(file, f"cannot read the file: {exc.strerror or exc}") from exc


def scan_file(file: str, data: bytes) -> Scan:
    """Walk every record of an MCAP file, checking its structure and every CRC.

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    data : bytes
        The file's bytes.

    Returns
    -------
    Scan
        Schemas, channels, metadata records, the statistics record and the messages (channel
        id, log time, undecoded payload) in file order.

    Raises
    ------
    NotMcapError
        The bytes do not start with the MCAP magic.
    TruncatedLogError
        The file is cut short or damaged (structure, CRC, compression, trailing bytes).
    """
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
