"""The safety supervisor: every fault injected through the simulated rig
reaches the fail-safe state within one sample, with its event logged; the re-identification
warnings; the pure rules on synthetic samples."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import yaml
from rig_helpers import PAPER_YAML, SINE, TS, first_stale_time

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.logs.reader import read_run_log
from pneutune.control.plant.params import S_X
from pneutune.control.rig.faults import Fault, FaultySimRig
from pneutune.control.rig.scenario_run import run_scenario, sim_rig_for
from pneutune.control.rig.supervisor import (
    EXHAUST_DUTIES,
    FAIL_SAFE_DUTIES,
    Supervisor,
    SupervisorSettings,
)
from pneutune.control.sim.scenarios import SCENARIOS


@pytest.fixture(scope="module")
def paper() -> ControllerConfig:
    return load_controller(PAPER_YAML)


@pytest.fixture(scope="module")
def clean(paper):
    """The fault-free run that the faulty ones are compared with (3 s of sine-0.5hz)."""
    rig, _, _ = sim_rig_for(SINE, seed=1)
    return run_scenario(paper, SINE, rig, duration=3.0)


def _faulty_run(controller, faults, duration=3.0, fail_safe=FAIL_SAFE_DUTIES, **rig_kwargs):
    rig, plant, seed = sim_rig_for(SINE, seed=1, rig_class=FaultySimRig, faults=faults,
                                   **rig_kwargs)
    res = run_scenario(controller, SINE, rig, duration=duration, fail_safe=fail_safe,
                       plant=plant, seed=seed)
    return rig, res


# (fault, expected code, expected fault time [s])
CASES = [
    (Fault("nan", 1.0, "x"), "sensor_nan", 1.0),
    (Fault("nan", 1.0, "p_a"), "sensor_nan", 1.0),
    (Fault("nan", 1.0, "p_b"), "sensor_nan", 1.0),
    (Fault("nan", 1.0, "p_s"), "sensor_nan", 1.0),
    (Fault("value", 1.0, "x", 1.0), "sensor_range", 1.0),             # broken wire: at the rail
    (Fault("value", 1.0, "p_b", -2.5e4), "sensor_range", 1.0),        # 4-20 mA loop open
    (Fault("value", 1.0, "p_s", 2.5e6), "sensor_range", 1.0),         # above full scale
    (Fault("stale", 1.0, "x"), "sensor_stale", first_stale_time(1.0)),
    (Fault("stale", 1.0, "p_a"), "sensor_stale", first_stale_time(1.0)),
    (Fault("supply", 1.0, value=2.0e5), "supply_loss", 1.0),
    (Fault("supply", 1.2, value=1.2e5), "supply_loss", 1.2),
]


@pytest.mark.parametrize(("fault", "code", "t_expected"), CASES,
                         ids=[f"{c[0].kind}-{c[0].channel}-{c[1]}" for c in CASES])
def test_fault_reaches_fail_safe_within_one_sample(paper, clean, tmp_path, fault, code,
                                                   t_expected):
    """The fault is raised at the first bad sample (or, for staleness, the first
    sample past limits.sensor_timeout_s), the fail-safe duties are written in that same sample,
    the event is on /rig/events of the log, and everything before it equals the clean run."""
    rig, res = _faulty_run(paper, [fault])
    assert res.fault is not None and res.fault.code == code and res.fault.level == "error"
    assert res.fault.t == pytest.approx(t_expected, abs=1e-9)
    assert res.metrics.status == "fault"
    np.testing.assert_array_equal(rig.last_duties, FAIL_SAFE_DUTIES)
    k = round(res.fault.t / TS)
    rec = res.loop.recording
    # up to the injection the run equals the clean run (the faulty rig draws the same noise)
    k_inject = round(fault.t / TS)
    np.testing.assert_array_equal(rec.duties_[:k_inject], clean.loop.recording.duties_[:k_inject])
    if rec.n == k + 1:  # a finite bad sample is logged, with the fail-safe duties
        np.testing.assert_array_equal(rec.duties_[k], FAIL_SAFE_DUTIES)
    else:
        assert rec.n == k and not np.all(np.isfinite(rig.read()))
    path = tmp_path / "fault.mcap"
    res.save_log(str(path))
    log = read_run_log(path)
    ev = log["/rig/events"]
    assert list(ev["code"]) == [code] and list(ev["level"]) == ["error"]
    assert ev.index[0] == pytest.approx(t_expected, abs=1e-9)
    assert "fail-safe" in ev["message"].iloc[0]
    assert log.run["fault"] == code and log.run["status"] == "fault"


def test_fail_safe_hold_keeps_the_piston(paper):
    """The fail-safe choice (all valves closed, docs/deploy.md): the trapped air and friction
    stop the piston within a few mm of where the fault found it. Measured: it coasts 0.18 mm
    from the sine's 55 mm/s (t = 1 s) and is at rest after 1 s; the bound 2 mm covers the
    stale-position case (1.6 mm, the controller ran blind for 5 samples)."""
    rig, res = _faulty_run(paper, [Fault("nan", 1.0, "p_a")])
    assert res.fault is not None
    x_at_fault = rig.state[S_X]
    for _ in range(round(1.0 / TS)):
        rig.advance()
    assert abs(rig.state[S_X] - x_at_fault) < 2e-3
    assert abs(rig.truth()[0]) < 1e-3  # v [m/s]


def test_fail_safe_exhaust_option(paper):
    """--fail-safe exhaust writes a_out and b_out open instead."""
    rig, res = _faulty_run(paper, [Fault("nan", 0.5, "x")], duration=1.0,
                           fail_safe=EXHAUST_DUTIES)
    assert res.fault is not None
    np.testing.assert_array_equal(rig.last_duties, EXHAUST_DUTIES)


def _with(controller: ControllerConfig, **limits) -> ControllerConfig:
    return controller.model_copy(
        update={"limits": controller.limits.model_copy(update=limits)})


def test_position_limit(paper, clean):
    """limits.x_max = 35 mm inside the stroke: the sine (6 .. 41 mm) trips it at the first
    sample whose reading exceeds 35.1 mm (x_tolerance 0.1 mm), found in the clean run."""
    c = _with(paper, x_max=0.035)
    x = clean.loop.recording.sensors_[:, 0]
    k = int(np.argmax(x > 0.035 + 1e-4))
    assert k > 0
    rig, res = _faulty_run(c, [])
    assert res.fault is not None and res.fault.code == "position_limit"
    assert res.fault.t == pytest.approx(k * TS, abs=1e-9)
    np.testing.assert_array_equal(rig.last_duties, FAIL_SAFE_DUTIES)


def test_overpressure(paper, clean):
    """limits.p_max = 4 bar: tripped at the first sample where p_a or p_b reads above it."""
    c = _with(paper, p_max=4.0e5)
    p = clean.loop.recording.sensors_[:, 1:3]
    k = int(np.argmax(np.any(p > 4.0e5, axis=1)))
    assert k > 0
    rig, res = _faulty_run(c, [])
    assert res.fault is not None and res.fault.code == "overpressure"
    assert res.fault.t == pytest.approx(k * TS, abs=1e-9)
    np.testing.assert_array_equal(rig.last_duties, FAIL_SAFE_DUTIES)


def test_stale_pressure_without_sample_times(paper):
    """A rig that cannot say whether a sample is new: a pressure frozen bit for bit is stale
    after the timeout (the value rule)."""
    f = Fault("stale", 1.0, "p_b", stamp=False)
    rig, res = _faulty_run(paper, [f], report_sample_times=False)
    assert res.fault is not None and res.fault.code == "sensor_stale"
    assert res.fault.t == pytest.approx(first_stale_time(1.0), abs=1e-9)
    np.testing.assert_array_equal(rig.last_duties, FAIL_SAFE_DUTIES)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_no_false_alarm_on_clean_runs(paper, name):
    """The paper's config on every scenario, judged by the value rule (no sample times):
    noisy pressures never repeat, the quantised position is not judged on its values, no
    limit trips, no warning."""
    sc = SCENARIOS[name]
    rig, _, _ = sim_rig_for(sc, seed=1, rig_class=FaultySimRig, report_sample_times=False)
    res = run_scenario(paper, sc, rig)
    assert res.fault is None
    assert res.loop.events == []
    x = res.loop.recording.sensors_[:, 0]
    assert np.any(x[1:] == x[:-1])  # the position does repeat: judging it would be wrong


def test_supply_drift_warning(paper, tmp_path):
    """Supply down from 6 to 4.8 bar at t = 1 s: 1.2 bar off the model's for 0.5 s gives one
    reidentify_supply warning at t = 1.5 s; it is not a loss (3.5 bar), the run completes."""
    _rig, res = _faulty_run(paper, [Fault("supply", 1.0, value=4.8e5)])
    assert res.fault is None and res.metrics.status == "ok"
    warns = [e for e in res.loop.events if e.level == "warning"]
    assert [e.code for e in warns] == ["reidentify_supply"]
    assert warns[0].t == pytest.approx(1.5, abs=1e-9)
    assert "identify" in warns[0].message
    res.save_log(str(tmp_path / "w.mcap"))
    ev = read_run_log(tmp_path / "w.mcap")["/rig/events"]
    assert list(ev["level"]) == ["warning"]


def test_theta_on_bound_warning(paper):
    """θ̂ of the mass frozen (gamma 0) 1 % of the range above theta_min: inside the 2 % band
    from t = 0, so one reidentify_theta warning at t = theta_hold_s = 1 s naming M."""
    a = paper.adaptation
    lo, hi = a.theta_min[0], a.theta_max[0]
    theta_0 = (lo + 0.01 * (hi - lo), *a.theta_0[1:])
    gamma = (0.0, *a.gamma[1:])
    c = paper.model_copy(update={"adaptation": a.model_copy(
        update={"theta_0": theta_0, "gamma": gamma})})
    _, res = _faulty_run(c, [], duration=2.0)
    assert res.fault is None
    warns = [e for e in res.loop.events if e.code == "reidentify_theta"]
    assert len(warns) == 1
    assert warns[0].t == pytest.approx(1.0, abs=1e-9)
    assert "M" in warns[0].message and "lower bound" in warns[0].message


# -- the pure rules ----------------------------------------------------------------------------


@pytest.fixture()
def sup(paper) -> Supervisor:
    return Supervisor(SupervisorSettings.from_controller(paper))


GOOD = np.array([0.0235, 3.0e5, 3.1e5, 6.0e5])


def test_rules_on_synthetic_samples(sup):
    """Each rule against hand-made samples (thresholds from data/controller-paper.yaml:
    x in [-1.5, 48.5] mm, p_max 6.5 bar, supply loss below 3.507 bar = p0 + (6 bar - p0)/2)."""
    assert sup.check_sensors(0.0, GOOD) is None
    cases = {
        "sensor_nan": [np.inf, 3e5, 3e5, 6e5],
        "sensor_range": [0.0235, 1.0e4, 3e5, 6e5],
        "position_limit": [0.0487, 3e5, 3e5, 6e5],
        "overpressure": [0.0235, 3e5, 6.6e5, 6.6e5],
        "supply_loss": [0.0235, 3e5, 3e5, 3.5e5],
    }
    for code, sample in cases.items():
        sup.reset()
        ev = sup.check_sensors(0.0, np.array(sample))
        assert ev is not None and ev.code == code, (code, ev)
    sup.reset()
    assert sup.check_sensors(0.0, [0.0485 + 0.9e-4, 3e5, 3e5, 6e5]) is None  # within 0.1 mm
    s = sup.settings
    assert s.supply_min == pytest.approx(101325.0 + 0.5 * (6.0e5 - 101325.0))


def test_stale_rules(sup):
    """Sample times: stale once t - time > timeout. Values: a pressure repeated exactly for
    more than the timeout; the position never by its value."""
    assert sup.check_sensors(0.1, GOOD, [0.08, 0.1, 0.1, 0.1]) is None     # 20 ms: not more
    ev = sup.check_sensors(0.1, GOOD, [0.076, 0.1, 0.1, 0.1])
    assert ev is not None and ev.code == "sensor_stale" and "sensor x" in ev.message
    sup.reset()
    for k in range(20):  # x repeats, pressures change: fine
        assert sup.check_sensors(k * TS, GOOD + np.array([0.0, k, k, k])) is None
    sup.reset()
    faults = [sup.check_sensors(k * TS, GOOD) for k in range(7)]
    assert faults[:6] == [None] * 6  # changed at t=0; 20 ms later is not more than 20 ms
    assert faults[6] is not None and faults[6].code == "sensor_stale"


def test_a_reading_in_the_wrong_unit_gets_a_hint(sup):
    """A chamber at ambient read as gauge (250 Pa) or in bar (1.01), a position in mm (23.5):
    the sensor_range fault says which unit the protocol wants."""
    for value in (250.0, 1.01):
        sup.reset()
        ev = sup.check_sensors(0.0, [0.0235, value, 3e5, 6e5])
        assert ev.code == "sensor_range"
        assert ev.message.endswith("(gauge, or bar? the protocol's pressures are absolute, in Pa)")
    sup.reset()
    ev = sup.check_sensors(0.0, [23.5, 3e5, 3e5, 6e5])
    assert ev.code == "sensor_range" and ev.message.endswith("(in mm? the protocol's positions "
                                                             "are in m)")
    sup.reset()  # far outside either unit: no hint
    ev = sup.check_sensors(0.0, [0.0235, 3e7, 3e5, 6e5])
    assert ev.code == "sensor_range" and ev.message.endswith("] Pa")


def test_a_nan_sample_time_is_stale_at_once(sup):
    """A finite reading whose sample time is NaN (the protocol's "never delivered"): stale at
    the first sample, with a message that says why; ``t - NaN > timeout`` is false, which let
    a frozen channel with a NaN stamp through before."""
    ev = sup.check_sensors(0.0, GOOD, [0.0, 0.0, 0.0, np.nan])
    assert ev is not None and ev.code == "sensor_stale"
    assert ev.message == ("sensor p_s reads 600000.0 at t=0.0000 s, but the rig gives its "
                          "sample time as NaN (never delivered): a value without a sample time "
                          "cannot be judged fresh")


def test_warnings_latch_once(sup):
    """A warning is given once per cause, and only after the hold time."""
    theta = np.array(sup.settings.theta_max) - 1e-9
    out = []
    for k in range(600):
        out += sup.check_estimates(k * TS, 6.0e5, theta)
    codes = [(e.code, round(e.t, 6)) for e in out]
    # M (θ1), b_v (θ3), A_f (θ4) each at their upper bound; F_n and the D's are not watched
    assert codes == [("reidentify_theta", 1.0)] * 3


def test_messages_name_the_reading_and_the_time(sup):
    """The events carry the channel, the reading and the times the decision was taken on:
    the age of a stale channel (by its sample time, or since its value last changed) and how
    long a warning's cause has held."""
    ev = sup.check_sensors(0.5, [0.0235, 3e5, np.nan, 6e5])
    assert ev.code == "sensor_nan" and ev.message == "sensor p_b reads nan at t=0.5000 s"
    sup.reset()
    ev = sup.check_sensors(0.1, GOOD, [0.1, 0.1, 0.1, 0.076])
    assert ev.message.startswith("sensor p_s: no new sample for 0.0240 s at t=0.1000 s")
    sup.reset()
    faults = [sup.check_sensors(k * TS, GOOD) for k in range(7)]
    assert faults[6].message.startswith("sensor p_a has read exactly 300000.0 Pa for 0.0240 s")
    sup.reset()
    warns = [w for k in range(200) for w in sup.check_estimates(k * TS, 3.9e5,
                                                                np.full(6, 0.5))]
    # 2.1 bar below the model's 6 bar from t = 0: given at the hold time, 0.5 s
    assert [(w.code, round(w.t, 6)) for w in warns] == [("reidentify_supply", 0.5)]
    assert "for 0.50 s" in warns[0].message


def test_new_settings_apply_and_keep_memory(sup):
    """Settings replaced during a run (an identification run relaxes a stroke limit near an
    end stop) act from the next sample, and what the supervisor has seen is kept: a pressure
    repeating since t = 0 is stale at the same sample as without the change."""
    near = [0.0487, 3e5, 3e5, 6e5]
    assert sup.check_sensors(0.0, near).code == "position_limit"
    strict = sup.settings
    sup.settings = dataclasses.replace(strict, x_max=0.050)
    assert sup.check_sensors(0.0, near) is None
    sup.settings = strict
    sup.reset()
    faults = []
    for k in range(7):
        if k == 3:
            sup.settings = dataclasses.replace(strict, x_max=0.050)
        faults.append(sup.check_sensors(k * TS, GOOD))
    assert faults[:6] == [None] * 6 and faults[6].code == "sensor_stale"


def test_settings_validation(paper):
    with pytest.raises(ValueError, match="supply_loss_fraction"):
        SupervisorSettings.from_controller(paper, supply_loss_fraction=1.5)


def test_cli_fault_exits_3(tmp_path):
    """deploy with limits.x_max = 42 mm, 1 mm above the sine's peak, on a rig whose load
    pushes 1500 N at that peak (t = 0.5 s; 42.35 mm at the next sample): exit status 3, one
    `error:` line naming the fault, the log written with the event. (A limit inside the
    reference is refused before anything runs.)"""
    with open(PAPER_YAML, encoding="utf-8") as fh:
        data = yaml.safe_load(fh)
    data["limits"]["x_max"] = 0.042
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(data), encoding="utf-8")
    push = tmp_path / "push.yaml"
    push.write_text("schema: pneutune.plant/1\ndisturbance: {force_steps: [[0.5, 1500.0]]}\n",
                    encoding="utf-8")
    log = tmp_path / "f.mcap"
    proc = subprocess.run([sys.executable, "-m", "pneutune.control.cli.deploy", str(cfg),
                           "--duration", "2", "--log", str(log), "--rig", f"sim:{push}"],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 3, proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "position_limit" in errors[0]
    ev = read_run_log(log)["/rig/events"]
    assert list(ev["code"]) == ["position_limit"]
