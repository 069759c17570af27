"""Restarts: several independent studies of one model, and the choice between their controllers.

One TPE study of 200 trials lands in a different region with each seed, and how good that region
is on the true plant varies more between seeds than between the methods tried to improve a single
study (docs/tuning.md, "Restarts"). ``tune --restarts K`` runs K studies, seeds S..S+K-1 (each
its own draws, noise, feasibility check and held-out guard), and keeps the controller that
scores best on *selection draws*: plants and sensor noise none of the studies saw, the same for
every candidate. Each study ranks its trials on its own draws, so the studies' objectives are
not comparable with one another; the selection draws are.

The selection draws are :data:`SELECTION_SEEDS` sets of the objective's draws, with the seeds
``seed + SELECTION_SEED_OFFSET + j``; each set's box is narrowed by its own feasibility check
(:func:`pneutune.tune.feasibility.check_feasibility`), as a study's is. The kept candidate has
the fewest failed runs there, then the lowest score: the mean over the sets of the objective
over the completed runs (:func:`select`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from optuna.trial import FrozenTrial

from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.model import ModelConfig

from .feasibility import InfeasibleModelError, check_feasibility
from .objective import Evaluation, ObjectiveSettings, TuneObjective, cvar

#: The selection draws use the seeds ``seed + SELECTION_SEED_OFFSET + j``, j < SELECTION_SEEDS.
SELECTION_SEED_OFFSET = 3_000_017
#: How many sets of the objective's draws score the candidates.
SELECTION_SEEDS = 2


@dataclass(frozen=True)
class Candidate:
    """One restart's result.

    Attributes
    ----------
    seed : int
        The study's seed.
    study : str
        The study's name.
    trial : FrozenTrial
        The trial its held-out guard kept.
    score : float
        Mean over the selection sets of the objective over the completed runs (nan: not
        scored; :func:`selection_score`).
    failed : int
        Runs that failed on the selection draws.
    failure : str or None
        The first of them.
    """

    seed: int
    study: str
    trial: FrozenTrial
    score: float = math.nan
    failed: int = 0
    failure: str | None = None


@dataclass(frozen=True)
class Selection:
    """The candidates, scored, and the one kept.

    Attributes
    ----------
    candidates : tuple of Candidate
        In restart order.
    kept : int
        Index of the kept candidate.
    seeds : tuple of int
        Seeds of the selection draws.
    """

    candidates: tuple[Candidate, ...]
    kept: int
    seeds: tuple[int, ...]

    @property
    def chosen(self) -> Candidate:
        """The kept candidate."""
        return self.candidates[self.kept]

    def notes(self) -> list[str]:
        """One line for controller.yaml's provenance and the command's output."""
        c = self.chosen
        others = ", ".join(f"seed {o.seed} {_score(o)}" for i, o in enumerate(self.candidates)
                           if i != self.kept)
        return [f"best of {len(self.candidates)} restarts on selection draws (seeds "
                f"{', '.join(map(str, self.seeds))}): seed {c.seed} trial #{c.trial.number} "
                f"scored {_score(c)} (study objective {c.trial.value:.4g}); {others}"]

    def rows(self) -> list[dict[str, object]]:
        """Per candidate: seed, study, trial, study objective, selection score (None: not
        finite), failed runs, the first failure, kept."""
        return [{"seed": c.seed, "study": c.study, "trial": c.trial.number,
                 "objective": c.trial.value,
                 "score": c.score if math.isfinite(c.score) else None, "failed": c.failed,
                 "failure": c.failure, "kept": i == self.kept}
                for i, c in enumerate(self.candidates)]


def _score(c: Candidate) -> str:
    if c.failed:
        return f"{c.score:.4g} with {c.failed} failed runs (first: {c.failure})"
    return f"{c.score:.4g}"


def selection_objectives(model: ModelConfig, seed: int, settings: ObjectiveSettings,
                         jobs: int = 1) -> list[TuneObjective]:
    """The objectives on the selection draws of a tune with seed ``seed``.

    Parameters
    ----------
    model : ModelConfig
    seed : int
        The first restart's seed.
    settings : ObjectiveSettings
        The studies' settings; each set's ``box`` is its own feasibility check's (the studies'
        own box when the check finds no trackable nominal plant).
    jobs : int
        Threads for the draws.

    Returns
    -------
    list of TuneObjective
    """
    out = []
    for j in range(SELECTION_SEEDS):
        s = seed + SELECTION_SEED_OFFSET + j
        try:
            st = dataclasses.replace(settings, box=check_feasibility(model, s, settings).box)
        except InfeasibleModelError:
            st = settings
        out.append(TuneObjective(model, s, st, jobs=jobs))
    return out


def selection_score(ev: Evaluation, alpha: float) -> tuple[int, float]:
    """Failed runs and the objective over the completed ones of one evaluation.

    Parameters
    ----------
    ev : Evaluation
        An evaluation run to the end (``stop_on_failure=False``).
    alpha : float
        The objective's CVaR level.

    Returns
    -------
    failed : int
        Runs that failed.
    value : float
        Mean over the scenarios of the CVaR over the draws whose run completed (the objective
        itself when none failed); inf when a scenario has no completed run.
    """
    by: dict[str, list[float]] = {}
    failed = 0
    for (scenario, _), rc in ev.runs.items():
        costs = by.setdefault(scenario, [])
        if rc.cost is None:
            failed += 1
        else:
            costs.append(rc.cost)
    if not by or any(not c for c in by.values()):
        return failed, math.inf
    return failed, sum(cvar(c, alpha) for c in by.values()) / len(by)


def select(candidates: Sequence[Candidate], objectives: Sequence[TuneObjective],
           make: Callable[[Mapping[str, float]], ControllerConfig]) -> Selection:
    """Score every candidate on the selection draws and keep the best.

    The best has the fewest failed runs, then the lowest score (:func:`selection_score`,
    averaged over the sets): a model whose ranges hold a plant that every candidate loses still
    gets the candidate that loses the fewest runs and tracks the rest best.

    Parameters
    ----------
    candidates : sequence of Candidate
        The restarts' guarded trials, in restart order.
    objectives : sequence of TuneObjective
        From :func:`selection_objectives`.
    make : callable
        ``make(params) -> ControllerConfig``.

    Returns
    -------
    Selection
        Ties keep the earliest restart.
    """
    scored = []
    for c in candidates:
        ctl = make(c.trial.params)
        failed, values, failure = 0, [], None
        for obj in objectives:
            ev = obj.evaluate(ctl, stop_on_failure=False)
            n, value = selection_score(ev, obj.settings.cvar_alpha)
            failed += n
            values.append(value)
            failure = failure or ev.failure
        scored.append(dataclasses.replace(c, score=sum(values) / len(values), failed=failed,
                                          failure=failure))
    kept = min(range(len(scored)), key=lambda i: (scored[i].failed, scored[i].score, i))
    return Selection(tuple(scored), kept, tuple(o.seed for o in objectives))


__all__ = ["SELECTION_SEEDS", "SELECTION_SEED_OFFSET", "Candidate", "Selection", "select",
           "selection_objectives", "selection_score"]
