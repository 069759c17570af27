"""Homing (``deploy --home auto|always|off``): a piston resting anywhere is moved to the
scenario's x_r(0) under the controller and supervisor before the scenario runs
(control/rig/homing.py). ``auto`` moves only a piston more than 1 mm away, and then a run that
needs no move is the run without homing, sample for sample.

Figures come from the paper's controller on the paper's rig (data/controller-paper.yaml,
PlantConfig()): a move from 6 or 40 mm to 23.5 mm ends within 0.15 mm of x_r(0) (measured
0.068-0.147 mm over 12 s runs, 2026-11-24); the bound asserted is 0.5 mm, half the start
tolerance.
"""

from __future__ import annotations

import math
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rig_helpers import PAPER_YAML, ROOT, SINE, TS, first_stale_time

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.logs.reader import read_run_log
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.exec_rig import PipeRig
from pneutune.control.rig.faults import Fault, FaultySimRig
from pneutune.control.rig.homing import HOME_HOLD_S, HOME_MOVE_S
from pneutune.control.rig.runtime import START_TOLERANCE
from pneutune.control.rig.scenario_run import run_scenario, sim_rig_for
from pneutune.control.rig.wire import RigIOError
from pneutune.control.sim.closed_loop import scenario_plant
from pneutune.control.sim.scenarios import SCENARIOS, move_and_hold

DRIVER = ROOT / "tests" / "drivers" / "other_sim_driver.py"
#: x_r(0) of the sines on the paper's rig: mid-stroke [m].
MID = 0.0235


@pytest.fixture(scope="module")
def paper():
    return load_controller(PAPER_YAML)


def _rig(x0: float, rig_class=DeploySimRig, **kw):
    plant = scenario_plant(PlantConfig(), SINE)
    return rig_class(plant, x0=x0, seed=1, **kw), plant


def test_move_and_hold_is_a_quintic_then_a_hold() -> None:
    t = np.arange(0, 4.0, 1e-3)
    ref = move_and_hold(t, 0.040, 0.006, 3.0)
    assert ref[0, 0] == pytest.approx(0.040, abs=1e-15)
    assert np.all(ref[t >= 3.0] == [0.006, 0.0, 0.0])
    # velocity and acceleration are the derivatives of the position (central differences)
    np.testing.assert_allclose(np.gradient(ref[:, 0], t)[1:-1], ref[1:-1, 1], atol=2e-5)
    np.testing.assert_allclose(np.gradient(ref[:, 1], t)[1:-1], ref[1:-1, 2], atol=2e-4)
    # the quintic's peak speed: 1.875 |Δx| / T
    assert np.abs(ref[:, 1]).max() == pytest.approx(1.875 * 0.034 / 3.0, rel=1e-4)


@pytest.mark.parametrize("x0", [0.006, 0.040])
def test_home_moves_a_resting_piston_to_the_start_then_runs_the_scenario(paper, x0):
    rig, plant = _rig(x0)
    res = run_scenario(paper, SINE, rig, duration=2.0, plant=plant, seed=1)  # home="auto"
    assert res.fault is None and res.metrics.status == "ok"
    homing = res.homing
    assert homing is not None and homing.fault is None
    assert homing.n_done == round((HOME_MOVE_S + HOME_HOLD_S) / TS)
    x = homing.recording.sensors_[:, 0]
    assert x[0] == pytest.approx(x0, abs=1e-4)  # starts where the piston rests
    assert abs(x[-1] - MID) < 0.5e-3
    # the scenario's own recording: its samples only, from its t = 0, x_r(0) at mid-stroke
    rec = res.loop.recording
    assert rec.n == round(2.0 / TS)
    assert rec.reference_[0, 0] == pytest.approx(MID, abs=1e-12)
    assert abs(rec.sensors_[0, 0] - MID) <= START_TOLERANCE
    first = res.loop.events[0]
    assert first.code == "homing" and first.level == "info"
    assert f"from x = {x[0] * 1e3:.3f} mm" in first.message
    assert res.run_meta["homing"] == "done"


def test_home_off_a_distant_piston_is_the_fault_start_position(paper):
    rig, _ = _rig(0.006)
    res = run_scenario(paper, SINE, rig, duration=1.0, home="off")
    assert res.fault is not None and res.fault.code == "start_position"
    assert "--home" in res.fault.message
    assert res.homing is None


def test_the_supervisor_judges_staleness_on_the_rig_clock_after_homing(paper):
    """The rig's clock runs on through the homing move: a position channel that freezes at rig
    time 5 s (scenario time 1 s) is stale one timeout later in scenario time. Without the
    clock offset the rig's sample times would lie 4 s in the loop's future and never age."""
    t_rig = HOME_MOVE_S + HOME_HOLD_S + 1.0
    rig, plant = _rig(0.010, FaultySimRig, faults=[Fault("stale", t_rig, "x")])
    res = run_scenario(paper, SINE, rig, duration=3.0, plant=plant, seed=1)
    assert res.homing is not None and res.homing.fault is None
    assert res.fault is not None and res.fault.code == "sensor_stale"
    assert res.fault.t == pytest.approx(first_stale_time(1.0), abs=1e-9)


def test_a_fault_during_homing_stops_before_the_scenario(paper, tmp_path):
    rig, plant = _rig(0.010, FaultySimRig, faults=[Fault("nan", 1.0, "p_a")])
    res = run_scenario(paper, SINE, rig, duration=2.0, plant=plant, seed=1)
    assert res.fault is not None and res.fault.code == "sensor_nan"
    assert res.fault.t == pytest.approx(1.0, abs=1e-9)
    assert res.loop is res.homing and res.metrics.status == "fault"
    assert math.isnan(res.metrics.E_p_mm) and math.isnan(res.metrics.E_rms_mm)
    assert res.run_meta["homing"] == "fault"
    path = tmp_path / "homing-fault.mcap"
    res.save_log(str(path))
    log = read_run_log(path)
    assert log.run["status"] == "fault" and log.run["homing"] == "fault"
    assert list(log["/rig/events"]["code"]) == ["sensor_nan"]


@pytest.mark.parametrize("home", ["auto", "always"])
def test_a_piston_at_the_start(paper, home):
    """``auto`` on a piston resting at x_r(0) reads once and runs the scenario exactly as
    ``off`` does (same recording to the last bit: the simulated rig draws its noise per
    reading); ``always`` moves and holds first (the homing's 4 s, then the scenario)."""
    runs = {}
    for mode in ("off", home):
        rig, plant, seed = sim_rig_for(SINE, seed=3)
        runs[mode] = run_scenario(paper, SINE, rig, duration=1.0, plant=plant, seed=seed,
                                  home=mode)
    off, other = runs["off"], runs[home]
    assert off.fault is None and other.fault is None
    if home == "auto":
        assert other.homing is None and other.loop.events == []
        np.testing.assert_array_equal(other.loop.recording.sensors_, off.loop.recording.sensors_)
        np.testing.assert_array_equal(other.loop.recording.duties_, off.loop.recording.duties_)
    else:
        assert other.homing is not None and other.run_meta["homing"] == "done"
        assert other.homing.n_done == round((HOME_MOVE_S + HOME_HOLD_S) / TS)
        assert other.loop.recording.n == off.loop.recording.n


def test_deploy_home_on_another_simulator_over_the_pipe(tmp_path):
    """The command a user runs: the other simulator's piston rests at 40 mm; with --home off
    deploy exits 3 (start_position, naming --home); by default the square wave (x_r(0) = 6 mm)
    runs after a homing move."""
    rig = (f"exec:{shlex.quote(sys.executable)} {shlex.quote(str(DRIVER))} "
           "--scenario {scenario} --seed {seed} --x0 0.040")
    deploy = str(Path(sys.executable).with_name("deploy"))
    base = [deploy, str(PAPER_YAML), "--rig", rig, "--scenario", "square-0.5hz",
            "--duration", "2", "--log", str(tmp_path / "sq.mcap")]
    refused = subprocess.run([*base, "--home", "off"], capture_output=True, text=True,
                             timeout=300)
    assert refused.returncode == 3, refused.stderr
    assert "start_position" in refused.stderr and "--home" in refused.stderr
    done = subprocess.run(base, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "square-0.5hz: homing: moved from x = 40.0" in done.stderr
    assert "to x_r(0) = 6.000 mm" in done.stderr
    log = read_run_log(tmp_path / "sq.mcap")
    assert log.run["homing"] == "done"
    x = log["/rig/sensors"]["x"].to_numpy()
    assert abs(x[0] - 0.006) <= START_TOLERANCE
    # a driver that simulates the timed disturbance on its own clock: deploy says it is early
    base[base.index("square-0.5hz")] = "disturbance-0.5hz"
    early = subprocess.run(base, capture_output=True, text=True, timeout=300)
    assert early.returncode == 0, early.stderr
    assert "homing_clock" in early.stderr and "4.00 s early" in early.stderr


def test_the_scenario_disturbance_starts_with_the_scenario_after_homing(paper):
    """The simulated rig applies the force steps of disturbance-0.5hz (30 N at 7.6 s, 80 N at
    9.8 s, off at 11.9 s) on the scenario's clock after the move, not 4 s early: the true
    external force per sample is the same as in the run without homing."""
    sc = SCENARIOS["disturbance-0.5hz"]
    runs = {}
    for mode in ("off", "always"):
        rig, plant, seed = sim_rig_for(sc, seed=2)
        runs[mode] = run_scenario(paper, sc, rig, plant=plant, seed=seed, home=mode,
                                  record_truth=True)
    f_off = runs["off"].loop.recording.truth_[:, 3]
    f_homed = runs["always"].loop.recording.truth_[:, 3]
    assert runs["always"].homing is not None
    np.testing.assert_array_equal(f_homed, f_off)
    assert f_off[round(9.0 / TS)] - f_off[round(7.0 / TS)] == pytest.approx(30.0, abs=1e-9)


class _FirstReadFails(DeploySimRig):
    """A rig whose first read raises (a DAQ timeout) and whose later reads work."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.reads = 0

    def read(self) -> np.ndarray:
        self.reads += 1
        if self.reads == 1:
            raise RigIOError("ADC card: conversion timeout")
        return super().read()


@pytest.mark.parametrize("home", ["auto", "always", "off"])
def test_a_failed_first_reading_is_the_rig_io_fault_with_its_message(paper, home):
    rig, _ = _rig(MID, _FirstReadFails)
    res = run_scenario(paper, SINE, rig, duration=1.0, home=home)
    assert res.fault is not None and res.fault.code == "rig_io" and res.fault.t == 0.0
    assert "ADC card: conversion timeout" in res.fault.message
    assert rig.reads == 1 and res.homing is None


def test_warnings_of_the_homing_move_reach_the_scenario_log(paper):
    """A supply 1.2 bar below the controller's p_s from 0.5 s of rig time on: the supervisor's
    reidentify_supply warning during the move is in the scenario's events at t = 0."""
    rig, plant = _rig(0.010, FaultySimRig, faults=[Fault("supply", 0.5, value=4.8e5)])
    res = run_scenario(paper, SINE, rig, duration=1.0, plant=plant, seed=1)
    assert res.homing is not None and res.homing.fault is None
    during = [e for e in res.loop.events if e.message.startswith("during the homing move")]
    assert [e.code for e in during] == ["reidentify_supply"] and during[0].t == 0.0


def test_a_plant_force_step_inside_the_move_waits_for_the_scenario(paper, tmp_path):
    """A plant file's own force step (40 N at 1 s, under sine-0.5hz) does not fire during the
    4 s move on the in-process rig, and comes at the scenario's 1 s as without homing. Over the
    pipe (pipe-sim: a child process timing it on its own clock) deploy warns homing_clock."""
    plant_cfg = PlantConfig().with_updates({"disturbance": {"force_steps": [[1.0, 40.0]]}})
    runs = {}
    for mode in ("off", "always"):
        rig, plant, seed = sim_rig_for(SINE, plant_cfg, seed=2)
        runs[mode] = run_scenario(paper, SINE, rig, duration=2.0, plant=plant, seed=seed,
                                  home=mode, record_truth=True)
    homing = runs["always"].homing
    assert homing is not None and np.all(homing.recording.truth_[:, 3] == 0.0)
    np.testing.assert_array_equal(runs["always"].loop.recording.truth_[:, 3],
                                  runs["off"].loop.recording.truth_[:, 3])
    assert runs["off"].loop.recording.truth_[round(1.5 / TS), 3] == pytest.approx(40.0)

    path = tmp_path / "plant.yaml"
    path.write_text("disturbance: {force_steps: [[1.0, 40.0]]}\n", encoding="utf-8")
    rig = PipeRig(plant=str(path), scenario=SINE.name, seed=2)
    try:
        res = run_scenario(paper, SINE, rig, duration=0.5, home="always",
                           plant=scenario_plant(plant_cfg, SINE), seed=2)
    finally:
        rig.close()
    assert [e.code for e in res.loop.events] == ["homing_clock", "homing"]
