"""The pruners of ``--pruner``.

Pruning (``--pruner``, :func:`make_pruner`): ``median`` (the default): ``MedianPruner`` on
the running mean after each scenario (also every study made before the option); ``wilcoxon``:
Optuna's ``WilcoxonPruner`` on per-run reports (each (scenario, draw) run's cost at its instance
id, :class:`~pneutune.tune.objective.TuneObjective` with ``instance_reports``), which stops a
trial once a signed-rank test over the runs done so far finds it worse than the best trial on
the same runs; ``none``. A study keeps its pruner (stored with it when not ``median``); without
``--pruner`` a resumed study uses its own.
"""

from __future__ import annotations

import warnings
from typing import Any

import optuna

from pneutune.control.errors import argument_error

from .objective import TuneError

#: MedianPruner start-up trials (TPE's are :data:`pneutune.tune.samplers.N_STARTUP_TRIALS`). (A
#: PercentilePruner keeping the best third was measured too: 30 % faster, but a worse best trial
#: on 3 of 3 studies.)
PRUNER_STARTUP_TRIALS = 10
#: Pruners of ``--pruner``.
PRUNERS: tuple[str, ...] = ("wilcoxon", "median", "none")
#: The pruner of a new study when none is asked for (``wilcoxon`` is about twice as fast but
#: found a worse best trial on some seeds: docs/tuning.md, "Pruning").
DEFAULT_PRUNER = "median"
#: The pruner of a study whose metadata names none (made before the option).
LEGACY_PRUNER = "median"
#: WilcoxonPruner: p-value below which a trial is stopped as worse than the best one, and the
#: paired runs needed before any test (one chunk of draws).
WILCOXON_P_THRESHOLD = 0.1
WILCOXON_STARTUP_STEPS = 4


def check_pruner(name: str | None) -> None:
    """Raise :class:`~pneutune.tune.objective.TuneError` unless ``name`` is None or one of
    :data:`PRUNERS`."""
    if name is not None and name not in PRUNERS:
        raise argument_error(TuneError, "pruner",
                             f"must be one of {', '.join(PRUNERS)}, got {name!r}")


def make_pruner(name: str) -> optuna.pruners.BasePruner:
    """The Optuna pruner of ``--pruner`` (module docstring).

    Parameters
    ----------
    name : str
        One of :data:`PRUNERS`.

    Returns
    -------
    optuna.pruners.BasePruner
    """
    check_pruner(name)
    if name == "wilcoxon":
        with warnings.catch_warnings():  # experimental in Optuna 3.6-5.x
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.pruners.WilcoxonPruner(p_threshold=WILCOXON_P_THRESHOLD,
                                                 n_startup_steps=WILCOXON_STARTUP_STEPS)
    if name == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=PRUNER_STARTUP_TRIALS,
                                           n_warmup_steps=0, interval_steps=1)
    return optuna.pruners.NopPruner()


def study_pruner(meta: dict[str, Any] | None, asked: str | None) -> str:
    """The pruner a study runs with: ``asked``, else the one stored in its metadata ``meta``
    (:data:`LEGACY_PRUNER` when it names none), else, for a new study (``meta`` None),
    :data:`DEFAULT_PRUNER`."""
    if asked is not None:
        return asked
    if meta is None:
        return DEFAULT_PRUNER
    return str(meta.get("pruner", LEGACY_PRUNER))


__all__ = ["DEFAULT_PRUNER", "LEGACY_PRUNER", "PRUNERS", "PRUNER_STARTUP_TRIALS",
           "WILCOXON_P_THRESHOLD", "WILCOXON_STARTUP_STEPS", "check_pruner", "make_pruner",
           "study_pruner"]
