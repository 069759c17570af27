"""From run logs to model.yaml: data checks, fits, bounds and validation."""
