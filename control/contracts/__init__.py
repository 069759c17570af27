"""The four file contracts as strict pydantic models: plant.yaml, model.yaml,
controller.yaml, their JSON Schemas, YAML reading and writing, atomic file output.

Layer 2: imports physics.
"""
