"""tune: search space, plant draws, objective, and the command end to end.

Expected values come from: the paper's Sec. 5.1 (gains, ε, Γ, Q/R), Table 1 (the normalisation
of the cost), ``model_from_plant`` (the truth model: every range ±20 % of the default plant) and
the definitions in ``tune/objective.py`` (CVaR, penalties).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import optuna
import pytest
from tune_helpers import QUICK, load_study, only_study_name, write_truth_model

from pneutune.control.cli.common import run_cli
from pneutune.control.cli.simulate import main as simulate_main
from pneutune.control.constants import WEAK_B_SPAN
from pneutune.control.contracts.controller import ProvenanceConfig, load_controller
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig, load_plant
from pneutune.control.contracts.yamlio import load_yaml_mapping, write_yaml
from pneutune.control.law.kalman import motion_model, process_cov, steady_state_gain
from pneutune.control.sim.closed_loop import Metrics, simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune import cli
from pneutune.tune.objective import (
    DEFAULT_SCENARIOS,
    FAIL_VALUE,
    ObjectiveSettings,
    TuneError,
    TuneObjective,
    cvar,
    run_cost,
)
from pneutune.tune.plants import draw_plants, nominal_plant, uncertainty_box
from pneutune.tune.space import (
    PAPER_Q_OVER_R,
    controller_from_params,
    params_from_controller,
    search_space,
    searches_theta_0,
)

MODEL = model_from_plant(PlantConfig())


# ---------------------------------------------------------------------------------------------
# search space
# ---------------------------------------------------------------------------------------------

def test_paper_params_give_the_sec51_gains_on_the_model() -> None:
    """The enqueued first trial is the paper's Sec. 5.1 controller with the model's θ box."""
    space = search_space(MODEL)
    cfg = controller_from_params(MODEL, space.paper_params())
    g = cfg.gains
    assert (g.k1, g.k2, g.k3, g.h2, g.h3, g.r2, g.r3) == (65.0, 6700.0, 50.0, 10.0, 100.0, 1.0,
                                                          0.1)
    assert (g.eps2, g.eps3) == (0.05, 250.0)  # fixed: only h²/ε enters the law
    assert cfg.adaptation.gamma == (0.2, 300.0, 2000.0, 500.0, 100.0, 100.0)
    assert cfg.adaptation.theta_min == MODEL.theta.min
    assert cfg.adaptation.theta_max == MODEL.theta.max
    assert all(lo < t0 < hi for lo, t0, hi in zip(cfg.adaptation.theta_min,
                                                  cfg.adaptation.theta_0,
                                                  cfg.adaptation.theta_max, strict=True))
    # motion R = the model's x_noise² (5 µm -> 2.5e-11 m²), Q at the paper's Q/R = 3.1e7
    assert cfg.kalman.motion.R == pytest.approx(2.5e-11, rel=1e-12)
    assert cfg.kalman.motion.Q / cfg.kalman.motion.R == pytest.approx(PAPER_Q_OVER_R, rel=1e-12)
    assert cfg.kalman.force.Q == pytest.approx(3100.0, rel=1e-12)
    assert cfg.valves == load_controller(
        Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml").valves
    searched = {k: v for k, v in params_from_controller(cfg).items() if k in space.names}
    assert searched == pytest.approx(space.paper_params(), rel=1e-15)


def _weak_b_model(half_width: float, model: ModelConfig = MODEL) -> ModelConfig:
    """``model`` with a_in's b range set to b ± ``half_width`` (the others unchanged)."""
    data = model.to_dict()
    v = data["valves"]["a_in"]
    v["b_min"], v["b_max"] = v["b"] - half_width, v["b"] + half_width
    return ModelConfig.model_validate(data)


#: The default plant's model with one valve's b as a short closed-loop log leaves it: identify
#: widens b by at least ±0.12 (PARTIAL_B_ERROR) when no valve is held fully open for 0.5 s.
WEAK_MODEL = _weak_b_model(0.12)


def test_theta_0_is_searched_only_where_a_valve_b_is_weakly_identified() -> None:
    """θ̂3(0) is the 15th parameter only on a model with a b range wider than WEAK_B_SPAN = 0.2
    (identify's "weakly identified"); the truth model's ranges (±20 % of b = 0.186, 0.074 wide)
    give 14 and the controller starts at the model's nominal θ3."""
    assert WEAK_B_SPAN == 0.2
    narrow = search_space(MODEL)
    assert len(narrow.params) == 14 and "adaptation.theta_0.b_v" not in narrow.names
    cfg = controller_from_params(MODEL, narrow.paper_params())
    assert cfg.adaptation.theta_0[2] == pytest.approx(MODEL.theta.nominal[2], rel=1e-12)
    assert cfg.adaptation.theta_max == MODEL.theta.max
    assert not searches_theta_0(_weak_b_model(0.0999))  # 0.1998 wide
    assert searches_theta_0(_weak_b_model(0.1001))  # 0.2002 wide
    wide = search_space(WEAK_MODEL)
    assert wide.names == (*narrow.names[:12], "adaptation.theta_0.b_v", *narrow.names[12:])


def test_space_is_log_scaled_around_the_paper_values() -> None:
    space = search_space(WEAK_MODEL)
    assert len(space.params) == 15
    for p in space.params:
        if p.name == "adaptation.theta_0.b_v":  # from the model's nominal θ3 up (docs/tuning.md)
            assert p.log and p.low == p.paper == MODEL.theta.nominal[2], p
            assert p.high == pytest.approx(4.0 * p.low, rel=1e-15), p
            continue
        assert p.log and p.low < p.paper < p.high, p
        assert p.high / p.low >= 10.0, p  # at least a decade


def test_motion_filter_range_reaches_20_rad_per_s() -> None:
    """The motion filter's Q/R spans 1e3-1e11 s^-4 over the model's R: estimator poles of about
    20 rad/s at the low end, 112 at the paper's 3.1e7, 430 at the top (steady-state gain at
    4 ms, computed here; docs/tuning.md)."""
    space = search_space(MODEL)
    q = next(p for p in space.params if p.name == "kalman.motion.Q")
    assert (q.low / space.R_motion, q.high / space.R_motion) == pytest.approx((1e3, 1e11))
    A, W, H = motion_model(0.004)
    for q_over_r, pole in ((1e3, 19.9), (3.1e7, 111.7), (1e11, 425.0)):
        K = steady_state_gain(A, process_cov(W, q_over_r), H, 1.0)
        z = np.linalg.eigvals((np.eye(3) - np.outer(K, H)) @ A)
        assert np.min(np.abs(np.log(z.astype(complex)))) / 0.004 == pytest.approx(pole, abs=0.5)


def test_at_ends_names_parameters_near_a_range_end() -> None:
    """5 % of the log span from an end is 'at' it; the paper's values are inside every range."""
    space = search_space(MODEL)
    assert space.at_ends(space.paper_params()) == []
    k1 = next(p for p in space.params if p.name == "gains.k1")  # 10-400 1/s
    span = math.log(k1.high / k1.low)
    near_low = k1.low * math.exp(0.049 * span)
    assert space.at_ends({"gains.k1": near_low}) == [("gains.k1", "low")]
    assert space.at_ends({"gains.k1": k1.low * math.exp(0.051 * span)}) == []
    assert space.at_ends({"gains.k1": k1.high}) == [("gains.k1", "high")]


def test_theta_0_of_b_v_moves_the_start_and_keeps_the_true_b_v_in_the_box() -> None:
    """θ̂3(0) searched: θ_0 of b_v is the trial's value, θ_max moves up in proportion, θ_min and
    every other θ stay the model's (Eq. 9 needs the true θ in the box)."""
    model = WEAK_MODEL
    space = search_space(model)
    b_v0 = model.theta.nominal[2]  # 3500 N s/m on the default plant, box [2800, 4200]
    assert (model.theta.min[2], model.theta.max[2]) == pytest.approx((2800.0, 4200.0))
    for factor, top in ((1.0, 4200.0), (1.2, 1.2 * 4200.0), (3.0, 3.0 * 4200.0)):
        cfg = controller_from_params(model, {**space.paper_params(),
                                             "adaptation.theta_0.b_v": factor * b_v0})
        a = cfg.adaptation
        assert a.theta_0[2] == pytest.approx(factor * b_v0, rel=1e-12)
        assert a.theta_max[2] == pytest.approx(top, rel=1e-12)
        assert a.theta_min == model.theta.min
        assert a.theta_max[:2] + a.theta_max[3:] == model.theta.max[:2] + model.theta.max[3:]
        assert params_from_controller(cfg)["adaptation.theta_0.b_v"] == pytest.approx(
            factor * b_v0, rel=1e-12)


def test_kalman_gain_depends_only_on_q_over_r() -> None:
    """Why R is not searched: scaling Q and R together leaves the filter gain unchanged."""
    A, W, H = motion_model(0.004)
    k1 = steady_state_gain(A, process_cov(W, 3.1e-3), H, 1e-10)
    k2 = steady_state_gain(A, process_cov(W, 3.1e-3 * 37.0), H, 1e-10 * 37.0)
    np.testing.assert_allclose(k1, k2, rtol=1e-9)


def test_h_and_eps_enter_only_as_h_squared_over_eps() -> None:
    """Why ε is not searched: (h, ε) and (2h, 4ε) give the same closed loop, sample for sample."""
    space = search_space(MODEL)
    cfg = controller_from_params(MODEL, space.paper_params())
    data = cfg.to_dict()
    data["gains"] = dict(data["gains"], h2=2 * cfg.gains.h2, eps2=4 * cfg.gains.eps2,
                         h3=2 * cfg.gains.h3, eps3=4 * cfg.gains.eps3)
    other = type(cfg).model_validate(data)
    sc = dataclasses.replace(SCENARIOS["sine-0.5hz"], duration=1.0)
    a = simulate_scenario(cfg, sc, PlantConfig(), seed=3)
    b = simulate_scenario(other, sc, PlantConfig(), seed=3)
    np.testing.assert_allclose(a.duties, b.duties, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# plants
# ---------------------------------------------------------------------------------------------

def test_nominal_plant_of_the_truth_model_is_the_default_plant() -> None:
    assert nominal_plant(MODEL, seed=1) == PlantConfig()


def test_draws_are_seeded_inside_the_box_with_corners() -> None:
    draws = draw_plants(MODEL, 7, seed=3)
    assert draws == draw_plants(MODEL, 7, seed=3)
    other = draw_plants(MODEL, 7, seed=4)
    assert draws[3].values != other[3].values  # Latin-hypercube draws follow the seed
    assert [d.label for d in draws] == ["nominal", "slow", "fast", "lhs-1", "lhs-2", "lhs-3",
                                        "lhs-4"]
    assert draws[0].noise_seed == 3
    assert len({d.noise_seed for d in draws}) == 7
    box = {c.key: c for c in uncertainty_box(MODEL)}
    # the truth model's ranges are ±20 %: mass 1.05 kg -> [0.84, 1.26]
    assert box["mass"].low == pytest.approx(0.84) and box["mass"].high == pytest.approx(1.26)
    assert draws[1].plant.mass == pytest.approx(1.26)  # slow corner: heaviest
    assert draws[1].plant.valves.a_in.C == pytest.approx(0.8 * 8.373e-9)  # and C_min
    assert draws[2].plant.mass == pytest.approx(0.84)  # fast corner: lightest
    for d in draws:
        assert d.plant.friction.F_S >= d.plant.friction.F_C
        for key, value in d.values.items():
            c = box[key]
            assert c.low - 1e-12 <= value <= c.high + 1e-12, (d.label, key, value)


# ---------------------------------------------------------------------------------------------
# objective
# ---------------------------------------------------------------------------------------------

def test_cvar_between_mean_and_worst() -> None:
    v = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    assert cvar(v, 0.25) == pytest.approx(7.5)  # worst two of eight
    assert cvar(v, 1.0) == pytest.approx(4.5)  # the mean
    assert cvar(v, 0.01) == pytest.approx(8.0)  # the worst case


def _metrics(**kw: float | str | bool) -> Metrics:
    base = dict(E_p_mm=0.42, E_rms_mm=0.19, switches_per_s=10.0, p_a_max_Pa=4.5e5,
                p_b_max_Pa=4.5e5, p_a_min_Pa=1.0e5, p_b_min_Pa=1.0e5, theta_in_bounds=True,
                end_stop_s=0.0, status="ok")
    base.update(kw)
    return Metrics(**base)  # type: ignore[arg-type]


def test_run_cost_is_one_at_table1_and_penalises() -> None:
    """Table 1's sine-0.5hz figures (0.42, 0.19 mm) cost exactly 1; penalties add as documented."""
    st = ObjectiveSettings()
    sc = SCENARIOS["sine-0.5hz"]
    p0, p_max = 101325.0, 6.5e5
    assert run_cost(_metrics(), sc, 0, p0, p_max, st).cost == pytest.approx(1.0, rel=1e-12)
    # 40 switches/s: ½ (40 - 20) / 20 = 0.5
    assert run_cost(_metrics(switches_per_s=40.0), sc, 0, p0, p_max, st).chatter == \
        pytest.approx(0.5)
    # 1 bar above p_max: 1 per bar + 1 once
    assert run_cost(_metrics(p_b_max_Pa=7.5e5), sc, 0, p0, p_max, st).pressure == \
        pytest.approx(2.0)
    # 0.5 s at an end stop: 2 (0.5 + 1)
    assert run_cost(_metrics(end_stop_s=0.5), sc, 0, p0, p_max, st).end_stop == \
        pytest.approx(3.0)
    bad = run_cost(_metrics(status="unstable"), sc, 0, p0, p_max, st)
    assert bad.cost is None and bad.failure == "unstable"
    nan = run_cost(_metrics(E_p_mm=float("nan")), sc, 0, p0, p_max, st)
    assert nan.cost is None and nan.failure == "non-finite metrics"
    # the disturbance scenario has no Table-1 row: normalised by the 0.5 Hz sine's
    assert run_cost(_metrics(), SCENARIOS["disturbance-0.5hz"], 0, p0, p_max, st).cost == \
        pytest.approx(1.0)


def test_bad_settings_are_typed_errors() -> None:
    with pytest.raises(TuneError, match="n_draws >= 1"):
        ObjectiveSettings(n_draws=0)
    with pytest.raises(TuneError, match="cvar_alpha"):
        ObjectiveSettings(cvar_alpha=0.0)
    with pytest.raises(ValueError, match="unknown scenario"):
        ObjectiveSettings(scenarios=("sine-9hz",))


def _quick_objective(**kw: object) -> TuneObjective:
    settings = ObjectiveSettings(scenarios=("sine-0.5hz", "square-0.5hz"), n_draws=2,
                                 duration=4.0, **kw)  # type: ignore[arg-type]
    return TuneObjective(MODEL, seed=1, settings=settings)


def test_unstable_runs_prune_the_trial_never_raise(monkeypatch: pytest.MonkeyPatch) -> None:
    obj = _quick_objective()

    def unstable(*_a: object, **_k: object) -> list[SimpleNamespace]:
        return [SimpleNamespace(metrics=_metrics(status="unstable", E_p_mm=float("nan")))
                for _ in obj.draws]

    monkeypatch.setattr(obj, "run_scenario", unstable)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    study.optimize(obj, n_trials=2)
    for t in study.trials:
        assert t.state == optuna.trial.TrialState.PRUNED
        assert t.user_attrs["failure"].startswith("unstable in sine-0.5hz on draw 0")
        assert t.intermediate_values == {0: FAIL_VALUE}


def test_aborted_runs_prune_and_scenarios_are_reported() -> None:
    """A real abort (|e1| > 1 µm at once) prunes; a normal trial reports after each scenario."""
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    study.optimize(_quick_objective(abort_error=1e-6), n_trials=1)
    t = study.trials[0]
    assert t.state == optuna.trial.TrialState.PRUNED
    assert t.user_attrs["failure"].startswith("aborted in sine-0.5hz")
    obj = _quick_objective()
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    study.enqueue_trial(obj.space.paper_params())
    study.optimize(obj, n_trials=1)
    t = study.trials[0]
    assert t.state == optuna.trial.TrialState.COMPLETE
    assert list(t.intermediate_values) == [0]  # after sine-0.5hz; the last is the value
    assert set(t.user_attrs["scenarios"]) == {"sine-0.5hz", "square-0.5hz"}
    # the value is the mean of the scenarios' CVaRs
    cv = [t.user_attrs["scenarios"][s]["cvar"] for s in ("sine-0.5hz", "square-0.5hz")]
    assert t.value == pytest.approx(float(np.mean(cv)), rel=1e-12)


def test_default_scenarios_are_table1_then_disturbance() -> None:
    assert DEFAULT_SCENARIOS == ("sine-0.5hz", "sine-0.75hz", "sine-0.5hz-heavy", "square-0.5hz",
                                 "disturbance-0.5hz")


# ---------------------------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------------------------

def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        run_cli(cli.main, argv)
    cap = capsys.readouterr()
    return int(exc.value.code), cap.out, cap.err


def test_tune_end_to_end_and_simulate_reproduces_the_nominal_figures(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A few trials with the full-length scenarios (one sine, the disturbance, two plants)."""
    model = write_truth_model(tmp_path)
    out = tmp_path / "out"
    code, stdout, stderr = _run(["--model", str(model), "--trials", "6", "--out", str(out),
                                 "--scenarios", "sine-0.5hz,disturbance-0.5hz", "--draws", "2",
                                 "--json"], capsys)
    assert code == 0, stderr
    lines = stdout.splitlines()
    assert len(lines) == 1  # exactly one JSON object on stdout
    res = json.loads(lines[0])
    assert res["trials"]["finished"] == 6
    cfg = load_controller(out / "controller.yaml")
    prov = cfg.provenance
    assert prov is not None
    assert prov.study == res["study"] and prov.trial == res["best"]["trial"]
    assert prov.objective == pytest.approx(res["best"]["objective"], rel=1e-15)
    assert prov.model_sha256 == res["model_sha256"] and len(prov.model_sha256) == 64
    assert prov.version and prov.created
    if "seed" in ProvenanceConfig.model_fields:  # contract 4's provenance.seed (requested)
        assert prov.seed == 1
    assert "seed 1." in (out / "controller.yaml").read_text(encoding="utf-8").splitlines()[0]
    for name in ("report.md", "history.png", "importance.png", "plant-nominal.yaml",
                 "plant-worst.yaml"):
        assert (out / name).is_file(), name
    assert (out / "history.png").read_bytes()[:4] == b"\x89PNG"
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "## Table 1 on the nominal plant" in report and "## Table 1 on the worst draw" in report

    # the objective's nominal figures, as stored with the best trial
    study = load_study(str(out / "study.journal"), res["study"])
    stored = study.trials[res["best"]["trial"]].user_attrs["scenarios"]
    plant = load_plant(out / "plant-nominal.yaml")
    assert plant == nominal_plant(MODEL, seed=1)
    for name in ("sine-0.5hz", "disturbance-0.5hz"):
        m = simulate_scenario(cfg, SCENARIOS[name], plant).metrics
        assert m.E_p_mm == pytest.approx(stored[name]["nominal_E_p_mm"], rel=1e-12)
        assert m.E_rms_mm == pytest.approx(stored[name]["nominal_E_rms_mm"], rel=1e-12)
        assert m.E_p_mm == pytest.approx(res["nominal"]["tuned"][name]["E_p_mm"], rel=1e-12)
    # and the `simulate` command on the written files
    code = simulate_main(["--controller", str(out / "controller.yaml"), "--plant",
                          str(out / "plant-nominal.yaml"), "--scenario", "sine-0.5hz", "--json"])
    sim = json.loads(capsys.readouterr().out)
    assert code == 0
    assert sim["scenarios"]["sine-0.5hz"]["E_rms_mm"] == pytest.approx(
        stored["sine-0.5hz"]["nominal_E_rms_mm"], rel=1e-12)

    # re-running the same command resumes: nothing left to do, same best trial
    code, stdout, _ = _run(["--model", str(model), "--trials", "6", "--out", str(out),
                            "--scenarios", "sine-0.5hz,disturbance-0.5hz", "--draws", "2",
                            "--json"], capsys)
    again = json.loads(stdout)
    assert code == 0 and again["trials"]["this_run"] == 0
    assert again["best"] == res["best"]


def test_same_seed_same_best_trial(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Same seed: same trials and best trial, also with the draws run in 2 processes."""
    model = write_truth_model(tmp_path)
    quick = ["--scenarios", "sine-0.5hz", "--draws", "4", "--duration", "4.0"]
    results = []
    for run, seed, jobs in (("a", 5, "1"), ("b", 5, "2"), ("c", 6, "1")):
        code, stdout, err = _run(["--model", str(model), "--trials", "14", "--seed", str(seed),
                                  "--out", str(tmp_path / run), *quick, "--jobs", jobs,
                                  "--json"], capsys)
        assert code == 0, err
        res = json.loads(stdout)
        study = load_study(str(tmp_path / run / "study.journal"), res["study"])
        results.append((res["best"], [(t.params, t.value) for t in study.trials]))
    assert results[0][0] == results[1][0]  # same trial number, value and parameters
    assert results[0][1] == results[1][1]  # every trial the same, to the last bit
    assert results[0][1][0][0] == results[2][1][0][0]  # trial 0 is the paper's either way
    assert results[0][1][1][0] != results[2][1][1][0]  # then the seed matters


@pytest.mark.parametrize(("argv", "needle"), [
    (["--model", "{tmp}/nope.yaml", "--trials", "3"], "run identify first"),
    (["--model", "{model}", "--trials", "0"], "--trials must be >= 1, got 0"),
    (["--model", "{model}", "--trials", "3", "--workers", "0"], "--workers must be >= 1"),
    (["--model", "{model}", "--trials", "3", "--jobs", "0"], "--jobs must be >= 1"),
    (["--model", "{model}", "--trials", "3", "--restarts", "0"], "--restarts must be >= 1"),
    (["--model", "{model}", "--trials", "3", "--storage", "redis://localhost/0"],
     "unknown scheme 'redis'"),
    (["--model", "{model}", "--trials", "3", "--scenarios", "sine-9hz"], "unknown scenario"),
    (["--model", "{bad}", "--trials", "3"], "mass"),
    (["--model", "{massless}", "--trials", "3"], "cannot make a controller.yaml"),
    (["--model", "{short}", "--trials", "3"],
     "rig.x_max: 1 mm either side of mid-stroke within [-1.50, 0.50] mm is too short for any "
     "scenario: they need at least 2.86 mm of stroke"),
    (["--model", "{model}", "--trials", "3", "--out", "{model}"],
     "--out names a folder that cannot be written"),
    (["--model", "{model}", "--trials", "3", "--storage", "{tmp}"],
     "is a folder; give the journal file's path"),
])
def test_bad_input_exits_2_with_one_error_line(argv: list[str], needle: str, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    model = write_truth_model(tmp_path)
    bad = tmp_path / "bad.yaml"
    bad.write_text(model.read_text(encoding="utf-8").replace("mass: 1.05", "mass: -1.0"),
                   encoding="utf-8")
    data = load_yaml_mapping(model)
    data["theta"]["min"][0] = 0.0  # a valid model.yaml, but contract 4 needs θ1_min > 0
    massless = tmp_path / "massless.yaml"
    write_yaml(massless, data)
    data = load_yaml_mapping(model)
    # a 2 mm stroke: a scenario scaled to it (0.7 of the 1 mm either side) would span less
    # than the 1 mm reference the scaling stops at (a 30 mm stroke is tuned: test_short_stroke)
    data["rig"]["x_max"] = 0.0005
    short = tmp_path / "short.yaml"
    write_yaml(short, data)
    argv = [a.format(tmp=tmp_path, model=model, bad=bad, massless=massless, short=short)
            for a in argv]
    out = [] if "--out" in argv else ["--out", str(tmp_path / "o")]
    code, stdout, stderr = _run([*argv, *out], capsys)
    assert code == 2
    assert stdout == ""
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert needle in lines[0]


def test_resuming_with_another_seed_is_refused(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    model = write_truth_model(tmp_path)
    args = ["--model", str(model), "--trials", "3", "--out", str(tmp_path / "o"), "--study",
            "axis", *QUICK]
    assert _run([*args, "--seed", "1"], capsys)[0] == 0
    code, _, stderr = _run([*args, "--seed", "2"], capsys)
    assert code == 2
    assert "was created for another seed" in stderr and "use another --study" in stderr
    assert only_study_name(str(tmp_path / "o" / "study.journal")) == "axis"


def test_progress_bar_goes_to_stderr(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """With a terminal the bar is drawn on stderr (tqdm disable=None); stdout stays clean."""
    import tqdm as tqdm_mod

    seen: list[object] = []
    real = tqdm_mod.tqdm

    def spy(*a: object, **k: object) -> object:
        seen.append(k.get("file"))
        k["disable"] = False
        return real(*a, **k)

    monkeypatch.setattr(cli, "tqdm", spy)
    model = write_truth_model(tmp_path)
    code, stdout, stderr = _run(["--model", str(model), "--trials", "3", "--out",
                                 str(tmp_path / "o"), *QUICK, "--json"], capsys)
    assert code == 0
    assert len(seen) == 1 and "3/3" in stderr
    assert math.isfinite(json.loads(stdout)["best"]["objective"])


def test_report_names_the_paper_controller_as_users_see_it(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """From a checkout report.md names ``data/controller-paper.yaml`` (the README's and the
    Makefile's name, a link to the packaged file); elsewhere the packaged file itself, by a
    path that does not climb out of the working directory."""
    from pneutune.control.contracts.controller import PAPER_CONTROLLER
    from pneutune.tune.api import paper_path

    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    assert paper_path() == "data/controller-paper.yaml"
    monkeypatch.chdir(tmp_path)
    assert (tmp_path / paper_path()).resolve() == PAPER_CONTROLLER.resolve()
    assert not paper_path().startswith("..")  # from outside the tree: its absolute path


def test_report_tells_the_valves_limit_from_chattering_gains() -> None:
    """report.md's verdict per scenario (tune/report.py::valve_verdict), on the metrics measured
    with benchmarks' fleet plants: plant 4's tuned controller on sine-0.75hz holds a valve fully
    open in long openings (flow_limited 0.34 of the window, E_p 1.59 vs the paper's 1.61 mm):
    the valves; plant 1 tuned with seed 5 is fully open 69 % of the window in bursts
    (flow_limited 0.06) and worse than the paper's gains (1.88 vs 1.24 mm): the gains; a good
    tune on plant 1 (1 %, 0.43 mm): nothing to say."""
    from pneutune.tune.report import valve_verdict

    paper4 = {"E_p_mm": 1.61, "full_open": 0.38, "flow_limited": 0.33}
    assert valve_verdict({"E_p_mm": 1.59, "full_open": 0.43, "flow_limited": 0.34},
                         paper4) == "flow-limited"
    paper1 = {"E_p_mm": 1.24, "full_open": 0.30, "flow_limited": 0.0}
    assert valve_verdict({"E_p_mm": 1.88, "full_open": 0.69, "flow_limited": 0.06},
                         paper1) == "chatter"
    assert valve_verdict({"E_p_mm": 0.43, "full_open": 0.01, "flow_limited": 0.0},
                         paper1) is None
    # bursts that still beat the paper's gains are not called out
    assert valve_verdict({"E_p_mm": 1.0, "full_open": 0.69, "flow_limited": 0.06},
                         paper1) is None
    assert valve_verdict({"E_p_mm": 1.0, "full_open": float("nan"),
                          "flow_limited": float("nan")}, paper1) is None


def test_restarts_with_a_named_study(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--restarts 2 --study axis: the studies are axis-seed1 and axis-seed2 in one journal;
    --json lists both with their selection scores and marks the lower one kept."""
    import optuna

    from pneutune.tune.storage import open_storage

    model = write_truth_model(tmp_path)
    code, stdout, _ = _run(["--model", str(model), "--trials", "2", "--out", str(tmp_path / "o"),
                            "--study", "axis", "--restarts", "2", "--json", *QUICK], capsys)
    assert code == 0
    rows = json.loads(stdout)["restarts"]
    assert [(r["seed"], r["study"]) for r in rows] == [(1, "axis-seed1"), (2, "axis-seed2")]
    best = min(range(2), key=lambda i: (rows[i]["failed"], rows[i]["score"], i))
    assert [r["kept"] for r in rows] == [i == best for i in range(2)]
    names = optuna.get_all_study_names(open_storage(str(tmp_path / "o" / "study.journal")))
    assert sorted(names) == ["axis-seed1", "axis-seed2"]
