"""Parse the ``rig`` and ``run`` metadata records of a run log (contract 1).

The ``rig`` record holds exactly the keys of ``RIG_KEYS`` and optionally the hints of
``RIG_HINT_KEYS``; its numbers are decimal strings (``repr(float)`` as the writer stores
them) and ``pwm_update`` one of ``PWM_UPDATE_MODES``. The ``run`` record is a string map that
names the log schema and may carry further keys. Errors name the record and the key.
"""

from __future__ import annotations

import math
import re

from mcap.records import Metadata

from pneutune.control.constants import (
    LOG_SCHEMA,
    PWM_UPDATE_MODES,
    RIG_HINT_KEYS,
    RIG_HINT_RANGES,
    RIG_KEYS,
)
from pneutune.control.errors import LogSchemaError, MissingMetadataError
from pneutune.control.logs.topics import RIG_NUMBER_KEYS

__all__ = ["parse_rig", "parse_rig_hints", "parse_run"]

_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_rig_hints(file: str, records: list[Metadata]) -> dict[str, float]:
    """The optional ``rig`` hints (``RIG_HINT_KEYS``), decimals within ``RIG_HINT_RANGES``.

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    records : list[mcap.records.Metadata]
        The file's metadata records; one of them is the ``rig`` record (:func:`parse_rig`
        checks that first).

    Returns
    -------
    dict[str, float]
        The hints the ``rig`` record carries.

    Raises
    ------
    LogSchemaError
        A hint is not a decimal number within its range.
    """
    raw = next(m for m in records if m.name == "rig").metadata
    out = {}
    for key in RIG_HINT_KEYS:
        if key in raw:
            text = raw[key]
            value = float(text) if _DECIMAL.fullmatch(text) else math.nan
            lo, hi, unit = RIG_HINT_RANGES[key]
            if not (math.isfinite(value) and lo <= value <= hi):
                raise LogSchemaError(file, f"'rig' metadata key {key} = {text!r} is not a "
                                     f"decimal number of {unit} within [{lo:g}, {hi:g}]")
            out[key] = value
    return out


def parse_rig(file: str, records: list[Metadata]) -> dict[str, float | str]:
    """The ``rig`` metadata record: numbers as floats, ``pwm_update`` as a string.

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    records : list[mcap.records.Metadata]
        The file's metadata records.

    Returns
    -------
    dict[str, float | str]
        The keys of ``RIG_KEYS``, in that order.

    Raises
    ------
    MissingMetadataError
        No ``rig`` record or more than one, a key of ``RIG_KEYS`` missing, a number that is
        not a finite decimal, a ``pwm_update`` outside ``PWM_UPDATE_MODES``.
    LogSchemaError
        A key outside ``RIG_KEYS`` and ``RIG_HINT_KEYS``.
    """
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


def parse_run(file: str, records: list[Metadata]) -> dict[str, str]:
    """The ``run`` metadata record.

    Parameters
    ----------
    file : str
        The file's name as error messages give it.
    records : list[mcap.records.Metadata]
        The file's metadata records.

    Returns
    -------
    dict[str, str]
        The record's keys and values.

    Raises
    ------
    MissingMetadataError
        No ``run`` record or more than one, or no ``schema`` key.
    LogSchemaError
        The ``schema`` is not the one this reader reads (``LOG_SCHEMA``).
    """
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
