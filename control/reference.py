"""The key tables of docs/contracts.md, generated from the contracts' own definitions.

The four file contracts are defined in code: the run log's topics and metadata by
:mod:`pneutune.control.logs.topics` and :data:`pneutune.control.constants.RIG_KEYS`, plant.yaml,
model.yaml and controller.yaml by their pydantic models, whose JSON Schemas
(:mod:`pneutune.control.contracts.json_schemas`) are the machine-readable truth. The user-facing
reference, docs/contracts.md, is prose around tables this module writes from them, between
``<!-- generated:NAME -->`` and ``<!-- /generated:NAME -->`` (NAME one of :data:`BLOCKS`); a test
checks that the committed page is current and names every key. Regenerate with
``python -m pneutune.control.reference``.

In the tables a key repeated per valve is written once, with ``<valve>`` for ``a_in``,
``a_out``, ``b_in`` and ``b_out``; a mapping of free names (model.yaml's ``effects``) has
``<name>``.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

from pneutune.control.constants import RIG_HINT_KEYS, RIG_HINT_RANGES, RIG_KEYS, VALVES
from pneutune.control.contracts.atomic import atomic_write_text
from pneutune.control.contracts.json_schemas import json_schema
from pneutune.control.logs.topics import REQUIRED_TOPICS, TOPIC_SPECS

#: The generated blocks: the run log (contract 1) and the three YAML contracts.
BLOCKS: tuple[str, ...] = ("log", "plant", "model", "controller")
#: The page the blocks live in.
PAGE = Path(__file__).resolve().parents[1] / "docs" / "contracts.md"

_VALVE_RE = re.compile(r"\b(" + "|".join(VALVES) + r")\b")


def _resolve(node: dict[str, Any], defs: dict[str, Any]) -> dict[str, Any]:
    """``node`` with a ``$ref`` (or a one-branch ``anyOf``/``allOf`` of one) replaced."""
    if "$ref" in node:
        return {**defs[node["$ref"].split("/")[-1]], **{k: v for k, v in node.items()
                                                       if k != "$ref"}}
    for key in ("allOf", "anyOf"):
        subs = [s for s in node.get(key, []) if s.get("type") != "null"]
        if len(subs) == 1 and ("$ref" in subs[0] or "properties" in subs[0]):
            return {**_resolve(subs[0], defs), **{k: v for k, v in node.items() if k != key}}
    return node


def _type(node: dict[str, Any], defs: dict[str, Any]) -> str:
    """A short type of a schema node: number, integer, string, one of [...], list, mapping."""
    if "enum" in node:
        return "one of " + ", ".join(f"`{v}`" for v in node["enum"])
    if "const" in node:
        return f"`{node['const']}`"
    if "anyOf" in node:
        kinds = [_type(_resolve(s, defs), defs) for s in node["anyOf"]]
        return " or ".join(dict.fromkeys(kinds))
    t = node.get("type")
    if t == "array":
        items = node.get("items")
        inner = _type(_resolve(items, defs), defs) if isinstance(items, dict) else "value"
        return f"list of {inner}"
    if t == "object" or "properties" in node:
        return "mapping"
    return str(t) if t else "value"


def _limits(node: dict[str, Any]) -> str:
    """The numeric bounds of a schema node, as ``> 0``, ``<= 1`` and so on."""
    out = []
    for key, sym in (("exclusiveMinimum", ">"), ("minimum", ">="), ("exclusiveMaximum", "<"),
                     ("maximum", "<=")):
        if key in node:
            out.append(f"{sym} {node[key]:g}")
    for key, sym in (("minItems", "at least"), ("maxItems", "at most")):
        if key in node:
            out.append(f"{sym} {node[key]} items")
    return ", ".join(out)


def schema_keys(name: str) -> list[tuple[str, str, str, str]]:
    """Every key of a YAML contract: (dotted path, type and limits, required or default,
    description), valves collapsed to ``<valve>``, in schema order.

    Parameters
    ----------
    name : str
        ``plant``, ``model`` or ``controller``.

    Returns
    -------
    list of tuple of str
    """
    schema = json_schema(name)
    defs = schema.get("$defs", {})
    rows: dict[str, tuple[str, str, str, str]] = {}

    def walk(node: dict[str, Any], path: str, depth: int) -> None:
        node = _resolve(node, defs)
        if depth > 10:
            return
        required = set(node.get("required", ()))
        for key, sub in node.get("properties", {}).items():
            full = _VALVE_RE.sub("<valve>", f"{path}.{key}" if path else key)
            r = _resolve(sub, defs)
            kind = _type(r, defs)
            lim = _limits(r)
            if "default" in sub or "default" in r:
                default = sub.get("default", r.get("default"))
                need = ("default " + (f"`{default}`" if not isinstance(default, (dict, list))
                                      else "as shown in the defaults") if default is not None
                        else "optional")
            else:
                need = "required" if key in required else "optional"
            text = " ".join(str(sub.get("description") or r.get("description") or "").split())
            text = text.replace("|", "\\|")
            if full not in rows:
                rows[full] = (full, kind + (f" ({lim})" if lim else ""), need, text)
            for branch in [r, *(_resolve(b, defs) for b in r.get("anyOf", ()))]:
                items = branch.get("items")
                if branch.get("type") == "array" and isinstance(items, dict):
                    walk(items, full, depth + 1)
                elif branch is r or "properties" in branch or isinstance(
                        branch.get("additionalProperties"), dict):
                    walk(branch, full, depth + 1)
        extra = node.get("additionalProperties")
        if isinstance(extra, dict):
            walk(extra, f"{path}.<name>" if path else "<name>", depth + 1)

    walk(schema, "", 0)
    return list(rows.values())


def _table(rows: list[tuple[str, ...]], head: tuple[str, ...]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def log_block() -> str:
    """The run log's tables: the ``rig`` metadata keys, then each topic's fields."""
    parts = [_table([(f"`{k}`", "decimal string" if k != "pwm_update" else
                      "`immediate` or `latched`", "required") for k in RIG_KEYS]
                    + [(f"`{k}`", "decimal string",
                        f"optional hint, {RIG_HINT_RANGES[k][0]:g} to {RIG_HINT_RANGES[k][1]:g} "
                        f"{RIG_HINT_RANGES[k][2]}") for k in RIG_HINT_KEYS],
                    ("`rig` key", "value", "")),
             ""]
    for topic, spec in TOPIC_SPECS.items():
        need = "required" if topic in REQUIRED_TOPICS else "optional"
        parts.append(f"**`{topic}`** ({need}; schema `{spec.schema_name}`): {spec.description}")
        parts.append("")
        parts.append(_table([(f"`{f.name}`", f.kind, " ".join(f.description.split()))
                             for f in spec.fields], ("field", "kind", "meaning")))
        parts.append("")
    return "\n".join(parts).rstrip() + "\n"


def block(name: str) -> str:
    """The generated Markdown of block ``name`` (one of :data:`BLOCKS`)."""
    if name == "log":
        return log_block()
    rows = [(f"`{p}`", k, n, d) for p, k, n, d in schema_keys(name)]
    return _table(rows, ("key", "type", "", "meaning")) + "\n"


def render(text: str) -> str:
    """``text`` with every generated block rewritten from the code.

    Raises
    ------
    ValueError
        A block's markers are missing.
    """
    for name in BLOCKS:
        start, end = f"<!-- generated:{name} -->", f"<!-- /generated:{name} -->"
        if start not in text or end not in text:
            raise ValueError(f"{PAGE.name}: the markers of block {name!r} are missing")
        head, rest = text.split(start, 1)
        _, tail = rest.split(end, 1)
        text = f"{head}{start}\n{block(name)}{end}{tail}"
    return text


def main() -> int:
    """Rewrite docs/contracts.md's generated blocks (exit 0), or with ``--check`` say whether
    they are current (exit 1 if not)."""
    text = PAGE.read_text(encoding="utf-8")
    new = render(text)
    if "--check" in sys.argv[1:]:
        return 0 if new == text else 1
    if new != text:
        atomic_write_text(PAGE, new)
    return 0


__all__ = ["BLOCKS", "PAGE", "block", "render", "schema_keys"]

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
