"""The held-out guard: the controller tune writes completes every run on held-out draws.

The study ranks its trials on its own plant draws. A trial can be best there and still go
unstable on another plant of the same box: fleet plant 1 read as a model, ``tune --seed 3``, had
its two best trials abort on a held-out draw (docs/tuning.md). Before controller.yaml is written,
:func:`guarded_best` scores the :data:`GUARD_TRIALS` best complete trials, best first, on guard
draws (the model's box with the seed ``seed + GUARD_SEED_OFFSET``: new sensor noise and new
Latin-hypercube plants beside the nominal plant and the two corners, which every set of draws
has) and keeps the first whose every run completes.

Only a failure moves the choice, never a better score on the guard draws: re-ranking the five
best by their held-out objective picked a worse controller on the true plant four times in
fifteen studies (docs/tuning.md, "The held-out guard").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import optuna
from optuna.trial import FrozenTrial, TrialState

from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.model import ModelConfig

from .objective import ObjectiveSettings, TuneObjective

#: The guard's plants and noise are drawn with ``seed + GUARD_SEED_OFFSET``.
GUARD_SEED_OFFSET = 2_000_029
#: How many of the best complete trials the guard tries before it gives up.
GUARD_TRIALS = 5


@dataclass(frozen=True)
class GuardResult:
    """What the guard chose.

    Attributes
    ----------
    trial : FrozenTrial
        The trial whose controller tune writes.
    rejected : tuple of (int, str)
        The better-ranked trials it passed over: number and the run that failed.
    seed : int
        Seed of the guard draws.
    passed : bool
        Whether ``trial`` completed every guard run (False: none of the trials tried did, and
        the study's best is kept).
    """

    trial: FrozenTrial
    rejected: tuple[tuple[int, str], ...]
    seed: int
    passed: bool

    def notes(self) -> list[str]:
        """What the user must know (nothing when the study's best passed)."""
        if self.passed and not self.rejected:
            return []
        failed = "; ".join(f"trial #{n}: {why}" for n, why in self.rejected)
        if self.passed:
            return [f"held-out guard (seed {self.seed}): the study's better trials fail a run on "
                    f"held-out draws ({failed}); trial #{self.trial.number} "
                    f"(objective {self.trial.value:.4g}) completes every run and is kept"]
        return [f"held-out guard (seed {self.seed}): none of the {len(self.rejected)} best "
                f"trials completes every run on held-out draws ({failed}); the "
                f"study's best is kept. The model's ranges may hold plants these gains cannot "
                f"hold: check plant-worst.yaml, or tune with more trials or another --seed"]


def guarded_best(study: optuna.Study, model: ModelConfig, seed: int,
                 settings: ObjectiveSettings, make: Callable[[Mapping[str, float]],
                                                             ControllerConfig],
                 jobs: int = 1, n_trials: int = GUARD_TRIALS) -> GuardResult:
    """The best complete trial whose controller completes every run on the guard draws.

    Parameters
    ----------
    study : optuna.Study
        A study with at least one complete trial.
    model : ModelConfig
        The model tuned on.
    seed : int
        The study's seed; the guard draws use ``seed + GUARD_SEED_OFFSET``.
    settings : ObjectiveSettings
        The study's objective settings (the same scenarios, draws and box).
    make : callable
        ``make(params) -> ControllerConfig``: a trial's controller.
    jobs : int
        Threads for the draws (:class:`~pneutune.tune.objective.TuneObjective`).
    n_trials : int
        How many of the best trials to try.

    Returns
    -------
    GuardResult
    """
    done = sorted((t for t in study.get_trials(deepcopy=False)
                   if t.state == TrialState.COMPLETE and t.value is not None),
                  key=lambda t: (t.value, t.number))[:max(1, n_trials)]
    if not done:
        raise ValueError(f"study {study.study_name!r} has no complete trial")
    guard_seed = seed + GUARD_SEED_OFFSET
    objective = TuneObjective(model, guard_seed, settings, jobs=jobs)
    rejected: list[tuple[int, str]] = []
    for t in done:
        ev = objective.evaluate(make(t.params), stop_on_failure=True)
        if ev.failure is None:
            return GuardResult(t, tuple(rejected), guard_seed, True)
        rejected.append((t.number, ev.failure))
    return GuardResult(done[0], tuple(rejected), guard_seed, False)


__all__ = ["GUARD_SEED_OFFSET", "GUARD_TRIALS", "GuardResult", "guarded_best"]
