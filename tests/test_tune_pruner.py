"""tune --pruner: per-run reports for the Wilcoxon pruner, the value of a completed trial, and
a study keeping its pruner on resume.

Expected values come from the definitions in ``tune/objective.py`` (instance ids, the chunks of
draws, the objective: the mean over scenarios of the CVaR over draws) and ``tune/pruners.py`` (the
pruner stored with a study). Values computed twice from the same bit-identical runs are compared
with a relative tolerance of 1e-12 (the same floating-point operations in the same order; the
tolerance only allows for nothing more than rounding).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import optuna
import pytest
from tune_helpers import QUICK, load_study, write_truth_model

from pneutune.control.cli.common import run_cli
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune import cli
from pneutune.tune.api import TuneSettings
from pneutune.tune.objective import (
    FAIL_VALUE,
    INSTANCE_CHUNK,
    ObjectiveSettings,
    TuneError,
    TuneObjective,
    estimate_from_best,
)
from pneutune.tune.pruners import (
    DEFAULT_PRUNER,
    PRUNERS,
    StagedPercentilePruner,
    make_pruner,
    study_pruner,
)

MODEL = model_from_plant(PlantConfig())
#: Two short scenarios on eight plants: 16 runs in four chunks of INSTANCE_CHUNK draws.
SETTINGS = ObjectiveSettings(scenarios=("sine-0.5hz", "square-0.5hz"), n_draws=8, duration=3.0)
REL = 1e-12


def _objective(**kw: object) -> TuneObjective:
    return TuneObjective(MODEL, seed=1, settings=SETTINGS, instance_reports=True,
                         **kw)  # type: ignore[arg-type]


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        run_cli(cli.main, argv)
    cap = capsys.readouterr()
    return int(exc.value.code), cap.out, cap.err


def test_chunks_partition_the_draws_and_the_order_is_a_seeded_permutation() -> None:
    obj = _objective()
    assert INSTANCE_CHUNK == 4
    assert obj.draw_chunks == ((0, 2, 4, 6), (1, 3, 5, 7))  # one corner draw in each
    everything = sorted((s, c) for s in range(2) for c in range(2))
    orders = [obj.instance_order(n) for n in range(8)]
    assert all(sorted(o) == everything for o in orders)
    assert len({tuple(o) for o in orders}) > 1  # shuffled per trial
    assert obj.instance_order(5) == _objective().instance_order(5)  # same seed, same order
    assert obj.instance_id(1, 3) == 11  # scenario index * draws + draw index


def test_instance_evaluation_gives_the_full_objective_in_any_order() -> None:
    obj = _objective()
    controller = obj.controller(obj.space.paper_params())
    full = obj.evaluate(controller)
    assert full.value is not None
    for n in (0, 7):
        ev = obj.evaluate_instances(controller, obj.instance_order(n))
        assert ev.value == pytest.approx(full.value, rel=REL)
        assert ev.running == pytest.approx(full.running, rel=REL)
        assert ev.scenario_cvar == pytest.approx(full.scenario_cvar, rel=REL)
        assert sorted(i for i, _ in ev.reported) == list(range(16))
        for s_index, sc in enumerate(obj.scenarios):
            for d in range(8):
                cost = dict(ev.reported)[obj.instance_id(s_index, d)]
                assert cost == pytest.approx(full.runs[(sc.name, d)].cost, rel=REL)


def test_wilcoxon_study_prunes_on_a_subset_and_completes_with_the_full_objective() -> None:
    """Random gains against the paper's (trial 0): most are pruned after a chunk or two."""
    obj = _objective()
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0),
                                pruner=make_pruner("wilcoxon"))
    study.enqueue_trial(obj.space.paper_params())
    study.optimize(obj, n_trials=16)
    n_runs = 16
    states = [t.state for t in study.trials]
    assert optuna.trial.TrialState.COMPLETE in states
    tested = [t for t in study.trials
              if t.state == optuna.trial.TrialState.PRUNED and "failure" not in t.user_attrs]
    assert tested, "expected a trial stopped by the signed-rank test"
    for t in study.trials:
        steps = set(t.intermediate_values)
        if t.state == optuna.trial.TrialState.COMPLETE:
            assert steps == set(range(n_runs))  # every run reported, nothing else
            ev = obj.evaluate(obj.controller(t.params))
            assert t.value == pytest.approx(ev.value, rel=REL)
            continue
        assert t.state == optuna.trial.TrialState.PRUNED
        instances = steps - {n_runs}
        assert n_runs in steps  # the summary step the sampler ranks on
        assert instances < set(range(n_runs))  # a proper subset of the instances
        if "failure" in t.user_attrs:
            assert t.intermediate_values[n_runs] == FAIL_VALUE
        else:
            assert len(instances) % INSTANCE_CHUNK == 0  # stopped between chunks
            estimate = t.intermediate_values[n_runs]  # from the best trial of that moment
            assert np.isfinite(estimate) and estimate > 0.0


def test_a_pruned_trials_estimate_is_the_best_value_scaled_by_its_runs() -> None:
    """best value 0.5; the trial's runs cost 2x and 1x the best's: 0.5 * sqrt(2 * 1)."""
    study = optuna.create_study()
    assert estimate_from_best([(0, 2.0), (1, 4.0)], study) == pytest.approx(3.0, rel=REL)
    study.add_trial(optuna.trial.create_trial(
        params={}, distributions={}, value=0.5, intermediate_values={0: 1.0, 1: 2.0, 2: 3.0}))
    got = estimate_from_best([(0, 2.0), (1, 2.0)], study)
    assert got == pytest.approx(0.5 * np.sqrt(2.0), rel=REL)


def test_pruner_names_and_defaults() -> None:
    assert PRUNERS == ("staged", "wilcoxon", "median", "none")
    assert DEFAULT_PRUNER == "staged"
    staged = make_pruner("staged")
    assert isinstance(staged, StagedPercentilePruner)
    assert staged.later_percentile == 25.0 and staged.n_startup == 10
    assert isinstance(make_pruner("median"), optuna.pruners.MedianPruner)
    assert isinstance(make_pruner("none"), optuna.pruners.NopPruner)
    assert study_pruner(None, None) == DEFAULT_PRUNER  # a new study
    assert study_pruner({"seed": 1}, None) == "median"  # a study made before the option
    assert study_pruner({"pruner": "wilcoxon"}, "median") == "median"  # asked: checked later
    with pytest.raises(TuneError, match=r"^pruner must be one of"):
        TuneSettings(trials=3, pruner="hyperband")


def test_a_study_keeps_its_pruner_on_resume(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    model = write_truth_model(tmp_path)
    for pruner, out in ((None, "new"), ("wilcoxon", "w"), ("median", "old")):
        args = ["--model", str(model), "--out", str(tmp_path / out), *QUICK, "--json"]
        first = [*args, "--trials", "3"] + ([] if pruner is None else ["--pruner", pruner])
        code, stdout, stderr = _run(first, capsys)
        assert code == 0, stderr
        assert json.loads(stdout)["pruner"] == (pruner or DEFAULT_PRUNER)
        code, stdout, stderr = _run([*args, "--trials", "5"], capsys)  # resumed, no flag
        assert code == 0, stderr
        res = json.loads(stdout)
        assert res["pruner"] == (pruner or DEFAULT_PRUNER)
        assert res["trials"]["this_run"] == 2
        other = "wilcoxon" if (pruner or DEFAULT_PRUNER) == "median" else "median"
        code, _, stderr = _run([*args, "--trials", "6", "--pruner", other], capsys)
        assert code == 2
        assert "was created for another pruner" in stderr
    meta = load_study(str(tmp_path / "old" / "study.journal"),
                      res["study"]).user_attrs["pneutune"]
    assert "pruner" not in meta  # a median study's metadata is that of studies before the flag


def test_same_seed_same_trials_with_wilcoxon_pruning(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Pruning decisions do not depend on --jobs (chunks are fixed): the same study."""
    model = write_truth_model(tmp_path)
    quick = ["--scenarios", "sine-0.5hz,square-0.5hz", "--draws", "8", "--duration", "3.0",
             "--pruner", "wilcoxon"]
    results = []
    for run, jobs in (("a", "1"), ("b", "2")):
        code, stdout, err = _run(["--model", str(model), "--trials", "14", "--seed", "5",
                                  "--out", str(tmp_path / run), *quick, "--jobs", jobs,
                                  "--json"], capsys)
        assert code == 0, err
        res = json.loads(stdout)
        study = load_study(str(tmp_path / run / "study.journal"), res["study"])
        results.append((res["best"], [(t.params, t.state, t.value, t.intermediate_values)
                                      for t in study.trials]))
    assert results[0] == results[1]
    assert any(s == optuna.trial.TrialState.PRUNED for _, s, _, _ in results[0][1])


def _trial(state: optuna.trial.TrialState, values: dict[int, float]) -> optuna.trial.FrozenTrial:
    done = state == optuna.trial.TrialState.COMPLETE
    return optuna.trial.create_trial(state=state, value=values[max(values)] if done else None,
                                     params={}, distributions={}, intermediate_values=values)


def _staged_study() -> optuna.Study:
    """Three complete trials, one pruned after the second step, one after the first."""
    complete, pruned = optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED
    study = optuna.create_study()
    for state, values in ((complete, {0: 1.0, 1: 2.0, 2: 2.0}),
                          (complete, {0: 2.0, 1: 4.0, 2: 4.0}),
                          (complete, {0: 1.5, 1: 5.0, 2: 5.0}),
                          (pruned, {0: 3.0, 1: 9.0}),  # stopped at step 1: past step 0
                          (pruned, {0: 10.0})):  # stopped at step 0: read at no step
        study.add_trial(_trial(state, values))
    return study


def test_the_staged_pruner_takes_the_median_then_the_best_quarter() -> None:
    """Step 0: the median of the trials past step 0, values 1, 2, 1.5, 3: 1.75 (the trial
    stopped at step 0 is not read). Step 1: the 25th percentile (numpy's linear rule) of 2, 4,
    5 and +inf for the trial stopped at step 1: 2 + 0.75 (4 - 2) = 3.5. The median pruner
    there reads the complete trials alone: 4 at step 1; the survivors alone would give the
    25th percentile of 2, 4, 5: 3.0."""
    study = _staged_study()
    pruner = StagedPercentilePruner(n_startup_trials=3)
    median = optuna.pruners.MedianPruner(n_startup_trials=3)
    running = optuna.trial.TrialState.RUNNING

    def stops(p: optuna.pruners.BasePruner, values: dict[int, float]) -> bool:
        return p.prune(study, _trial(running, values))

    assert not stops(pruner, {0: 1.75})
    assert stops(pruner, {0: 1.76})
    assert not stops(pruner, {0: 0.5, 1: 3.5})
    assert stops(pruner, {0: 0.5, 1: 3.51})
    assert not stops(pruner, {0: 0.5, 1: 3.25})  # the survivors' 3.0 would stop it
    assert not stops(median, {0: 0.5, 1: 3.75})  # what the median pruner keeps...
    assert stops(pruner, {0: 0.5, 1: 3.75})  # ...the best quarter stops
    assert stops(pruner, {0: 0.5, 1: float("nan")})
    # monotone in the value (the bound of pruning_oracle relies on it)
    grid = np.linspace(0.0, 10.0, 201)
    for step in (0, 1):
        decisions = [stops(pruner, {**{s: 0.5 for s in range(step)}, step: v}) for v in grid]
        assert decisions == sorted(decisions)


def test_the_staged_pruner_waits_for_its_start_up_trials() -> None:
    """Three complete trials, four needed: nothing is stopped, however bad."""
    pruner = StagedPercentilePruner(n_startup_trials=4)
    running = optuna.trial.TrialState.RUNNING
    assert not pruner.prune(_staged_study(), _trial(running, {0: 1e9}))
    with pytest.raises(ValueError, match="later_percentile"):
        StagedPercentilePruner(later_percentile=120.0)
