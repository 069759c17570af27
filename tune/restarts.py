"""Restarts: several independent studies of one model, and the choice between their controllers.

One TPE study of 200 trials lands in a different region with each seed, and how good that region
is on the true plant varies more between seeds than between the methods tried to improve a single
study (docs/tuning.md, "Restarts"). ``tune --restarts K`` runs K studies, seeds S..S+K-1 (each
its own draws, noise, feasibility check and held-out guard), and keeps the controller that
scores best on *selection draws*, the same for every candidate. Each study ranks its trials on
its own draws, so the studies' objectives are not comparable with one another; the selection
draws are.

The selection draws are :data:`SELECTION_SEEDS` sets of the objective's draws, with the seeds
``seed + SELECTION_SEED_OFFSET + j``: new sensor noise and new Latin-hypercube plants (the
nominal plant and the two corners of the box are in every set of draws, the studies' too).
Each set's box is narrowed by its own feasibility check
(:func:`pneutune.tune.feasibility.check_feasibility`), as a study's is. The kept candidate has
the fewest failed runs there, then the lowest score: the objective over the runs that every
candidate completed (:func:`select`), so that candidates are compared on the same plants.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
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
        Mean over the selection sets of the objective over the runs every candidate completed
        (nan: not scored, or no run that every candidate completed; :func:`common_score`).
    failed : int
        Runs that failed on the selection draws.
    failure : str or None
        The first of them.
    finished : int
        Finished (complete + pruned) trials the study holds.
    this_run : int
        Of them, those this run finished.
    """

    seed: int
    study: str
    trial: FrozenTrial
    score: float = math.nan
    failed: int = 0
    failure: str | None = None
    finished: int = 0
    this_run: int = 0


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
        """Per candidate: seed, study, its finished trials and those of this run, the kept
        trial and its study objective, selection score (None: not finite), failed runs, the
        first failure, kept."""
        return [{"seed": c.seed, "study": c.study, "finished": c.finished,
                 "this_run": c.this_run, "trial": c.trial.number, "objective": c.trial.value,
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
        The settings the studies started from (before their feasibility checks); each set's
        ``box`` is its own feasibility check's, or ``settings.box`` when that check finds the
        nominal plant untrackable.
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
            st = dataclasses.replace(settings, box=check_feasibility(model, s, settings,
                                                                     jobs=jobs).box)
        except InfeasibleModelError:
            st = settings
        out.append(TuneObjective(model, s, st, jobs=jobs))
    return out


def run_costs(ev: Evaluation) -> dict[tuple[str, int], float | None]:
    """Each run's cost of an evaluation run to the end: (scenario, draw) -> cost, None if the
    run failed."""
    return {key: rc.cost for key, rc in ev.runs.items()}


def common_score(costs: Mapping[tuple[str, int], float | None],
                 completed: set[tuple[str, int]], alpha: float) -> float:
    """The objective over the runs in ``completed``.

    Parameters
    ----------
    costs : mapping
        (scenario, draw) -> cost (:func:`run_costs`).
    completed : set
        The runs to score: those every candidate completed.
    alpha : float
        The objective's CVaR level.

    Returns
    -------
    float
        Mean over the scenarios with a run in ``completed`` of the CVaR over those runs' costs,
        as :meth:`~pneutune.tune.objective.TuneObjective.evaluate` aggregates (its value when
        every run is in ``completed``); nan when none is.
    """
    by: dict[str, list[float]] = {}
    for (scenario, draw), cost in costs.items():
        if (scenario, draw) in completed and cost is not None:
            by.setdefault(scenario, []).append(cost)
    if not by:
        return math.nan
    return float(np.mean([cvar(c, alpha) for c in by.values()]))


def select(candidates: Sequence[Candidate], objectives: Sequence[TuneObjective],
           make: Callable[[Mapping[str, float]], ControllerConfig]) -> Selection:
    """Score every candidate on the selection draws and keep the best.

    The best has the fewest failed runs, then the lowest score: per selection set the objective
    over the runs that every candidate completed (:func:`common_score`), averaged over the
    sets. A model whose ranges hold a plant that every candidate loses still gets the candidate
    that loses the fewest runs and tracks the same other plants best.

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
        Ties (and nan scores) keep the earliest restart.
    """
    ctls = [make(c.trial.params) for c in candidates]
    costs: list[list[dict[tuple[str, int], float | None]]] = []  # [candidate][set]
    failures: list[str | None] = []
    for ctl in ctls:
        per_set, failure = [], None
        for obj in objectives:
            ev = obj.evaluate(ctl, stop_on_failure=False)
            per_set.append(run_costs(ev))
            failure = failure or ev.failure
        costs.append(per_set)
        failures.append(failure)
    # per selection set, the runs every candidate completed
    completed = [{k for k in costs[0][j] if all(per[j].get(k) is not None for per in costs)}
                 for j in range(len(objectives))]
    scored = []
    for i, c in enumerate(candidates):
        values = [common_score(costs[i][j], completed[j], obj.settings.cvar_alpha)
                  for j, obj in enumerate(objectives)]
        failed = sum(v is None for per_set in costs[i] for v in per_set.values())
        score = float(np.mean(values)) if values and not any(math.isnan(v) for v in values) \
            else math.nan
        scored.append(dataclasses.replace(c, score=score, failed=failed, failure=failures[i]))

    def rank(i: int) -> tuple[int, float, int]:
        sc = scored[i].score
        return scored[i].failed, (math.inf if math.isnan(sc) else sc), i

    kept = min(range(len(scored)), key=rank)
    return Selection(tuple(scored), kept, tuple(o.seed for o in objectives))


__all__ = ["SELECTION_SEEDS", "SELECTION_SEED_OFFSET", "Candidate", "Selection", "common_score",
           "run_costs", "select", "selection_objectives"]
