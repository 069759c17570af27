"""From model.yaml to controller.yaml: scenarios x sampled plants, objective, Optuna study.

``tune(model, TuneSettings(trials=200))`` does what the ``tune`` command does
(:mod:`pneutune.tune.api`).
"""

from pneutune.tune.api import TuneResult, TuneSettings, tune

__all__ = ["TuneResult", "TuneSettings", "tune"]
