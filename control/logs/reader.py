"""Read and check an MCAP run log (contract 1, :mod:`pneutune.control.logs.topics`).

:func:`read_run_log` composes three layers: :mod:`~pneutune.control.logs.container` walks the
file's records, checking its structure and every CRC; :mod:`~pneutune.control.logs.metadata`
parses the ``rig`` and ``run`` records; :mod:`~pneutune.control.logs.decode` turns the
payloads of each contract topic into columns.

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
    A file that was cut short or damaged raises
    :class:`~pneutune.control.errors.TruncatedLogError` rather than yielding partial data
    (:mod:`~pneutune.control.logs.container` lists the checks).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from pneutune.control.errors import EmptyLogError, LogSchemaError, MissingTopicError
from pneutune.control.logs.container import MCAP_MAGIC, read_bytes, scan_file
from pneutune.control.logs.decode import TopicDecoder, check_time_order
from pneutune.control.logs.mcap_json import JsonDecoderFactory
from pneutune.control.logs.metadata import parse_rig, parse_rig_hints, parse_run
from pneutune.control.logs.topics import REQUIRED_TOPICS, TOPIC_SPECS, TOPICS, topic_spec

__all__ = ["MCAP_MAGIC", "RunLog", "read_run_log"]

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


def run_stop_note(run: dict[str, str]) -> str:
    """What a log's ``run`` record says of a run that stopped early, and what to do, as a
    sentence starting with "; " ("" for a run that ended normally or says nothing).

    Parameters
    ----------
    run : dict[str, str]
        The ``run`` metadata record (``status``, ``fault``, ``stopped_in``,
        ``segments_completed`` as ``record`` and ``deploy`` write them).
    """
    status = run.get("status", "")
    if status not in ("fault", "interrupted"):
        return ""
    how = "was interrupted" if status == "interrupted" else (
        f"stopped with the fault {run['fault']}" if run.get("fault") else "stopped with a fault")
    where = f" in segment {run['stopped_in']}" if run.get("stopped_in") else ""
    done = (f" after {run['segments_completed']} segments" if run.get("segments_completed")
            else "")
    return (f"; the run that wrote it {how}{where}{done}: record it again once the cause is "
            "fixed (its log's events say what stopped it), or record the missing segments "
            "(record --segments) and identify both logs")


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
    data = read_bytes(file, path)
    scan = scan_file(file, data)

    n_messages = len(scan.msg_ns)
    if n_messages == 0:
        raise EmptyLogError(file, "the log holds no messages")
    rig = parse_rig(file, scan.metadata)
    run = parse_run(file, scan.metadata)

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
            + f"; present: {', '.join(sorted(present)) or 'none'}" + run_stop_note(run),
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
        check_time_order(file, topic, ns)
        payloads = [scan.msg_data[i] for i in index.tolist()]
        decoder = TopicDecoder(file, TOPIC_SPECS[topic], ns)
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
        rig_hints=parse_rig_hints(file, scan.metadata),
    )
