"""The other simulator (tests/drivers/other_sim_driver.py) and the loop over it
(benchmarks/other_sim.py).

The driver is a second implementation of the paper's Sec. 2, reached only through the pipe
protocol: these tests keep it a conforming driver, check two facts of its physics that need no
pneutune code, and (slow) run the commissioning loop deploy -> identify -> tune -> deploy on it
with the benchmark, as a program.
"""

from __future__ import annotations

import json
import math
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from drivers import other_sim_driver as osd

from pneutune.control.logs.reader import read_run_log
from pneutune.control.rig.conformance import check_driver

ROOT = Path(__file__).resolve().parents[1]
DRIVER = Path(osd.__file__).resolve()
BENCHMARK = ROOT / "benchmarks" / "other_sim.py"
PAPER = ROOT / "data" / "controller-paper.yaml"
DEPLOY = str(Path(sys.executable).with_name("deploy"))
RECORD = str(Path(sys.executable).with_name("record"))


def test_driver_passes_every_conformance_check() -> None:
    report = check_driver([sys.executable, str(DRIVER), "--scenario", "sine-0.5hz", "--seed",
                           "1"], samples=200)
    assert report.passed, report.format()


def test_valves_shut_hold_the_piston_and_open_valves_extend_it() -> None:
    """All valves shut: the piston stays within 1 µm over 1 s (LuGre holds it; no leak). a_in
    and b_out fully open: it reaches x_max within 0.5 s (the driver author measured 0.19 s) and
    p_a climbs to within 2 % of the supply."""
    plant = osd.load_plant_dict({"sensors": {"x_noise": 0.0, "p_noise": 0.0}})
    sim = osd.CylinderSim(plant, "sine-0.5hz", seed=1)
    x0 = sim.state[0]
    for _ in range(250):
        sim.write((0.0, 0.0, 0.0, 0.0))
        sim.advance()
    assert abs(sim.state[0] - x0) < 1e-6
    for _ in range(125):
        sim.write((1.0, 0.0, 0.0, 1.0))
        sim.advance()
    assert sim.state[0] > osd.X_MAX - 5e-4
    for _ in range(250):
        sim.advance()
    assert sim.state[2] == pytest.approx(osd.P_S, rel=0.02)


def test_sampling_faster_keeps_the_physics_and_the_control_period() -> None:
    """--sample-period 0.5 ms: 5 RK4 steps of 0.1 ms per sample, the hello's Ts 0.5 ms and its
    rig block's 4 ms; with the duties held for 4 ms the state at every 4 ms tick is the 4 ms
    run's (the same steps, to rounding). A sample period equal to Ts is the default itself."""
    plant = osd.load_plant_dict({"sensors": {"x_noise": 0.0, "p_noise": 0.0}})
    slow = osd.CylinderSim(plant, "identification", seed=1)
    fast = osd.CylinderSim(plant, "identification", seed=1, sample_period=0.0005)
    same = osd.CylinderSim(plant, "identification", seed=1, sample_period=0.004)
    assert (fast.nsub, same.nsub, slow.nsub) == (5, 40, 40)
    assert fast.hello()["Ts"] == 0.0005 and fast.hello()["rig"]["Ts"] == 0.004
    assert slow.hello() == same.hello() and slow.hello()["Ts"] == 0.004
    for k in range(150):
        duties = tuple(min(1.0, max(0.0, 0.5 + 0.6 * math.sin(0.05 * k * (i + 1) + i)))
                       for i in range(4))
        for sim in (slow, fast, same):
            sim.write(duties)
        slow.advance()
        same.advance()
        for _ in range(8):
            fast.advance()
        assert same.state == slow.state
        assert fast.t == pytest.approx(slow.t, abs=1e-12)
        assert fast.state[0] == pytest.approx(slow.state[0], abs=1e-9)
        assert fast.state[2] == pytest.approx(slow.state[2], abs=1e-3)
        assert fast.state[3] == pytest.approx(slow.state[3], abs=1e-3)


def test_a_sample_period_that_does_not_divide_ts_is_refused() -> None:
    proc = subprocess.run([sys.executable, str(DRIVER), "--sample-period", "0.0007"],
                          input=b"H", capture_output=True, timeout=30)
    assert proc.returncode == 2
    assert b"--sample-period" in proc.stderr and proc.stdout == b""


def test_driver_passes_the_check_at_a_sample_period() -> None:
    """`driver check` with {sample_period} = 0.5 ms: the hello's Ts is 0.5 ms, dividing the rig
    block's 4 ms, and the clock advances by 0.5 ms."""
    cmd = (f"{shlex.quote(sys.executable)} {shlex.quote(str(DRIVER))} "
           "--sample-period {sample_period}")
    proc = subprocess.run([sys.executable, "-m", "pneutune.control.driver", "check", cmd,
                           "--sample-period", "0.0005"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.slow  # 52 s of the protocol at 0.5 ms through the driver: about 25 s
def test_record_runs_the_identification_protocol_on_the_other_simulator(tmp_path: Path) -> None:
    """The rest and chamber-A valve tests at 0.5 ms (52 s of the protocol): exit 0, every sample
    logged at 0.5 ms, the rig block's Ts the plant's 4 ms, and one contact onto x_max."""
    rig = (f"exec:{shlex.quote(sys.executable)} {shlex.quote(str(DRIVER))} "
           "--scenario {scenario} --seed {seed} --sample-period {sample_period}")
    out = tmp_path / "run.mcap"
    proc = subprocess.run([RECORD, "--experiment", "identification", "--segments",
                           "rest,valves:a", "--sample-period", "0.0005", "--rig", rig, "--out",
                           str(out), "--json"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["status"] == "ok" and summary["missing_segments"] == []
    assert [c["stop"] for c in summary["contacts"]] == ["x_max"]
    log = read_run_log(out)
    assert float(log.run["sample_period"]) == 0.0005
    assert log.rig["Ts"] == 0.004
    t = log["/rig/sensors"].index.to_numpy()
    assert t[1] - t[0] == pytest.approx(0.0005)


def test_print_plant_gives_the_complete_plant_and_the_moving_mass(tmp_path: Path) -> None:
    """--print-plant (the benchmark's truth): the plant file over the defaults, and the heavy
    sine's payload in the moving mass only."""
    plant = tmp_path / "plant.yaml"
    plant.write_text("mass: 1.4\nfriction: {F_C: 75.0}\n")
    truth = {}
    for scenario in ("sine-0.5hz", "sine-0.5hz-heavy", "identification"):
        proc = subprocess.run([sys.executable, str(DRIVER), "--plant", str(plant), "--scenario",
                               scenario, "--print-plant"], capture_output=True, text=True,
                              timeout=30)
        assert proc.returncode == 0, proc.stderr
        truth[scenario] = json.loads(proc.stdout)
    assert truth["sine-0.5hz"]["plant"] == osd.load_plant_dict({"mass": 1.4,
                                                                "friction": {"F_C": 75.0}})
    assert truth["sine-0.5hz"]["moving_mass"] == truth["identification"]["moving_mass"] == 1.4
    assert truth["sine-0.5hz-heavy"]["moving_mass"] == pytest.approx(1.4 + osd.PAYLOAD_HEAVY)


def test_plant_file_with_a_misspelt_key_is_refused(tmp_path: Path) -> None:
    bad = tmp_path / "plant.yaml"
    bad.write_text("friction: {F_c: 60.0}\n")
    proc = subprocess.run([sys.executable, str(DRIVER), "--plant", str(bad)], input=b"",
                          capture_output=True, timeout=30)
    assert proc.returncode == 2
    assert b"F_c" in proc.stderr


def test_deploy_runs_the_papers_controller_on_the_other_simulator(tmp_path: Path) -> None:
    """2 s of sine-0.5hz: no supervisor fault, a finite E_p below 5 mm (the driver's author
    measured 0.105 mm over the full 12 s)."""
    rig = (f"exec:{shlex.quote(sys.executable)} {shlex.quote(str(DRIVER))} "
           "--scenario {scenario} --seed {seed}")
    proc = subprocess.run([DEPLOY, str(PAPER), "--rig", rig, "--duration", "2", "--log",
                           str(tmp_path / "run.mcap"), "--json"], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)["scenarios"]["sine-0.5hz"]
    assert res["status"] == "ok" and math.isfinite(res["E_p_mm"]) and res["E_p_mm"] < 5.0


@pytest.mark.slow
def test_the_commissioning_loop_closes_on_the_other_simulator(tmp_path: Path) -> None:
    """deploy (paper) -> identify -> tune (40 trials) -> deploy (tuned) on the rough plant:
    every command exits 0, and the tuned controller beats the paper's gains on the 0.5 Hz sine
    (at 200 trials, benchmarks/other_sim.py: 0.26 against 0.69 mm). The benchmark runs as a
    program; its row is read from its JSON."""
    proc = subprocess.run([sys.executable, str(BENCHMARK), "--plants", "rough", "--trials", "40",
                           "--seed", "1", "--out", str(tmp_path), "--id-scenario", "sine-0.5hz",
                           "--id-log", "deploy"], capture_output=True, text=True, timeout=3600)
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    [row] = json.loads((tmp_path / "other_sim.json").read_text())
    assert row["stage"] == "done", row.get("error")
    assert row["tuned"]["sine-0.5hz"] < row["paper"]["sine-0.5hz"], row
