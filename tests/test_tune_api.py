"""``pneutune.tune.tune``: the command as a library call.

The model is ``model_from_plant(PlantConfig())`` (the default plant's truth, every range ±20 %),
tuned in memory with quick settings (one 4 s scenario, two plants): a notebook's use.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import command_message
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune import TuneSettings, tune
from pneutune.tune.objective import ObjectiveSettings, TuneError, TuneObjective

QUICK = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=2, duration=4.0)


@pytest.mark.parametrize(("field", "value", "message"), [
    ("trials", 0, "trials must be >= 1, got 0"),
    ("workers", 0, "workers must be >= 1, got 0"),
    ("seed", -1, "seed must be >= 0, got -1"),
    ("jobs", 0, "jobs must be >= 1, got 0"),
    ("restarts", 0, "restarts must be >= 1, got 0"),
])
def test_settings_are_validated_in_the_library(field: str, value: int, message: str) -> None:
    """The library refuses what the command refuses; its message names the argument, and the
    command's (``command_message``) the flag."""
    kwargs = {"trials": 5, field: value}
    with pytest.raises(TuneError) as info:
        TuneSettings(**kwargs)
    assert str(info.value) == message
    assert command_message(info.value) == "--" + message


def test_a_model_in_memory_tunes_and_resumes(tmp_path: Path) -> None:
    """3 trials: the controller written equals the one returned, the summary is the --json
    object, and the same call again runs no trial (the study is resumed from its journal)."""
    model = model_from_plant(PlantConfig())
    settings = TuneSettings(trials=3, out=tmp_path, jobs=1, objective=QUICK)
    result = tune(model, settings)
    assert isinstance(result.controller, ControllerConfig)
    assert load_controller(result.paths["controller"]) == result.controller
    summary = result.summary()
    assert summary["trials"]["finished"] == 3 and summary["trials"]["this_run"] == 3
    assert summary["model"] == "<model>" and len(summary["model_sha256"]) == 64
    assert Path(summary["report"]).is_file()
    again = tune(model, settings)
    assert again.summary()["trials"]["this_run"] == 0
    assert again.best.number == result.best.number


def test_the_pid_baseline_is_tuned_with_the_same_objective(tmp_path: Path) -> None:
    """--variant pid: the study searches the pid block and the motion filter's Q, the first
    trial is contract 4's default PID (ki at its range's low end, 1e5), the controller written
    is a pid controller, and its study is not the DARC's (name ends in -pid)."""
    model = model_from_plant(PlantConfig())
    objective = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=2, duration=4.0,
                                  variant="pid")
    result = tune(model, TuneSettings(trials=3, out=tmp_path, jobs=1, objective=objective))
    assert result.controller.variant == "pid"
    assert set(result.best.params) == {"pid.kp", "pid.ki", "pid.kd", "pid.i_max",
                                       "kalman.motion.Q"}
    first = result.study.trials[0].params
    assert first["pid.kp"] == 3.0e6 and first["pid.ki"] == 1.0e5
    assert result.summary()["study"].endswith("-pid")


def test_the_report_scores_both_controllers_on_held_out_draws(tmp_path: Path) -> None:
    """Generalisation: report.md and --json score the tuned and the paper's gains on
    draws the study never saw (seed + HELDOUT_SEED_OFFSET). With 4 draws the Latin-hypercube
    plant (draw 3) is a new plant; the overfit figure is the ratio of ratios of the four
    objective values (recomputed here from the evaluations, to 1e-12)."""
    from pneutune.tune.report import HELDOUT_SEED_OFFSET

    model = model_from_plant(PlantConfig())
    objective = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=4, duration=4.0)
    result = tune(model, TuneSettings(trials=2, out=tmp_path, jobs=1, seed=5,
                                      objective=objective))
    comp = result.comparison
    held = comp.heldout
    assert held is not None and held.seed == 5 + HELDOUT_SEED_OFFSET
    study_draws = TuneObjective(model, 5, objective).draws
    assert held.objective.draws[3].values != study_draws[3].values  # a new plant
    assert held.objective.draws[0].values == study_draws[0].values  # the same nominal plant
    assert held.objective.draws[0].noise_seed != study_draws[0].noise_seed  # new noise
    summary = result.summary()["heldout"]
    ratio = ((held.tuned.value / comp.tuned.value) / (held.paper.value / comp.paper.value) - 1.0)
    assert summary["overfit"] == pytest.approx(ratio, rel=1e-12)
    assert set(summary["mean_E_p_mm"]["tuned"]) == {"sine-0.5hz"}
    text = Path(result.paths["report"]).read_text()
    assert "## Generalisation: held-out plants and noise" in text
    assert f"seed {5 + HELDOUT_SEED_OFFSET}" in text


@pytest.mark.parametrize(("tuned", "paper", "says"), [(1.2, 1.6, False), (1.6, 1.6, False),
                                                      (5.75, 4.91, True), (1.0, None, False)])
def test_a_tuned_controller_worse_than_the_papers_is_said(tuned: float, paper: float | None,
                                                          says: bool) -> None:
    """The kept trial scoring above the paper's controller on the study's plants gets a warning
    that names both objectives and what to do (5.75 vs 4.91: plant 1 of the fleet, a 12 s
    closed-loop log, 60 trials, before θ̂3(0) was searched;
    docs/notes/2026-11-26-tune-other-simulator.md)."""
    from types import SimpleNamespace

    from pneutune.tune.api import behind_paper

    comp = SimpleNamespace(tuned=SimpleNamespace(value=tuned), paper=SimpleNamespace(value=paper))
    line = behind_paper(comp, 58, TuneSettings(trials=60))  # type: ignore[arg-type]
    if not says:
        assert line is None
        return
    assert line is not None and line.startswith("warning: trial #58 scores 5.75")
    assert "(4.91)" in line and "--trials" in line and "--seed" in line


def test_restarts_keep_the_study_that_scores_best_on_the_selection_draws(tmp_path: Path) -> None:
    """restarts=2 on a plant with a 3 ms IO delay, where the paper's gains (every study's trial
    0) track badly: seed 3's study keeps trial 0, seed 4's a trial of its own. Each score is
    recomputed here from the kept trial's parameters on :func:`selection_objectives` (to
    1e-12); the two differ, and the lower is kept, here the second study's. The progress bar
    runs over both studies; the same call again resumes both and runs no trial."""
    import optuna

    from pneutune.tune.restarts import SELECTION_SEED_OFFSET, selection_objectives
    from pneutune.tune.space import controller_from_params
    from pneutune.tune.storage import DEFAULT_JOURNAL, open_storage

    model = model_from_plant(PlantConfig().with_updates({"io": {"delay": 0.003}}))
    settings = TuneSettings(trials=4, out=tmp_path, jobs=1, seed=3, restarts=2, objective=QUICK)
    calls: list[tuple[int, int]] = []
    result = tune(model, settings, progress=lambda done, total: calls.append((done, total)))
    rows = result.summary()["restarts"]
    assert [r["seed"] for r in rows] == [3, 4]
    assert rows[0]["study"] != rows[1]["study"]
    assert [(r["finished"], r["this_run"]) for r in rows] == [(4, 4), (4, 4)]
    assert calls[-1] == (8, 8) and all(a[0] <= b[0] for a, b in itertools.pairwise(calls))
    objectives = selection_objectives(model, 3, QUICK, jobs=1)
    assert [o.seed for o in objectives] == [3 + SELECTION_SEED_OFFSET, 4 + SELECTION_SEED_OFFSET]
    storage = open_storage(str(tmp_path / DEFAULT_JOURNAL))
    scores = []
    for r in rows:
        study = optuna.load_study(study_name=r["study"], storage=storage)
        ctl = controller_from_params(model, study.trials[r["trial"]].params)
        scores.append(sum(o.evaluate(ctl).value for o in objectives) / len(objectives))
        assert r["failed"] == 0 and r["score"] == pytest.approx(scores[-1], rel=1e-12)
    assert abs(scores[0] - scores[1]) > 0.01 * scores[0]
    kept = min(range(2), key=lambda i: scores[i])
    assert kept == 1 and [r["kept"] for r in rows] == [False, True]
    assert result.summary()["seed"] == 4
    assert result.best.number == rows[1]["trial"]
    assert result.study.study_name == rows[1]["study"]
    assert "## Restarts" in Path(result.paths["report"]).read_text()
    assert any("best of 2 restarts" in n for n in result.controller.provenance.notes)
    again = tune(model, settings).summary()["restarts"]
    assert [(r["finished"], r["this_run"]) for r in again] == [(4, 0), (4, 0)]
    assert [{k: v for k, v in r.items() if k != "this_run"} for r in again] == \
        [{k: v for k, v in r.items() if k != "this_run"} for r in rows]


def test_restarts_rank_by_failed_runs_then_score_on_common_runs() -> None:
    """The candidate with the fewest failed runs is kept even with a higher score; among equal
    counts the lowest score, each candidate scored only on the runs every candidate completed
    (CVaR α = 0.5 over those draws, the mean over the scenarios), so that a candidate that fails
    its worst plant gains nothing by it."""
    from types import SimpleNamespace

    from pneutune.tune.restarts import Candidate, select

    def runs(s1: tuple[float | None, ...], s2: tuple[float | None, ...]) -> dict:
        return {**{("s1", d): SimpleNamespace(cost=c) for d, c in enumerate(s1)},
                **{("s2", d): SimpleNamespace(cost=c) for d, c in enumerate(s2)}}

    table = {  # candidate -> its runs on scenarios s1, s2 (three draws each)
        0: runs((0.1, None, 0.1), (0.1, 0.1, 0.1)),
        1: runs((1.0, 3.0, 2.0), (1.0, 1.0, 1.0)),
        2: runs((1.0, 0.5, None), (1.0, 1.0, 1.0)),
        3: runs((0.3, 0.3, 9.0), (0.3, 0.3, 0.3)),  # fails nothing, worst on s1's draw 2
        4: runs((0.5, 0.5, None), (0.3, 0.3, 0.3)),  # fails exactly that run
    }

    class Fake:
        seed = 11
        settings = SimpleNamespace(cvar_alpha=0.5)

        def evaluate(self, ctl: int, stop_on_failure: bool = True) -> SimpleNamespace:
            failed = [k for k, r in table[ctl].items() if r.cost is None]
            return SimpleNamespace(runs=table[ctl],
                                   failure=f"aborted in {failed[0][0]}" if failed else None)

    def cands(*ids: int) -> list[Candidate]:
        return [Candidate(i, f"s{i}", SimpleNamespace(params={"i": i}, number=0, value=0.5))
                for i in ids]  # type: ignore[arg-type]

    def pick(*ids: int):
        return select(cands(*ids), [Fake()], lambda p: p["i"])  # type: ignore[arg-type]

    sel = pick(0, 1, 2)
    assert sel.kept == 1
    rows = sel.rows()
    assert [r["failed"] for r in rows] == [1, 0, 1]
    # runs every candidate completed: s1's draw 0, all of s2; CVaR_0.5 of one cost is itself
    assert [r["score"] for r in rows] == pytest.approx([0.1, 1.0, 1.0], rel=1e-12)
    assert "seed 0 0.1 with 1 failed runs (first: aborted in s1)" in sel.notes()[0]
    assert pick(0, 2).kept == 0  # both lose one run: the lower score on the runs both completed
    # 4 fails the plant where 3 is worst: on the same runs 3 scores 0.3 and 4 scores 0.4, so 3
    # is kept on failures alone and would be on the score too
    sel = pick(4, 3)
    assert [r["score"] for r in sel.rows()] == pytest.approx([0.4, 0.3], rel=1e-12)
    assert sel.kept == 1


def test_outputs_are_written_under_the_folder_lock(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Two runs on one --out never interleave their files: report.md and the plots are written
    while the run holds the folder's lock (another process's non-blocking flock is refused),
    right after controller.yaml, and the lock is free again afterwards."""
    import fcntl
    import os

    from pneutune.tune import api
    from pneutune.tune.storage import OUT_LOCK

    def held() -> bool:
        fd = os.open(tmp_path / OUT_LOCK, os.O_RDWR)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        finally:
            os.close(fd)  # closing drops a lock this fd took
        return False

    seen: list[bool] = []
    real = api.write_report

    def spy(out, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(held() and (Path(out) / "controller.yaml").is_file())
        return real(out, *args, **kwargs)

    monkeypatch.setattr(api, "write_report", spy)
    tune(model_from_plant(PlantConfig()),
         TuneSettings(trials=2, out=tmp_path, jobs=1, objective=QUICK))
    assert seen == [True]
    assert not held()
