"""JSON Schemas of the YAML contracts, exported to ``control/schemas/`` for outside tools.

plant.yaml (contract 2), model.yaml (contract 3) and controller.yaml (contract 4) are defined by
their pydantic models; the committed ``*.schema.json`` files are generated from them and a test
checks they are current. Regenerate with ``python -m pneutune.control.contracts.json_schemas``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from pneutune.control.contracts.atomic import atomic_write_text

SCHEMA_DIR = Path(__file__).resolve().parent / "schemas"


def _models() -> dict[str, tuple[type[BaseModel], str]]:
    from pneutune.control.contracts.controller import ControllerConfig
    from pneutune.control.contracts.model import ModelConfig
    from pneutune.control.contracts.plant import PlantConfig

    return {"plant": (PlantConfig, "pneutune.plant/1"),
            "model": (ModelConfig, "pneutune.model/1"),
            "controller": (ControllerConfig, "pneutune.controller/1")}


def json_schema(name: str) -> dict[str, Any]:
    """The JSON Schema of a contract: ``plant``, ``model`` or ``controller``."""
    model, title = _models()[name]
    schema = model.model_json_schema(by_alias=True, mode="validation")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = f"https://pneutune.invalid/schemas/{name}.schema.json"
    schema["title"] = title
    return schema


def schema_text(name: str) -> str:
    """The schema as the committed file's text."""
    return json.dumps(json_schema(name), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def schema_path(name: str) -> Path:
    """Where the committed schema of ``name`` lives."""
    return SCHEMA_DIR / f"{name}.schema.json"


def write_all() -> list[Path]:
    """Regenerate every committed schema file."""
    paths = []
    for name in _models():
        atomic_write_text(schema_path(name), schema_text(name))
        paths.append(schema_path(name))
    return paths


if __name__ == "__main__":  # pragma: no cover
    for p in write_all():
        print(p)
