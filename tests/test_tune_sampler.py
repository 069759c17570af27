"""``tune --sampler`` (docs/tuning.md, "Sampler"): TPE stays the default; ``cmaes`` is TPE, then
CMA-ES warm-started from the TPE trials; without the ``cmaes`` package the command exits 2 with
one ``error:`` line saying how to install it."""

from __future__ import annotations

import sys
from pathlib import Path

import optuna
import pytest

from pneutune.control.cli.common import run_cli
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune import TuneSettings, cli, samplers, tune
from pneutune.tune.objective import ObjectiveSettings
from pneutune.tune.study import StudySpec, default_study_name

QUICK = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=2, duration=2.0)


def test_the_default_sampler_stays_tpe() -> None:
    """Default everywhere is the TPE sampler tune always used, and the default study name is
    unchanged (so existing studies resume)."""
    assert TuneSettings(trials=1).sampler == "tpe"
    assert StudySpec("s.journal", "n", 1, 1, 1, "sha").sampler == "tpe"
    sampler = samplers.make_sampler("tpe", 7)
    assert type(sampler) is optuna.samplers.TPESampler
    assert default_study_name("ab" * 32, 3) == f"tune-{'ab' * 6}-seed3"
    assert default_study_name("ab" * 32, 3, sampler="cmaes") == f"tune-{'ab' * 6}-seed3-cmaes"


def test_the_default_tpe_samples_the_parameters_jointly() -> None:
    """The default TPE is multivariate whatever Optuna's own default (True from Optuna 5,
    False before): after its start-up trials it proposes every parameter from one joint
    density, so the relative search space it infers holds both parameters of this study."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=samplers.make_sampler("tpe", 3))
    study.optimize(lambda t: (t.suggest_float("x", 1e-3, 1.0, log=True) - 0.1) ** 2
                   + t.suggest_float("y", 0.0, 1.0) ** 2,
                   n_trials=samplers.N_STARTUP_TRIALS + 1)
    space = study.sampler.infer_relative_search_space(study, study.trials[-1])
    assert sorted(space) == ["x", "y"]


def test_cmaes_continues_a_tpe_warm_start(tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """With a warm start of 10 complete trials: the trials up to the 10th complete one are
    exactly those of the TPE study with the same seed (the paper's trial, then TPE's start-up
    points; some of them prune), the later ones are sampled by CMA-ES (they carry its
    generation attribute), and report.md names the sampler."""
    pytest.importorskip("cmaes")
    monkeypatch.setattr(samplers, "CMAES_WARM_START", 10)
    model = model_from_plant(PlantConfig())
    cma = tune(model, TuneSettings(trials=18, out=tmp_path / "cma", jobs=1, objective=QUICK,
                                   sampler="cmaes"))
    trials = cma.study.get_trials(deepcopy=False)
    complete = [t.number for t in trials if t.state.name == "COMPLETE"]
    warm = complete[9] + 1  # trials sampled by TPE: up to and with the 10th complete one
    assert len(trials) == 18 and warm <= 16, complete  # at least two CMA-ES trials
    tpe = tune(model, TuneSettings(trials=warm, out=tmp_path / "tpe", jobs=1, objective=QUICK))
    assert [t.params for t in trials[:warm]] == [t.params for t in tpe.study.trials]
    assert not any("cma:generation" in t.system_attrs for t in trials[:warm])
    assert all("cma:generation" in t.system_attrs for t in trials[warm:])
    summary = cma.summary()
    assert summary["sampler"] == "cmaes" and summary["study"].endswith("-cmaes")
    report = Path(summary["report"]).read_text()
    assert "sampler: CMA-ES warm-started from the first 10 complete TPE trials" in report


def test_cmaes_without_the_package_exits_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """`import cmaes` failing (simulated) is bad input: one error line with the install command,
    exit status 2, before any simulation."""
    monkeypatch.setitem(sys.modules, "cmaes", None)  # makes `import cmaes` raise ImportError
    with pytest.raises(SystemExit) as exc:
        run_cli(cli.main, ["--model", str(tmp_path / "missing.yaml"), "--trials", "3",
                           "--sampler", "cmaes", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err.count("error:") == 1 and err.startswith("error: --sampler cmaes needs the cmaes "
                                                       "package")
    assert "pip install 'pneutune[cmaes]'" in err
    assert not (tmp_path / "study.journal").exists()
    with pytest.raises(samplers.SamplerError, match="must be one of tpe, cmaes, gp"):
        TuneSettings(trials=1, sampler="random")
