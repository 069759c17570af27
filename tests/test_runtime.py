"""The deploy runtime: it reproduces the simulator, its logs are
contract-1 logs that identify can read, the out-of-process example driver gives the same
numbers, the realtime pacing reports its figures; and reports/summary.md."""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.cli.deploy import main
from pneutune.control.cli.summary import summary_markdown, write_summary
from pneutune.control.constants import RIG_KEYS
from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.logs.reader import read_run_log
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.exec_rig import PipeRig
from pneutune.control.rig.pipe_server import serve
from pneutune.control.rig.scenario_run import run_scenario, sim_rig_for
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES
from pneutune.control.rig.wire import PROTOCOL, RigIOError
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"


@pytest.fixture(scope="module")
def paper():
    return load_controller(PAPER_YAML)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_deploy_reproduces_simulate(paper, name):
    """The runtime calls the same compiled step as the simulator, the sim rig
    draws the same noise (four standard normals per sample from default_rng(seed)) and starts
    from the same state, so deploy on the sim rig equals `simulate --controller` sample for
    sample; the metrics agree to 1e-9 mm (here exactly)."""
    sc = SCENARIOS[name]
    sim = simulate_scenario(paper, sc, seed=7)
    rig, _, _ = sim_rig_for(sc, seed=7)
    dep = run_scenario(paper, sc, rig)
    rec = dep.loop.recording
    assert dep.fault is None and dep.loop.events == []
    np.testing.assert_array_equal(rec.sensors_, sim.sensors)
    np.testing.assert_array_equal(rec.duties_, sim.duties)
    np.testing.assert_array_equal(rec.state_, sim.control_state)
    assert dep.metrics.E_p_mm == pytest.approx(sim.metrics.E_p_mm, abs=1e-9)
    assert dep.metrics.E_rms_mm == pytest.approx(sim.metrics.E_rms_mm, abs=1e-9)
    assert dep.metrics.switches_per_s == sim.metrics.switches_per_s


def test_deploy_log_round_trip(tmp_path, capsys):
    """`deploy` writes a contract-1 log that read_run_log accepts, with what
    identify needs (/rig/sensors, /rig/valves, every rig metadata key) and the closed-loop
    topics (/control/reference, /control/state, /experiment/segment, /sim/truth); the numbers
    are those printed with --json."""
    log = tmp_path / "d.mcap"
    code = main([str(PAPER_YAML), "--scenario", "sine-0.75hz", "--duration", "3", "--log",
                 str(log), "--json", "--seed", "3"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"scenarios", "faults", "realtime"}
    assert out["faults"] == [] and out["realtime"]["enabled"] is False
    m = out["scenarios"]["sine-0.75hz"]
    assert m["samples"] == 750 and m["status"] == "ok" and m["log"] == str(log)
    run = read_run_log(log)
    for topic in ("/rig/sensors", "/rig/valves", "/control/reference", "/control/state",
                  "/experiment/segment", "/sim/truth"):
        assert run.has(topic), topic
        if topic != "/experiment/segment":
            assert len(run[topic]) == 750, topic
    assert set(run.rig) == set(RIG_KEYS)
    assert run.rig == PlantConfig().rig_metadata()  # numbers round-trip bit for bit
    assert run.run["seed"] == "3" and run.run["scenario"] == "sine-0.75hz"
    assert run.run["status"] == "ok" and run.run["rig"] == "sim"
    x = run["/rig/sensors"]["x"].to_numpy()
    x_r = run["/control/reference"]["x_r"].to_numpy()
    e = (x - x_r)[-round(3 * (1 / 0.75) / 0.004):]
    assert np.max(np.abs(e)) * 1e3 == pytest.approx(m["E_p_mm"], abs=1e-9)


def test_pipe_driver_matches_in_process(paper):
    """The example driver runs the simulated rig in another process (the pipe
    protocol, IEEE doubles); 2 s of sine-0.5hz give bit-identical samples to the same rig in
    process."""
    sc = SCENARIOS["sine-0.5hz"]
    rig, _, _ = sim_rig_for(sc, seed=5)
    local = run_scenario(paper, sc, rig, duration=2.0, record_truth=True)
    with PipeRig(scenario=sc.name, seed=5) as remote_rig:
        assert remote_rig.Ts == 0.004 and remote_rig.rig_metadata()["pwm_hz"] == 60.0
        remote = run_scenario(paper, sc, remote_rig, duration=2.0, record_truth=True)
    a, b = local.loop.recording, remote.loop.recording
    assert b.n == 500 and remote.fault is None
    np.testing.assert_array_equal(a.sensors_, b.sensors_)
    np.testing.assert_array_equal(a.duties_, b.duties_)
    np.testing.assert_array_equal(a.truth_, b.truth_)
    assert remote.metrics.E_p_mm == pytest.approx(local.metrics.E_p_mm, abs=1e-12)


def test_pipe_driver_via_cli(tmp_path, capsys):
    """`deploy --rig pipe-sim` gives the numbers of `--rig sim`."""
    got = {}
    for rig in ("sim", "pipe-sim"):
        assert main([str(PAPER_YAML), "--rig", rig, "--duration", "1", "--json",
                     "--log", str(tmp_path / f"{rig}.mcap")]) == 0
        got[rig] = json.loads(capsys.readouterr().out)["scenarios"]["sine-0.5hz"]
    assert got["pipe-sim"]["E_rms_mm"] == got["sim"]["E_rms_mm"]


def _frames(*requests: bytes) -> io.BytesIO:
    return io.BytesIO(b"".join(requests))


def test_pipe_protocol_in_process():
    """The server side of the pipe protocol on byte streams: hello, read, write, advance,
    close; close and end of input leave the fail-safe duties."""
    rig = DeploySimRig(PlantConfig(), seed=1)
    out = io.BytesIO()
    duties = struct.pack("<4d", 0.5, 0.0, 0.0, 0.5)
    code = serve(rig, _frames(b"H", b"R", b"W" + duties, b"A", b"C"), out)
    assert code == 0
    data = out.getvalue()
    assert data[:1] == b"K"
    (n,) = struct.unpack("<I", data[1:5])
    hello = json.loads(data[5:5 + n])
    assert hello["protocol"] == PROTOCOL and hello["Ts"] == 0.004
    rest = data[5 + n:]
    assert rest[:1] == b"K"
    vals = struct.unpack("<9d", rest[1:73])
    assert vals[0] == 0.0 and 0.02 < vals[1] < 0.03  # t, x at mid-stroke
    assert rest[73:74] == b"K"                         # write
    assert rest[74:75] == b"K" and struct.unpack("<d", rest[75:83])[0] == 0.004
    assert rest[83:] == b"K"                           # close
    np.testing.assert_array_equal(rig.last_duties, FAIL_SAFE_DUTIES)

    rig = DeploySimRig(PlantConfig(), seed=1)
    assert serve(rig, _frames(b"W" + duties), io.BytesIO()) == 0  # then end of input
    np.testing.assert_array_equal(rig.last_duties, FAIL_SAFE_DUTIES)

    rig = DeploySimRig(PlantConfig(), seed=1)
    out = io.BytesIO()
    assert serve(rig, _frames(b"W" + struct.pack("<4d", 2.0, 0, 0, 0)), out) == 1
    assert out.getvalue()[:1] == b"E" and b"[0, 1]" in out.getvalue()


def test_pipe_rig_reports_a_dead_server():
    """A server that is not there or dies: a RigIOError naming what happened, no hang."""
    with pytest.raises(RigIOError, match=r"closed its output|gone"):
        PipeRig(command=[sys.executable, "-c", "import sys; sys.exit(0)"], timeout=5.0)
    with pytest.raises(RigIOError, match="no reply"):
        PipeRig(command=[sys.executable, "-c", "import time; time.sleep(5)"], timeout=0.3,
                startup_timeout=0.3)


def test_realtime_pacing(paper):
    """--realtime: 0.4 s of samples take at least 0.4 s of wall time and the statistics are
    reported (the jitter and overrun figures depend on the machine: not asserted)."""
    sc = SCENARIOS["sine-0.5hz"]
    rig, _, _ = sim_rig_for(sc, seed=1)
    res = run_scenario(paper, sc, rig, duration=0.4, realtime=True)
    t = res.loop.timing
    assert res.fault is None and t.realtime and t.samples == 100
    assert t.wall_s >= 0.396
    assert 0.0 <= t.jitter_p50 <= t.jitter_p99 <= t.jitter_max
    assert t.overruns >= 0 and 0.0 < t.step_p50 <= t.step_p99
    rig, _, _ = sim_rig_for(sc, seed=1)
    fast = run_scenario(paper, sc, rig, duration=0.4)
    np.testing.assert_array_equal(fast.loop.recording.duties_, res.loop.recording.duties_)


def test_cli_json_in_a_subprocess(tmp_path):
    """The console command: one JSON object on stdout, exit 0, the log at --log."""
    proc = subprocess.run([sys.executable, "-m", "pneutune.control.cli.deploy",
                           str(PAPER_YAML), "--duration", "1", "--json", "--log",
                           str(tmp_path / "c.mcap")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    obj = json.loads(proc.stdout)
    assert obj["scenarios"]["sine-0.5hz"]["samples"] == 250
    assert (tmp_path / "c.mcap").is_file()


def test_help_teaches(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for needle in ("examples:", "deploy data/controller-paper.yaml", "pipe-sim", "Exit status",
                   "fail-safe", "identify"):
        assert needle in text


def test_summary_markdown(tmp_path):
    """reports/summary.md: one row per scenario with the paper's Table 1 values (0.42/0.19 for
    sine-0.5hz), both simulated configs and links to the figures, relative to the file."""
    figs = tmp_path / "figures"
    figs.mkdir()
    (figs / "sine-0.5hz-tracking.png").write_bytes(b"png")
    paper = {"scenarios": {"sine-0.5hz": {"E_p_mm": 0.3301, "E_rms_mm": 0.1009, "status": "ok"},
                           "disturbance-0.5hz": {"E_p_mm": 0.39, "E_rms_mm": 0.14,
                                                 "status": "fault"}}}
    tuned = {"sine-0.5hz": {"E_p_mm": 0.2, "E_rms_mm": 0.05, "status": "ok"}}
    path = write_summary(tmp_path / "summary.md", paper, tuned, figs)
    text = path.read_text(encoding="utf-8")
    assert "| sine-0.5hz | 0.42 / 0.19 | 0.33 / 0.10 | 0.20 / 0.05 | " \
           "[tracking](figures/sine-0.5hz-tracking.png) |" in text
    assert "| disturbance-0.5hz | – | 0.39 / 0.14 (fault) | – |" in text
    assert summary_markdown(paper).count("\n| ") == 3  # header + 2 rows
    # the rig deploy ran on, from its --json "rig": the default plant, or a plant file
    assert "plant.yaml defaults, the paper's rig without real-rig effects" in text
    on_file = summary_markdown({**paper, "rig": "sim:data/plant-paper-rig.yaml"})
    assert "the simulated rig of `data/plant-paper-rig.yaml`" in on_file


def test_deploy_plots_write_the_figures(tmp_path):
    """`deploy --plots DIR` (used by make demo) draws the paper-like figures of each run."""
    import subprocess
    import sys

    paper = Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml"
    res = subprocess.run([sys.executable, "-m", "pneutune.control.cli.deploy", str(paper),
                          "--scenario", "sine-0.75hz", "--duration", "3", "--log",
                          str(tmp_path / "d.mcap"), "--plots", str(tmp_path / "figs")],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == sorted(
        f"sine-0.75hz-{k}.png" for k in ("tracking", "pressures", "theta", "duties"))
