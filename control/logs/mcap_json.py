"""JSON message codec for the ``mcap`` package (which ships no JSON decoder).

MCAP's registry names the message encoding ``json`` (UTF-8 JSON text, one value per message) and
the schema encoding ``jsonschema`` (a JSON Schema document). :class:`JsonDecoderFactory` plugs into
:func:`mcap.reader.make_reader` (``decoder_factories=[JsonDecoderFactory()]``) so that
``iter_decoded_messages`` yields Python objects; the run-log reader
(:mod:`pneutune.control.logs.reader`) uses the same factory to decide whether it can decode a
channel and :func:`decode_json` to decode each message.

Decoding is Python's :func:`json.loads`, which also accepts the non-standard tokens ``NaN``,
``Infinity`` and ``-Infinity`` that some writers emit. They decode to non-finite floats, so a
caller that rejects non-finite values (the run-log reader does) reports them as such instead of
as a syntax error. Encoding (:func:`encode_json`) is strict, compact JSON: no spaces, no
non-finite floats.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from mcap.decoder import DecoderFactory
from mcap.records import Schema

#: Message encoding handled here (MCAP registry name).
MESSAGE_ENCODING = "json"
#: Schema encodings accepted for JSON channels: a JSON Schema, or none (self-describing JSON).
SCHEMA_ENCODINGS: tuple[str, ...] = ("jsonschema", "")

_decode = json.JSONDecoder().decode
_encoder = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def decode_json(data: bytes) -> Any:
    """Decode one JSON message.

    Parameters
    ----------
    data : bytes
        The message payload, UTF-8 JSON text.

    Returns
    -------
    Any
        The decoded value (``dict`` for the run-log topics).

    Raises
    ------
    ValueError
        The payload is not UTF-8 (:class:`UnicodeDecodeError`) or not JSON
        (:class:`json.JSONDecodeError`).
    RecursionError
        The payload nests deeper than the interpreter's recursion limit.
    """
    return _decode(data.decode("utf-8"))


def encode_json(value: Any) -> bytes:
    """Encode a value as compact, strict JSON (UTF-8, no spaces, no NaN or infinities).

    Parameters
    ----------
    value : Any
        A JSON-serialisable value.

    Returns
    -------
    bytes
        UTF-8 JSON text.

    Raises
    ------
    ValueError
        ``value`` holds a NaN or an infinity.
    TypeError
        ``value`` holds an object JSON cannot represent.
    """
    return _encoder.encode(value).encode("utf-8")


class JsonDecoderFactory(DecoderFactory):
    """Provide :func:`decode_json` for channels with message encoding ``json``.

    A channel qualifies when its message encoding is ``json`` and its schema is absent or has
    schema encoding ``jsonschema`` (or the empty encoding). The schema's content is not used for
    decoding: JSON is self-describing.
    """

    def decoder_for(
        self, message_encoding: str, schema: Schema | None
    ) -> Callable[[bytes], Any] | None:
        """Return the decoder for a channel, or ``None`` if this factory cannot decode it.

        Parameters
        ----------
        message_encoding : str
            The channel's message encoding.
        schema : mcap.records.Schema or None
            The channel's schema record (``None`` for schema id 0).

        Returns
        -------
        callable or None
            :func:`decode_json`, or ``None``.
        """
        if message_encoding != MESSAGE_ENCODING:
            return None
        if schema is not None and schema.encoding not in SCHEMA_ENCODINGS:
            return None
        return decode_json
