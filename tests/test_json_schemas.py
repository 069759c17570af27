"""The committed JSON Schemas of the YAML contracts are current, and they accept the shipped
files and reject what the loaders reject (so outside tools see the same contract)."""

from __future__ import annotations

from pathlib import Path

import jsonschema
import pytest
import yaml

from pneutune.control.contracts.json_schemas import json_schema, schema_path, schema_text
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["plant", "model", "controller"])
def test_committed_schema_is_current(name):
    """control/schemas/<name>.schema.json equals the pydantic models' schema (regenerate with
    `python -m pneutune.control.contracts.json_schemas`)."""
    assert schema_path(name).read_text(encoding="utf-8") == schema_text(name)


def test_schemas_accept_shipped_and_generated_files():
    jsonschema.validate(yaml.safe_load((ROOT / "data" / "controller-paper.yaml").read_text()),
                        json_schema("controller"))
    jsonschema.validate(PlantConfig().to_dict(), json_schema("plant"))
    jsonschema.validate(model_from_plant(PlantConfig()).to_dict(), json_schema("model"))


def test_schema_rejects_unknown_key():
    data = PlantConfig().to_dict()
    data["frction"] = {}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(data, json_schema("plant"))
