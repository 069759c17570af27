"""docs/contracts.md is the user-facing reference of the four files: it must be current with the
code and name every key of every contract (the JSON Schemas are the machine-readable truth)."""

from __future__ import annotations

import json
import re

import pytest

from pneutune.control.constants import RIG_HINT_KEYS, RIG_KEYS, VALVES
from pneutune.control.contracts.json_schemas import schema_path
from pneutune.control.logs.topics import TOPIC_SPECS
from pneutune.control.reference import PAGE, render, schema_keys

TEXT = PAGE.read_text(encoding="utf-8")
VALVE = re.compile(r"\b(" + "|".join(VALVES) + r")\b")


def test_the_generated_tables_are_current() -> None:
    """Regenerate with ``python -m pneutune.control.reference`` when this fails."""
    assert render(TEXT) == TEXT


def _committed_keys(name: str) -> set[str]:
    """Every dotted key of a committed JSON Schema file (independently of the generator):
    properties, through $refs, anyOf branches, array items and free-name mappings."""
    schema = json.loads(schema_path(name).read_text(encoding="utf-8"))
    defs = schema.get("$defs", {})
    out: set[str] = set()

    def walk(node: dict, path: str, depth: int) -> None:
        if depth > 12 or not isinstance(node, dict):
            return
        if "$ref" in node:
            walk(defs[node["$ref"].split("/")[-1]], path, depth + 1)
        for sub in node.get("anyOf", []) + node.get("allOf", []):
            walk(sub, path, depth + 1)
        if isinstance(node.get("items"), dict):
            walk(node["items"], path, depth + 1)
        extra = node.get("additionalProperties")
        if isinstance(extra, dict):
            walk(extra, f"{path}.<name>" if path else "<name>", depth + 1)
        for key, sub in node.get("properties", {}).items():
            full = VALVE.sub("<valve>", f"{path}.{key}" if path else key)
            out.add(full)
            walk(sub, full, depth + 1)

    walk(schema, "", 0)
    return out


@pytest.mark.parametrize("name", ["plant", "model", "controller"])
def test_every_schema_key_is_named(name: str) -> None:
    keys = _committed_keys(name)
    assert len(keys) > 40  # the walk found the contract, not an empty shell
    missing = sorted(k for k in keys if f"`{k}`" not in TEXT)
    assert not missing, missing
    assert {k[0] for k in schema_keys(name)} == keys


def test_every_log_topic_field_and_rig_key_is_named() -> None:
    for topic, spec in TOPIC_SPECS.items():
        assert f"`{topic}`" in TEXT, topic
        for field in spec.fields:
            assert f"`{field.name}`" in TEXT, (topic, field.name)
    for key in (*RIG_KEYS, *RIG_HINT_KEYS):
        assert f"`{key}`" in TEXT, key
