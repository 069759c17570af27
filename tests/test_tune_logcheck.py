"""The model against its own log (tune/logcheck.py): the logged controller replayed on the
model's nominal plant beside the log's measured tracking, and the two warnings.

The log is a real closed loop written by ``deploy`` (the paper's controller, sine-0.5hz, 8 s,
on the simulated paper rig); the models are the rig itself read as a model
(``model_from_plant``), exact or with its friction tripled, pointed at that log.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from tune_helpers import QUICK, load_study, only_study_name, run_tune

from pneutune.control.cli.common import run_cli
from pneutune.control.cli.deploy import main as deploy_main
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.model import ModelConfig, save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.logcheck import RATIO, check_log
from pneutune.tune.space import motion_R

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "data" / "controller-paper.yaml"


@pytest.fixture(scope="module")
def logged(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(closed-loop log, the controller file that ran) from ``deploy``."""
    d = tmp_path_factory.mktemp("logcheck")
    ctrl = d / "controller.yaml"
    shutil.copy(PAPER, ctrl)
    log = d / "run.mcap"
    with pytest.raises(SystemExit) as exc:
        from pneutune.control.cli.common import run_cli
        run_cli(deploy_main, [str(ctrl), "--scenario", "sine-0.5hz", "--duration", "8",
                              "--log", str(log), "--seed", "4"])
    assert exc.value.code == 0
    return log, ctrl


def _model(log: Path, friction_factor: float = 1.0) -> ModelConfig:
    data = model_from_plant(PlantConfig()).to_dict()
    data["source"] = {"log": str(log), "sha256": sha256_file(log), "duration_s": 8.0}
    for key in ("F_C", "F_S", "b_v"):
        data["friction"][key] *= friction_factor
    data["friction"]["ranges"] = {k: [v[0] * friction_factor, v[1] * friction_factor]
                                  if k in ("F_C", "F_S", "b_v") else v
                                  for k, v in data["friction"]["ranges"].items()}
    return ModelConfig.model_validate(data)


def _slow(ctrl: ControllerConfig) -> ControllerConfig:
    data = ctrl.to_dict()
    data["gains"] = dict(data["gains"], k1=10.0, k2=300.0)  # the low ends of tune's ranges
    return ControllerConfig.model_validate(data)


def test_the_exact_model_tracks_like_its_log(logged: tuple[Path, Path]) -> None:
    """The plant that made the log, read as a model: the log's E_p lies within a factor RATIO
    of the three replays' (the same plant; only the noise draws differ) and nothing is said."""
    log, ctrl = logged
    paper = load_controller(ctrl)
    lc = check_log(_model(log), paper, seed=1)
    assert lc.skipped is None and lc.scenario == "sine-0.5hz"
    assert lc.measured is not None and len(lc.logged_on_model) == 3
    replays = [e for e, _ in lc.logged_on_model]
    assert min(replays) / RATIO <= lc.measured[0] <= RATIO * max(replays)
    assert lc.tuned_on_model == lc.logged_on_model  # the same controller, the same runs
    assert lc.warnings() == []
    assert "The rig tracked like the model" in "\n".join(lc.lines())


def test_a_model_with_triple_friction_is_called_pessimistic(logged: tuple[Path, Path]) -> None:
    """F_C, F_S and b_v x3 on the model: its replays track far worse than the log did."""
    log, ctrl = logged
    lc = check_log(_model(log, 3.0), load_controller(ctrl), seed=1)
    assert lc.measured is not None
    assert RATIO * lc.measured[0] < min(e for e, _ in lc.logged_on_model)
    (warning,) = lc.warnings()
    assert "the rig tracked better than the model" in warning and "pessimistic" in warning


def test_a_tuned_controller_worse_on_the_nominal_plant_is_said(logged: tuple[Path, Path]
                                                               ) -> None:
    """The exact model, and a 'tuned' controller with k1, k2 at the low ends of tune's ranges:
    worse than the logged one on the nominal plant, which the warning says."""
    log, ctrl = logged
    lc = check_log(_model(log), _slow(load_controller(ctrl)), seed=1)
    (warning,) = lc.warnings()
    assert "does worse than the logged one" in warning


@pytest.mark.parametrize("case", ["missing", "changed_log", "changed_controller", "open_loop"])
def test_nothing_is_checked_and_the_report_says_why(case: str, logged: tuple[Path, Path],
                                                    tmp_path: Path) -> None:
    log, ctrl = logged
    paper = load_controller(ctrl)
    model = _model(log)
    if case == "missing":
        data = model.to_dict()
        data["source"]["log"] = str(tmp_path / "gone.mcap")
        model, why = ModelConfig.model_validate(data), "is not at that path"
    elif case == "changed_log":
        copy = tmp_path / "run.mcap"
        shutil.copy(log, copy)
        with copy.open("ab") as fh:
            fh.write(b"\0")
        data = model.to_dict()
        data["source"]["log"] = str(copy)
        model, why = ModelConfig.model_validate(data), "has changed since identify"
    elif case == "changed_controller":
        saved = ctrl.read_bytes()
        ctrl.write_bytes(saved + b"\n# edited\n")
        try:
            lc = check_log(model, paper, seed=1)
        finally:
            ctrl.write_bytes(saved)
        assert lc.skipped is not None and "has changed since the run" in lc.skipped
        return
    else:
        run = ROOT / "data" / "run.mcap"
        data = model.to_dict()
        data["source"] = {"log": str(run), "sha256": sha256_file(run), "duration_s": 1.0}
        model, why = ModelConfig.model_validate(data), "it is not a closed-loop run"
    lc = check_log(model, paper, seed=1)
    assert lc.skipped is not None and why in lc.skipped, lc.skipped
    assert lc.warnings() == [] and lc.lines()[2].startswith("Not checked: ")


def test_a_log_of_a_homing_move_that_faulted_is_not_checked(tmp_path: Path) -> None:
    """deploy's log when a fault stopped the homing move (p_a NaN at 1 s of a move from 10 mm)
    holds no scenario: nothing to replay."""
    from pneutune.control.rig.faults import Fault, FaultySimRig
    from pneutune.control.rig.runtime import run_scenario
    from pneutune.control.sim.closed_loop import scenario_plant
    from pneutune.control.sim.scenarios import SCENARIOS

    sc = SCENARIOS["sine-0.5hz"]
    rig = FaultySimRig(scenario_plant(PlantConfig(), sc), faults=[Fault("nan", 1.0, "p_a")],
                       x0=0.010, seed=1)
    res = run_scenario(load_controller(PAPER), sc, rig)
    assert res.homing is not None and res.fault is not None
    log = tmp_path / "homing.mcap"
    res.save_log(str(log), run={"controller": str(PAPER),
                                "controller_sha256": sha256_file(PAPER)})
    lc = check_log(_model(log), load_controller(PAPER), seed=1)
    assert lc.skipped is not None and "homing move" in lc.skipped, lc.skipped


def test_the_controller_that_ran_in_the_log_is_a_trial_of_the_study(
        logged: tuple[Path, Path], tmp_path: Path) -> None:
    """A re-tune after a re-identification starts from the controller on the rig: tune enqueues
    the searched parameters of the log's controller right after the paper's (trial 1), with the
    motion filter's Q/R kept under the model's R. The paper's own controller (the fixture's log)
    is trial 0 already and is not enqueued twice."""
    paper_log, _ = logged
    paper_model = tmp_path / "paper-model.yaml"
    save_model(_model(paper_log), paper_model)
    code, _, err = run_tune(["--model", str(paper_model), "--trials", "2", "--out",
                             str(tmp_path / "paper-tune"), *QUICK])
    assert code == 0 and "the controller that ran in the log" not in err, err

    data = yaml.safe_load(PAPER.read_text(encoding="utf-8"))
    data["gains"].update(k1=100.0, k2=9000.0, h3=150.0)
    data["adaptation"]["gamma"][2] = 3000.0
    ctrl = tmp_path / "retuned.yaml"
    ctrl.write_text(yaml.safe_dump(data), encoding="utf-8")
    log = tmp_path / "run.mcap"
    with pytest.raises(SystemExit) as exc:
        run_cli(deploy_main, [str(ctrl), "--scenario", "sine-0.5hz", "--duration", "8",
                              "--log", str(log), "--seed", "4"])
    assert exc.value.code == 0
    model = _model(log)
    model_path = tmp_path / "model.yaml"
    save_model(model, model_path)
    out = tmp_path / "tune"
    code, _, err = run_tune(["--model", str(model_path), "--trials", "3", "--out", str(out),
                               *QUICK])
    assert code == 0, err
    assert "the controller that ran in the log" in err
    storage = str(out / "study.journal")
    trial = load_study(storage, only_study_name(storage)).trials[1].params
    logged = load_controller(ctrl)
    assert trial["gains.k1"] == 100.0 and trial["gains.k2"] == 9000.0
    assert trial["gains.h3"] == 150.0 and trial["adaptation.gamma.b_v"] == 3000.0
    q_over_r = logged.kalman.motion.Q / logged.kalman.motion.R
    assert trial["kalman.motion.Q"] / motion_R(model) == pytest.approx(q_over_r, rel=1e-12)
