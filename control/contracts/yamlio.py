"""YAML input and output for the configuration files (plant.yaml, model.yaml, controller.yaml).

* Read as YAML 1.2 (ruamel.yaml's safe loader, pure Python): ``6.0e5`` is a number, ``yes`` and
  ``no`` are strings, and only plain data is built, never arbitrary objects. Files written for
  YAML 1.1 (exponents with a sign, ``true``/``false``) read the same.
* A key given twice in one mapping is an error (a silent overwrite would hide a typo), and so are
  anchors and aliases (``&a``/``*a``): a contract file has no use for them, and nested aliases
  expand exponentially (the "billion laughs").
* pydantic validation errors become one :class:`~pneutune.control.errors.ConfigError` naming the
  file, the dotted key path and the rule.
* Output is written atomically by PyYAML, with floats in a form that YAML 1.1 and 1.2 both read
  back as floats (an exponent with a sign), so that older readers of the files still work.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError
from ruamel.yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from pneutune.control.contracts.atomic import atomic_write_text
from pneutune.control.errors import ConfigError

M = TypeVar("M", bound=BaseModel)


def _reader() -> YAML:
    """A YAML 1.2 reader building plain data only."""
    return YAML(typ="safe", pure=True)


def _check_nodes(root: Node | None) -> str:
    """The first duplicate key, anchor or alias in a composed document, as a sentence ("" if
    none)."""
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        # an alias (*a) composes to its anchored node itself, so refusing every anchor refuses
        # every alias too, before a recursive or exponentially nested one is walked
        anchor = getattr(node, "anchor", None)
        if anchor:
            return (f"an anchor (&{anchor}) at line {node.start_mark.line + 1}; anchors and "
                    f"aliases are not allowed in a contract file")
        if isinstance(node, MappingNode):
            first: dict[tuple[str, str], int] = {}
            for key, value in node.value:
                if isinstance(key, ScalarNode):
                    k = (key.tag if isinstance(key.tag, str) else str(key.tag), key.value)
                    if k in first:
                        return (f"duplicate key {key.value!r} at line {key.start_mark.line + 1} "
                                f"(first at line {first[k] + 1})")
                    first[k] = key.start_mark.line
                stack.extend((value, key))
        elif isinstance(node, SequenceNode):
            stack.extend(reversed(node.value))
    return ""


def load_yaml_mapping(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a YAML file whose top level is a mapping.

    Parameters
    ----------
    path : path-like
        The file.

    Returns
    -------
    dict
        The parsed mapping.

    Raises
    ------
    ConfigError
        The file cannot be read, is not YAML, repeats a key or is not a mapping.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(p), "", "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(str(p), "", f"cannot read the file ({exc})") from None
    reader = _reader()
    try:
        root = reader.compose(text)
        problem = _check_nodes(root)
        if problem:
            raise ConfigError(str(p), "", problem)
        # built from the checked nodes: parsing the text again took as long as composing it
        data = None if root is None else reader.constructor.construct_document(root)
    except YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(str(p), "", f"not valid YAML{where}: {problem}") from None
    except ConfigError:  # _check_nodes' (a ValueError too), as it is
        raise
    except ValueError as exc:  # a scalar the constructor cannot build (an integer of 4301 digits)
        reason = str(exc).split(";")[0]
        raise ConfigError(str(p), "", f"a value cannot be read as a number ({reason})") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(str(p), "",
                          f"expected a mapping at the top level, got {type(data).__name__}")
    return data


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Merge ``over`` onto ``base``: nested mappings merge key by key, anything else replaces.

    Keys of ``over`` unknown to ``base`` are kept, so that validation can reject them by name.
    """
    out: dict[str, Any] = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _data_loc(loc: tuple[Any, ...], data: Any) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """``loc`` without the member labels pydantic puts in it for a union, and those labels.

    ``source.SourceInfo.run`` is the file's ``source.run``: a string that is not the last item
    and not a key of the mapping the path has reached (a missing parent would have been the
    error itself), or that comes where the path has reached a list, is such a label. Without
    the data the path stays as pydantic gave it.
    """
    if data is None:
        return loc, ()
    out: list[Any] = []
    labels: list[Any] = []
    node = data
    for i, item in enumerate(loc):
        if isinstance(item, str) and i + 1 < len(loc) and (
                (isinstance(node, Mapping) and item not in node)
                or isinstance(node, (list, tuple))):
            labels.append((len(out), item))
            continue
        out.append(item)
        try:
            node = node[item]
        except (KeyError, IndexError, TypeError):
            node = None
    return tuple(out), tuple(labels)


def _format_loc(loc: tuple[Any, ...]) -> str:
    parts: list[str] = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        else:
            parts.append(("." if parts else "") + str(item))
    return "".join(parts)


def _describe(err: Mapping[str, Any]) -> str:
    etype = err.get("type", "")
    value = err.get("input")
    if etype == "extra_forbidden":
        return "unknown key (check the spelling against the schema)"
    if etype == "missing":
        return "required key is missing"
    if etype in ("float_type", "int_type", "bool_type") and isinstance(value, str):
        hint = ""
        try:
            float(value)
            hint = " (a number in quotes is a string: write it without them, e.g. 6.0e+5)"
        except ValueError:
            pass
        kind = {"float_type": "a number", "int_type": "an integer", "bool_type": "true/false"}
        return f"expected {kind[etype]}, got the string {value!r}{hint}"
    msg = str(err.get("msg", "invalid value"))
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    if etype not in ("value_error", "assertion_error") and value is not None and not isinstance(
        value, (dict, list)
    ):
        msg = f"{msg}, got {value!r}"
    return msg


def validation_error(file: str, exc: ValidationError, prefix: str = "",
                     data: Any = None) -> ConfigError:
    """Turn the first error of a pydantic ValidationError into a ConfigError.

    Parameters
    ----------
    file : str
        The file the data came from.
    exc : pydantic.ValidationError
        The validation failure.
    prefix : str
        Key path to prepend (when a sub-model was validated on its own).
    data : object, optional
        The validated data: with it, the key path leaves out pydantic's union member labels.
    """
    errs = exc.errors(include_url=False)
    err = errs[0]
    loc, labels = _data_loc(tuple(err.get("loc", ())), data)
    key = _format_loc(loc)
    # the other members of a union fail too: count only the problems of the first's member
    errs = [e for e in errs if _data_loc(tuple(e.get("loc", ())), data)[1] == labels]
    if prefix:
        key = f"{prefix}.{key}" if key else prefix
    message = _describe(err)
    if not key:  # a rule across blocks (a model validator) names its key first: "a.b: ..."
        named = re.match(r"^([A-Za-z_][\w]*(?:\.[A-Za-z_][\w]*)+): (.+)$", message, re.S)
        if named:
            key = f"{prefix}.{named.group(1)}" if prefix else named.group(1)
            message = named.group(2)
    if len(errs) > 1:
        message += f" (and {len(errs) - 1} more problem{'s' if len(errs) > 2 else ''})"
    return ConfigError(file, key, message)


def validate_model(model: type[M], data: Mapping[str, Any], file: str) -> M:
    """Validate ``data`` against a pydantic model, raising :class:`ConfigError` on failure."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise validation_error(file, exc, data=data) from None


def load_config(path: str | os.PathLike[str], model: type[M], schema: str,
                defaults: Mapping[str, Any] | None = None) -> M:
    """Load a configuration file: YAML mapping, schema id check, optional merge, validation.

    Parameters
    ----------
    path : path-like
        The file.
    model : pydantic model class
        What the document must validate as.
    schema : str
        The expected ``schema`` value (e.g. ``pneutune.plant/1``); a file may omit the key.
    defaults : mapping, optional
        Plain-data defaults the file is deep-merged over (plant.yaml); None: the file must be
        complete.

    Raises
    ------
    ConfigError
        Bad YAML, a different schema, or a validation failure, naming the file and key.
    """
    data = load_yaml_mapping(path)
    if "schema" in data and data["schema"] != schema:
        raise ConfigError(str(path), "schema", f"expected {schema!r}, got {data['schema']!r}")
    if defaults is not None:
        data = deep_merge(defaults, data)
    return validate_model(model, data, str(path))


class _Dumper(yaml.SafeDumper):
    """SafeDumper writing floats that YAML 1.1 and 1.2 read back as floats (exponent with a
    sign)."""


def _represent_float(dumper: yaml.SafeDumper, value: float) -> yaml.ScalarNode:
    if math.isnan(value):
        text = ".nan"
    elif math.isinf(value):
        text = ".inf" if value > 0 else "-.inf"
    else:
        text = repr(float(value))
        if "e" in text and "e-" not in text and "e+" not in text:
            text = text.replace("e", "e+")
        if "." not in text and "e" in text:
            mant, exp = text.split("e")
            text = f"{mant}.0e{exp}"
        elif "." not in text and "inf" not in text and "nan" not in text:
            text += ".0"
    return dumper.represent_scalar("tag:yaml.org,2002:float", text)


_Dumper.add_representer(float, _represent_float)


def dump_yaml(data: Mapping[str, Any]) -> str:
    """Serialise a mapping to YAML text (key order kept, block style for nested mappings)."""
    return yaml.dump(dict(data), Dumper=_Dumper, sort_keys=False, default_flow_style=None,
                     width=100, allow_unicode=True)


def write_yaml(path: str | os.PathLike[str], data: Mapping[str, Any], header: str = "") -> None:
    """Write a mapping to ``path`` atomically, with an optional ``#`` comment header."""
    text = dump_yaml(data)
    if header:
        text = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines()) + text
    atomic_write_text(path, text)
