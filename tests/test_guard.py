"""The held-out guard (tune/guard.py): a trial that fails a run on new plants is passed over.

The model is the default plant's truth (``model_from_plant``). The failing controller is the
pid variant with every gain 0: Q_Ld = 0 closes all valves, the piston stays where it is, and the
sine reference leaves it by more than the 5 mm abort threshold within its first second, on any
plant. The paper's gains complete every run on this model (its trial 0 in every study).
"""

from __future__ import annotations

import optuna
import pytest

from pneutune.control.contracts.controller import PidConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.guard import GUARD_SEED_OFFSET, guarded_best
from pneutune.tune.objective import ObjectiveSettings
from pneutune.tune.space import controller_from_params, search_space

MODEL = model_from_plant(PlantConfig())
SPACE = search_space(MODEL)
SETTINGS = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=3, duration=2.0)
DEAD_K1 = 11.0  # a trial with this k1 gets the dead controller


def _make(params):
    cfg = controller_from_params(MODEL, params)
    if params["gains.k1"] == DEAD_K1:
        return cfg.model_copy(update={"variant": "pid", "pid": PidConfig(kp=0.0, ki=0.0, kd=0.0)})
    return cfg


def _study(values_and_k1: list[tuple[float, float]]) -> optuna.Study:
    study = optuna.create_study(study_name="guard-test")
    for value, k1 in values_and_k1:
        params = {**SPACE.paper_params(), "gains.k1": k1}
        study.add_trial(optuna.trial.create_trial(
            params=params, distributions=SPACE.distributions(), value=value))
    return study


def test_guard_passes_over_a_best_trial_that_fails_on_new_plants() -> None:
    """Best trial #0 aborts on the guard draws; #1 (the paper's gains) completes and is kept;
    #2 is never run. The note names both and the guard's seed."""
    study = _study([(0.5, DEAD_K1), (0.6, 65.0), (0.7, 65.0)])
    g = guarded_best(study, MODEL, 7, SETTINGS, _make)
    assert g.passed and g.trial.number == 1
    assert [n for n, _ in g.rejected] == [0]
    assert "aborted" in g.rejected[0][1]
    assert g.seed == 7 + GUARD_SEED_OFFSET
    (note,) = g.notes()
    assert "trial #0: aborted" in note and "trial #1 (objective 0.6) completes" in note


def test_guard_walks_the_trials_by_objective_not_by_number() -> None:
    """Trials added out of order (#0: 0.7, #1: 0.5 dead, #2: 0.6): the guard tries #1 first, then
    keeps #2; #0 is never reached."""
    study = _study([(0.7, 65.0), (0.5, DEAD_K1), (0.6, 65.0)])
    g = guarded_best(study, MODEL, 7, SETTINGS, _make)
    assert g.passed and g.trial.number == 2 and [n for n, _ in g.rejected] == [1]


def test_guard_tries_at_most_n_trials() -> None:
    """Seven dead trials and a good one ranked eighth: the default five are tried, none passes,
    and the study's best is kept with the warning."""
    study = _study([(0.1 * (k + 1), DEAD_K1) for k in range(7)] + [(0.9, 65.0)])
    g = guarded_best(study, MODEL, 7, SETTINGS, _make)
    assert not g.passed and g.trial.number == 0
    assert [n for n, _ in g.rejected] == [0, 1, 2, 3, 4]


def test_guard_keeps_the_best_when_it_passes_and_says_nothing() -> None:
    study = _study([(0.5, 65.0), (0.6, DEAD_K1)])
    g = guarded_best(study, MODEL, 7, SETTINGS, _make)
    assert g.passed and g.trial.number == 0 and g.rejected == () and g.notes() == []


def test_guard_keeps_the_best_and_warns_when_none_passes() -> None:
    study = _study([(0.5, DEAD_K1), (0.6, DEAD_K1)])
    g = guarded_best(study, MODEL, 7, SETTINGS, _make, n_trials=2)
    assert not g.passed and g.trial.number == 0 and len(g.rejected) == 2
    assert "none of the 2 best trials" in g.notes()[0]


def test_guard_needs_a_complete_trial() -> None:
    with pytest.raises(ValueError, match="no complete trial"):
        guarded_best(optuna.create_study(), MODEL, 7, SETTINGS, _make)
