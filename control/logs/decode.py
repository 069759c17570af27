"""Decode the payloads of a run log's contract topics into columns (contract 1).

A message of a contract topic must hold exactly the topic's fields, each of the right type
(:class:`~pneutune.control.errors.LogSchemaError` otherwise, naming topic, log time and
field). Numeric topics in the writer's compact layout are decoded all at once
(:func:`_bulk_numeric`); anything else, and anything the bulk path does not recognise, message
by message as JSON. ``null`` in a numeric field (and the non-standard tokens ``NaN`` and
``Infinity`` written by other tools, and numbers that overflow to infinity) reads as a
non-finite float, which :meth:`TopicDecoder.check_finite` rejects or turns into NaN.
"""

from __future__ import annotations

import io
import itertools
import math
from typing import Any

import numpy as np
import pandas as pd

from pneutune.control.errors import LogSchemaError, NonFiniteValueError, TimeOrderError
from pneutune.control.logs.mcap_json import decode_json
from pneutune.control.logs.topics import (
    EVENT_LEVELS,
    LEVEL,
    NUMBER,
    OBJECT,
    VECTOR6,
    TopicSpec,
    format_ns,
)

__all__ = ["TopicDecoder", "check_time_order"]

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


class TopicDecoder:
    """Decode the messages of one topic into columns, with errors naming topic and time.

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    spec : TopicSpec
        The topic's fields.
    ns : numpy.ndarray
        Log times [ns] of the topic's messages, in the order of the payloads to decode.
    """

    def __init__(self, file: str, spec: TopicSpec, ns: np.ndarray) -> None:
        self.file = file
        self.spec = spec
        self.ns = ns

    def fail(self, i: int, what: str) -> LogSchemaError:
        """The error for message ``i``: topic, its log time and ``what`` is wrong.

        Parameters
        ----------
        i : int
            Index of the message in the topic.
        what : str
            What is wrong with it.

        Returns
        -------
        LogSchemaError
            The error, to raise.
        """
        return LogSchemaError(
            self.file, f"{self.spec.topic}: message at t={format_ns(self.ns[i])}: {what}"
        )

    def objects(self, payloads: list[bytes]) -> list[dict[str, Any]]:
        """Parse every message as a JSON object with exactly the topic's fields.

        Parameters
        ----------
        payloads : list[bytes]
            The messages, in the order of the log times.

        Returns
        -------
        list[dict[str, Any]]
            One object per message.

        Raises
        ------
        LogSchemaError
            A message is not UTF-8 JSON, not an object, or lacks or adds a field.
        """
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
        """The JSON values of a numeric field as floats (``null`` as NaN).

        Parameters
        ----------
        name : str
            The field, for the error message.
        values : list[Any]
            The field's values, ``per_message`` of them per message.
        per_message : int, optional
            Values per message (6 for ``theta_hat``).

        Returns
        -------
        numpy.ndarray
            float64; integers beyond the float range as infinities.

        Raises
        ------
        LogSchemaError
            A value is not a number or ``null``.
        """
        if not set(map(type, values)) <= _NUMBER_TYPES:
            i = next(k for k, v in enumerate(values) if type(v) not in _NUMBER_TYPES)
            raise self.fail(i // per_message, f"{name} = {values[i]!r} is not a number")
        try:
            return np.array(values, dtype=np.float64)
        except OverflowError:
            return np.array([_to_float(v) for v in values], dtype=np.float64)

    def decode(self, payloads: list[bytes]) -> dict[str, Any]:
        """Decode the topic's messages into columns.

        Parameters
        ----------
        payloads : list[bytes]
            The messages, in the order of the log times.

        Returns
        -------
        dict[str, Any]
            One column per name of ``spec.columns``: float64 arrays for numbers
            (``theta_hat`` as ``theta_hat_0`` .. ``theta_hat_5``), lists of strings, an
            object array of dicts for ``params``.

        Raises
        ------
        LogSchemaError
            A message does not match the topic's schema.
        """
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
        """Reject non-finite numbers, or set them to NaN in place.

        Parameters
        ----------
        cols : dict[str, Any]
            Columns from :meth:`decode`.
        allow_nonfinite : bool
            Set NaN and infinities to NaN instead of raising.

        Raises
        ------
        NonFiniteValueError
            A numeric column holds a non-finite value and ``allow_nonfinite`` is False; names
            topic, field and the first such log time.
        """
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
            v = float(col[i])
            what = ("null or NaN" if math.isnan(v) else
                    f"{'+' if v > 0 else '-'}Infinity or a number beyond ±1.8e308")
            raise NonFiniteValueError(
                self.file,
                f"{self.spec.topic}: {label} is not a finite number ({what}) at "
                f"t={format_ns(self.ns[i])}, {int(bad.sum())} such value(s) in this field; "
                "contract 1 wants finite numbers: repair or drop those messages (Python "
                "callers may read them as NaN with read_run_log(..., allow_nonfinite=True))",
            )


def check_time_order(file: str, topic: str, ns: np.ndarray) -> None:
    """Check that the log times of a topic never go backwards (file order).

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    topic : str
        The topic, for the error message.
    ns : numpy.ndarray
        The topic's log times [ns] in file order.

    Raises
    ------
    TimeOrderError
        A log time is earlier than the one before it; names both times.
    """
    back = np.flatnonzero(ns[1:] < ns[:-1])
    if back.size:
        i = int(back[0])
        raise TimeOrderError(
            file,
            f"{topic}: log time goes backwards from t={format_ns(ns[i])} to "
            f"t={format_ns(ns[i + 1])} (messages {i} and {i + 1} of the topic, file order)",
        )
