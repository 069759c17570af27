"""The pruners of ``--pruner``.

Pruning (``--pruner``, :func:`make_pruner`): ``staged`` (the default,
:class:`StagedPercentilePruner`): on the running mean after each scenario, the median after the
first scenario and the best quarter after each later one; ``median``: ``MedianPruner`` on the
running mean after each scenario (every study made before the option); ``wilcoxon``:
Optuna's ``WilcoxonPruner`` on per-run reports (each (scenario, draw) run's cost at its instance
id, :class:`~pneutune.tune.objective.TuneObjective` with ``instance_reports``), which stops a
trial once a signed-rank test over the runs done so far finds it worse than the best trial on
the same runs; ``none``. A study keeps its pruner (stored with it when not ``median``); without
``--pruner`` a resumed study uses its own.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
import optuna
from optuna.trial import FrozenTrial, TrialState

from pneutune.control.errors import argument_error

from .objective import TuneError

#: MedianPruner start-up trials (TPE's are :data:`pneutune.tune.samplers.N_STARTUP_TRIALS`). (A
#: PercentilePruner keeping the best third was measured too: 30 % faster, but a worse best trial
#: on 3 of 3 studies.)
PRUNER_STARTUP_TRIALS = 10
#: Pruners of ``--pruner``.
PRUNERS: tuple[str, ...] = ("staged", "wilcoxon", "median", "none")
#: The pruner of a new study when none is asked for (``wilcoxon`` is about twice as fast but
#: found a worse best trial on some seeds: docs/tuning.md, "Pruning").
DEFAULT_PRUNER = "staged"
#: The pruner of a study whose metadata names none (made before the option).
LEGACY_PRUNER = "median"
#: WilcoxonPruner: p-value below which a trial is stopped as worse than the best one, and the
#: paired runs needed before any test (one chunk of draws).
WILCOXON_P_THRESHOLD = 0.1
WILCOXON_STARTUP_STEPS = 4
#: StagedPercentilePruner: the percentile of the trials past the first step that a trial must
#: be at or below after the first step (the median) and after each later step (the best quarter).
STAGED_FIRST_PERCENTILE = 50.0
STAGED_LATER_PERCENTILE = 25.0


class StagedPercentilePruner(optuna.pruners.PercentilePruner):
    """The median after the first step, a stricter percentile after each later one.

    The reference trials are those that went past the first step: the complete ones and those
    pruned at a later step (before this pruner, every trial that passed the first step's median
    completed, so this is the set ``MedianPruner`` compared with). At step 0 a trial is pruned
    when its value is above the median of theirs, as ``MedianPruner`` does. At a later step
    ``s`` it is pruned when its value is above the ``later_percentile`` of theirs at ``s``, a
    trial stopped at ``s`` or before counting as worse than any value (so the percentile is
    of the same set at every step, not of the survivors of the steps before, which would make
    each step stricter than the last).

    Only exact values are read: a trial's value at a step it went past is that scenario's
    running mean, whatever bound it was stopped on later. So stopping a scenario early on a lower
    bound (:func:`~pneutune.tune.objective.pruning_oracle`) never changes a decision, and the
    pruner prunes more as the value grows.

    Why the later steps can be stricter: on 36 studies of ``tune --trials 200`` on the fleet's
    models (docs/tuning.md, "Pruning"), the running mean after the first scenario ranked the
    complete trials as their objective does with a Spearman correlation of 0.82-0.98, after two
    scenarios 0.87-0.99 and after four 0.96-0.997. Replayed on those studies' complete trials
    in their order, the best quarter after each later scenario would have stopped none of the
    five best trials of any study, and saved 28 % of the later scenarios' runs. A trial outside
    the best quarter after a later scenario is one the TPE sampler files among the worse trials
    whatever its last scenarios give.

    Parameters
    ----------
    later_percentile : float
        Percentile (0-100) after each step but the first.
    n_startup_trials : int
        No pruning before this many trials completed.
    """

    def __init__(self, later_percentile: float = STAGED_LATER_PERCENTILE,
                 n_startup_trials: int = PRUNER_STARTUP_TRIALS) -> None:
        super().__init__(STAGED_FIRST_PERCENTILE, n_startup_trials=n_startup_trials,
                         n_warmup_steps=0, interval_steps=1)
        if not 0.0 <= later_percentile <= 100.0:
            raise ValueError(f"later_percentile must be in [0, 100], got {later_percentile}")
        self.later_percentile = float(later_percentile)
        self.n_startup = int(n_startup_trials)

    def prune(self, study: optuna.Study, trial: FrozenTrial) -> bool:
        """Whether ``trial`` stops at its last reported step (class docstring)."""
        step = trial.last_step
        if step is None:
            return False
        trials = study.get_trials(deepcopy=False,
                                  states=(TrialState.COMPLETE, TrialState.PRUNED))
        if sum(t.state == TrialState.COMPLETE for t in trials) < self.n_startup:
            return False
        value = trial.intermediate_values[step]
        if math.isnan(value):
            return True
        values = [_value_if_past(t, step) for t in trials if _past(t, 0)]
        if not values:
            return False
        pct = STAGED_FIRST_PERCENTILE if step == 0 else self.later_percentile
        return bool(value > float(np.percentile(np.asarray(values, dtype=float), pct)))


def _past(trial: FrozenTrial, step: int) -> bool:
    """``trial`` went past ``step``: it completed, or reported at a later step."""
    return trial.state == TrialState.COMPLETE or (
        bool(trial.intermediate_values) and max(trial.intermediate_values) > step)


def _value_if_past(trial: FrozenTrial, step: int) -> float:
    """``trial``'s value at ``step`` if it went past it, else +inf (it was stopped there or
    before: worse than any trial that went on)."""
    if _past(trial, step) and step in trial.intermediate_values:
        return float(trial.intermediate_values[step])
    return math.inf


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
    if name == "staged":
        return StagedPercentilePruner()
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


__all__ = [
    "DEFAULT_PRUNER",
    "LEGACY_PRUNER",
    "PRUNERS",
    "PRUNER_STARTUP_TRIALS",
    "STAGED_FIRST_PERCENTILE",
    "STAGED_LATER_PERCENTILE",
    "WILCOXON_P_THRESHOLD",
    "WILCOXON_STARTUP_STEPS",
    "StagedPercentilePruner",
    "check_pruner",
    "make_pruner",
    "study_pruner",
]
