"""The model against its own log (tune/logcheck.py): the logged controller replayed on the
model's nominal plant beside the log's measured tracking, and the two warnings; and what
identify records of the log for it (identify/run_record.py, model.yaml's ``source.run``).

The log is a real closed loop written by ``deploy`` (the paper's controller, sine-0.5hz, 8 s,
on the simulated paper rig); the models are the rig itself read as a model
(``model_from_plant``), exact or with its friction tripled, with the log's record as identify
makes it. The check reads only that record: the log and the controller file are never opened.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from tune_helpers import QUICK, load_study, only_study_name, run_tune

from pneutune.control.cli.common import run_cli
from pneutune.control.cli.deploy import main as deploy_main
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.model import LoggedRun, ModelConfig, load_model, save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ConfigError
from pneutune.control.logs.reader import read_run_log
from pneutune.control.sim.truth import model_from_plant
from pneutune.identify.pipeline import identify
from pneutune.identify.run_record import run_record
from pneutune.tune.logcheck import RATIO, check_log, logged_controller
from pneutune.tune.space import motion_R

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "data" / "controller-paper.yaml"
#: The fixture's log: 8 s at the 4 ms control period, indices over three 2 s sine periods.
SAMPLES, WINDOW = 2000, 1500


def _deploy(folder: Path, ctrl: Path | str = "controller.yaml", log: str = "run.mcap") -> None:
    """``deploy CTRL --scenario sine-0.5hz --duration 8 --log LOG --seed 4`` run in ``folder``
    (the run record names the controller as given)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(folder)
        with pytest.raises(SystemExit) as exc:
            run_cli(deploy_main, [str(ctrl), "--scenario", "sine-0.5hz", "--duration", "8",
                                  "--log", log, "--seed", "4"])
    assert exc.value.code == 0


@pytest.fixture(scope="module")
def logged(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(closed-loop log, the controller file that ran) from ``deploy``."""
    d = tmp_path_factory.mktemp("logcheck")
    ctrl = d / "controller.yaml"
    shutil.copy(PAPER, ctrl)
    _deploy(d, ctrl)
    return d / "run.mcap", ctrl


def _model(log: Path, friction_factor: float = 1.0, run: dict[str, Any] | None = None,
           record: bool = True) -> ModelConfig:
    """The default plant as a model, its source the log with the record identify makes of it
    (``run`` instead when given; none with ``record=False``)."""
    data = model_from_plant(PlantConfig()).to_dict()
    data["source"] = {"log": str(log), "sha256": sha256_file(log), "duration_s": 8.0}
    if record:
        data["source"]["run"] = run if run is not None else run_record(read_run_log(log))
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


def _indices(log: Path) -> tuple[float, float]:
    """The log's E_p and E_rms [mm] from its topics with numpy alone: |x - x_r| over the last
    WINDOW samples (three 2 s periods of sine-0.5hz at 4 ms)."""
    rl = read_run_log(log)
    e = (rl["/rig/sensors"]["x"].to_numpy() - rl["/control/reference"]["x_r"].to_numpy())
    e = e[-WINDOW:]
    return float(np.max(np.abs(e)) * 1e3), float(np.sqrt(np.mean(e**2)) * 1e3)


def test_identify_records_the_closed_loop_of_the_log(logged: tuple[Path, Path]) -> None:
    """The record of deploy's log: closed loop, its scenario and controller as the run record
    names them, the controller's content as the file holds it, 2000 samples (8 s at 4 ms) and
    the indices the log's own topics give (the same samples and arithmetic: rel 1e-12)."""
    log, ctrl = logged
    run = LoggedRun.model_validate(run_record(read_run_log(log)))
    assert run.closed_loop and not run.homing_fault and run.scenario == "sine-0.5hz"
    assert run.controller == str(ctrl) and run.controller_sha256 == sha256_file(ctrl)
    assert run.controller_config == load_controller(ctrl) and run.controller_missing is None
    assert run.samples == SAMPLES
    e_p, e_rms = _indices(log)
    assert run.E_p_mm == pytest.approx(e_p, rel=1e-12)
    assert run.E_rms_mm == pytest.approx(e_rms, rel=1e-12)
    assert 0.0 < run.E_rms_mm < run.E_p_mm < 1.0  # mm: the paper's controller tracks


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


def test_a_model_whose_logs_are_gone_still_gets_its_check(tmp_path: Path) -> None:
    """deploy and identify in one folder (relative names, as on a rig's PC), model.yaml moved
    elsewhere, then the log and the controller file deleted: the check reads model.yaml alone
    and gives what it gave before the deletion (the same records and noise seeds: equal), the
    rig's E_p being the log's own (rel 1e-12). The identified model tracks like the rig: the
    log's E_p within a factor RATIO of the replays (the model comes from this log)."""
    rig_pc = tmp_path / "rig"
    rig_pc.mkdir()
    shutil.copy(PAPER, rig_pc / "controller.yaml")
    _deploy(rig_pc)
    e_p, e_rms = _indices(rig_pc / "run.mcap")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(rig_pc)
        model = identify(["run.mcap"]).model
    paper = load_controller(PAPER)
    before = check_log(model, paper, seed=1)
    moved = tmp_path / "elsewhere" / "model.yaml"
    moved.parent.mkdir()
    save_model(model, moved)
    shutil.rmtree(rig_pc)
    loaded = load_model(moved)
    assert loaded.sources[0].log == "run.mcap" and loaded.sources[0].run is not None
    assert loaded.sources[0].run.controller == "controller.yaml"
    lc = check_log(loaded, paper, seed=1, model_path=str(moved))
    assert lc.skipped is None and lc.scenario == "sine-0.5hz" and lc.measured is not None
    assert (lc.log, lc.controller, lc.measured) == (before.log, before.controller,
                                                    before.measured)
    np.testing.assert_array_equal(lc.logged_on_model, before.logged_on_model)
    np.testing.assert_array_equal(lc.tuned_on_model, before.tuned_on_model)
    assert lc.measured[0] == pytest.approx(e_p, rel=1e-12)
    assert lc.measured[1] == pytest.approx(e_rms, rel=1e-12)
    replays = [e for e, _ in lc.logged_on_model]
    assert min(replays) / RATIO <= lc.measured[0] <= RATIO * max(replays)
    cfg, name = logged_controller(loaded, str(moved))
    assert cfg == paper and name == "controller.yaml"


def test_a_model_without_the_record_says_to_identify_again(logged: tuple[Path, Path]) -> None:
    """A model.yaml whose source has no ``run`` (written before identify recorded it): nothing
    is checked, no controller is taken, and both say to run identify again."""
    log, ctrl = logged
    model = _model(log, record=False)
    assert model.sources[0].run is None
    lc = check_log(model, load_controller(ctrl), seed=1)
    assert lc.skipped is not None and "run identify again" in lc.skipped, lc.skipped
    assert lc.warnings() == [] and lc.lines()[2].startswith("Not checked: ")
    cfg, why = logged_controller(model)
    assert cfg is None and "run identify again" in why


@pytest.mark.parametrize("case", ["changed", "gone", "beside", "open_loop"])
def test_what_identify_finds_of_the_controller_decides_the_check(
        case: str, logged: tuple[Path, Path], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The controller file as identify finds it when it reads the log: changed since the run
    (sha256) or gone, it is recorded as ``controller_missing`` and nothing is checked; named
    relative to a folder that is not the working directory, it is found beside the log; an
    identification run (data/run.mcap) is no closed loop."""
    log, ctrl = logged
    paper = load_controller(ctrl)
    if case == "open_loop":
        run = ROOT / "data" / "run.mcap"
        rec = run_record(read_run_log(run))
        assert rec["closed_loop"] is False and "samples" not in rec and "E_p_mm" not in rec
        data = _model(log).to_dict()
        data["source"] = {"log": str(run), "sha256": sha256_file(run), "duration_s": 1.0,
                          "run": rec}
        lc = check_log(ModelConfig.model_validate(data), paper, seed=1)
        assert lc.skipped is not None and "it is not a closed-loop run" in lc.skipped
        return
    folder = tmp_path / "rig"
    folder.mkdir()
    shutil.copy(PAPER, folder / "controller.yaml")
    _deploy(folder)  # the run record names `controller.yaml`, relative to the folder
    if case == "changed":
        with (folder / "controller.yaml").open("a", encoding="utf-8") as fh:
            fh.write("\n# edited after the run, before identify\n")
        why = "`controller.yaml` has changed since the run (sha256)"
    elif case == "gone":
        (folder / "controller.yaml").unlink()
        why = "the controller that ran (`controller.yaml`) is not at that path nor beside the log"
    monkeypatch.chdir(tmp_path)  # not the folder: `controller.yaml` is not found from here
    rec = run_record(read_run_log(folder / "run.mcap"))
    assert rec["controller"] == "controller.yaml" and rec["samples"] == SAMPLES
    if case == "beside":
        assert "controller_missing" not in rec
        assert LoggedRun.model_validate(rec).controller_config == paper
        assert check_log(_model(folder / "run.mcap"), paper, seed=1).skipped is None
        return
    assert rec["controller_missing"] == why and "controller_config" not in rec
    e_p, _ = _indices(folder / "run.mcap")  # measured all the same
    assert rec["E_p_mm"] == pytest.approx(e_p, rel=1e-12)
    model = _model(folder / "run.mcap", run=rec)
    lc = check_log(model, paper, seed=1)
    assert lc.skipped == f"identify recorded no controller for it: {why}", lc.skipped
    assert lc.controller == "controller.yaml" and lc.scenario == "sine-0.5hz"
    assert lc.warnings() == [] and lc.lines()[2].startswith("Not checked: ")
    cfg, reason = logged_controller(model)
    assert cfg is None and why in reason


def test_a_log_of_a_homing_move_that_faulted_is_not_checked(tmp_path: Path) -> None:
    """deploy's log when a fault stopped the homing move (p_a NaN at 1 s of a move from 10 mm)
    holds no scenario: recorded as ``homing_fault`` without indices, nothing to replay."""
    from pneutune.control.rig.faults import Fault, FaultySimRig
    from pneutune.control.rig.scenario_run import run_scenario
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
    rec = run_record(read_run_log(log))
    assert rec["homing_fault"] is True and "E_p_mm" not in rec
    lc = check_log(_model(log, run=rec), load_controller(PAPER), seed=1)
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
    _deploy(tmp_path, ctrl)
    model = _model(tmp_path / "run.mcap")
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


@pytest.mark.parametrize(("edit", "key", "message"), [
    (lambda src: src["run"].__setitem__("closed_loop", "maybe"), "source.run.closed_loop",
     "expected true/false, got the string 'maybe'"),
    (lambda src: src.pop("sha256"), "source.sha256", "required key is missing"),
])
def test_a_bad_source_names_the_files_key(logged: tuple[Path, Path], tmp_path: Path,
                                          edit: Any, key: str, message: str) -> None:
    """``source`` is one log's mapping or a list of them (a union to pydantic, which puts the
    member's class name in the error's path and adds the other member's failure): the error
    names the key as written in the file, ``source.run.closed_loop``, and counts one problem."""
    data = _model(logged[0]).to_dict()
    edit(data["source"])
    path = tmp_path / "model.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_model(path)
    assert (exc.value.key, exc.value.message) == (key, message)
