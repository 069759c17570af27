"""A scenario the trial may be pruned after: its corner draws first, then two more, and a lower
bound that stops the trial without the other draws when the pruner would stop it anyway
(``TuneObjective.evaluate`` with ``would_prune``).

Expected values come from the definitions in ``tune/objective.py`` (the CVaR at level 0.25 over
eight draws is the mean of the two largest costs; costs are non-negative) and from running the
same study with and without the bound: the pruner must take the same decision on every trial.
"""

from __future__ import annotations

from pathlib import Path

import numba
import optuna
import pytest

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune import objective as objective_module
from pneutune.tune import report as report_module
from pneutune.tune.objective import ObjectiveSettings, TuneObjective, pruning_oracle
from pneutune.tune.pruners import StagedPercentilePruner
from pneutune.tune.samplers import tpe

MODEL = model_from_plant(PlantConfig())
#: Three short scenarios on eight plants (the CVaR averages the two worst).
SETTINGS = ObjectiveSettings(scenarios=("sine-0.5hz", "square-0.5hz", "sine-0.75hz"),
                             n_draws=8, duration=3.0)


def test_the_bound_is_the_mean_of_the_largest_known_costs() -> None:
    """k = ceil(0.25 * 8) = 2: of costs 5, 4, 1 the bound is (5 + 4) / 2; of one cost 3 it is
    3 / 2 (the other of the two largest is at least 0); a failed run gives no bound."""
    obj = TuneObjective(MODEL, seed=1, settings=SETTINGS, jobs=1)
    assert obj.scenario_bound([5.0, 1.0, 4.0]) == pytest.approx(4.5, rel=1e-15)
    assert obj.scenario_bound([3.0]) == pytest.approx(1.5, rel=1e-15)
    assert obj.scenario_bound([3.0, None]) is None
    # the two corners of the box, then two Latin-hypercube draws; the nominal plant runs last
    assert obj.bound_stages() == ((1, 2), (3, 4))
    # with more threads, as many draws a stage as threads (numba's thread count caps them)
    threads = min(4, numba.config.NUMBA_NUM_THREADS)
    wide = TuneObjective(MODEL, seed=1, settings=SETTINGS, jobs=4).bound_stages()
    assert wide == (((1, 2), (3, 4)) if threads <= 2 else ((1, 2, 3, 4), (5, 6, 7)))
    three = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=3, duration=3.0)
    # three draws: the CVaR is the worst one (ceil(0.25 * 3) = 1), a draw a stage on one thread
    assert TuneObjective(MODEL, seed=1, settings=three, jobs=1).bound_stages() == ((1,), (2,))
    two = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=2, duration=3.0)
    assert TuneObjective(MODEL, seed=1, settings=two, jobs=1).bound_stages() == ()


def test_the_bound_is_below_the_scenarios_cvar() -> None:
    """On the paper's gains and on three random gain sets, the bound from the corners is at
    most the scenario's CVaR over all eight draws (the costs from a full evaluation)."""
    obj = TuneObjective(MODEL, seed=1, settings=SETTINGS, jobs=1)
    random = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=5))
    for p in (obj.space.paper_params(), *(obj.space.suggest(random.ask()) for _ in range(3))):
        ev = obj.evaluate(obj.controller(p), stop_on_failure=False)
        first, second = obj.bound_stages()
        for sc in obj.scenarios:
            if sc.name not in ev.scenario_cvar:
                continue  # a failed run: no bound, nothing to compare
            for known in (first, first + second):
                bound = obj.scenario_bound([ev.runs[(sc.name, d)].cost for d in known])
                assert bound is not None and bound <= ev.scenario_cvar[sc.name]


#: The pruners the bound must not change: the median (the ``median`` pruner), and the median then
#: the best quarter (``staged``), which also reads the trials pruned after the first scenario.
PRUNERS = {
    "median": lambda: optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=0,
                                                  interval_steps=1),
    "staged": lambda: StagedPercentilePruner(n_startup_trials=3),
}


def _study(monkeypatch: pytest.MonkeyPatch, bound: bool, pruner: str) -> optuna.Study:
    if not bound:
        monkeypatch.setattr(objective_module, "pruning_oracle", lambda trial: None)
    obj = TuneObjective(MODEL, seed=1, settings=SETTINGS, jobs=1)
    study = optuna.create_study(sampler=tpe(3), pruner=PRUNERS[pruner]())
    study.enqueue_trial(obj.space.paper_params())
    study.optimize(obj, n_trials=30)
    monkeypatch.undo()
    return study


@pytest.mark.parametrize("pruner", sorted(PRUNERS))
def test_the_bound_changes_no_decision_of_the_pruner(monkeypatch: pytest.MonkeyPatch,
                                                    tmp_path: Path, pruner: str) -> None:
    """The same seeded study with and without the bound: the same parameters and states on
    every trial, the same value of every complete trial (bit for bit: the same runs), the same
    values reported before a pruned trial's last step, and at that step a value no higher; at
    least one trial stopped on the bound (a lower value there). A trial stopped on the bound, and
    only such a trial, says so in ``user_attrs["pruned_on_bound"]``, with fewer draws run than
    the scenario has: history.png draws its value as a lower bound."""
    with_bound = _study(monkeypatch, bound=True, pruner=pruner)
    without = _study(monkeypatch, bound=False, pruner=pruner)
    lowered = 0
    for a, b in zip(with_bound.trials, without.trials, strict=True):
        assert a.params == b.params
        assert a.state == b.state
        assert sorted(a.intermediate_values) == sorted(b.intermediate_values)
        if a.state == optuna.trial.TrialState.COMPLETE:
            assert a.value == b.value
            assert a.intermediate_values == b.intermediate_values
            continue
        last = max(a.intermediate_values)
        for step, value in a.intermediate_values.items():
            if step == last:
                assert value <= b.intermediate_values[step]
                lowered += value < b.intermediate_values[step]
                on_bound = a.user_attrs.get("pruned_on_bound")
                # the bound is reported a hair low (1e-12), so it is below the CVaR
                assert (on_bound is not None) == (value < b.intermediate_values[step])
                assert "pruned_on_bound" not in b.user_attrs
                if on_bound is not None:
                    assert 2 <= on_bound["draws_run"] < SETTINGS.n_draws
                    assert on_bound["scenario"] == SETTINGS.scenarios[last]
            else:
                assert value == b.intermediate_values[step]
    assert lowered > 0, "expected a trial stopped on the bound"
    assert with_bound.best_trial.number == without.best_trial.number
    saved = []
    monkeypatch.setattr(report_module, "save_figure", lambda fig, path: saved.append(fig))
    report_module.plot_history(with_bound, tmp_path / "history.png")
    labels = saved[0].axes[0].get_legend_handles_labels()[1]
    assert "pruned on a lower bound (value at least)" in labels


def test_no_oracle_where_a_pruned_value_could_steer_the_sampler() -> None:
    """CMA-ES reads pruned trials' values and the Wilcoxon pruner is no percentile: no bound."""
    for sampler, pruner in ((optuna.samplers.RandomSampler(seed=0),
                             optuna.pruners.MedianPruner()),
                            (tpe(0), optuna.pruners.NopPruner())):
        study = optuna.create_study(sampler=sampler, pruner=pruner)
        assert pruning_oracle(study.ask()) is None
    for pruner in (optuna.pruners.MedianPruner(), StagedPercentilePruner()):
        study = optuna.create_study(sampler=tpe(0), pruner=pruner)
        assert pruning_oracle(study.ask()) is not None
    assert pruning_oracle(optuna.trial.FixedTrial({})) is None  # no study behind it


def test_a_fixed_trial_is_scored_as_before() -> None:
    """Optuna's FixedTrial (an objective's debugging aid): the paper's gains score the value of
    a full evaluation, bit for bit (the same runs)."""
    obj = TuneObjective(MODEL, seed=1, settings=SETTINGS, jobs=1)
    params = obj.space.paper_params()
    value = obj(optuna.trial.FixedTrial(params))
    full = obj.evaluate(obj.controller(params))
    assert full.value is not None and value == full.value
