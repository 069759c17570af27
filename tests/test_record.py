"""``record``: the excitation protocols on any rig, supervised (control/rig/excitation.py,
control/rig/excitation_plan.py, control/rig/contacts.py, control/cli/record.py).

The simulated rig is the paper's (the default plant); the figures quoted beside the tolerances
were measured on it when the command was written. Drivers: the example server
(``python -m pneutune.control.driver serve``), the C driver of docs/examples/rig_driver.c and
tests/drivers/spy_driver.py (a piston at rest that logs the requests, can lie about its period,
die or press Ctrl-C).
"""

from __future__ import annotations

import json
import math
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rig_helpers import compile_c_driver

from pneutune.control.cli.deploy import main as deploy_main
from pneutune.control.cli.record import EXIT_FAULT, EXIT_INTERRUPTED
from pneutune.control.cli.record import main as record_main
from pneutune.control.cli.simulate import main as simulate_main
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.driver import main as driver_main
from pneutune.control.errors import PneutuneError
from pneutune.control.logs.reader import read_run_log
from pneutune.control.rig.contacts import CONTACT_WARN_FACTOR
from pneutune.control.rig.excitation import execute_protocol, protocol_settings, record_on_sim
from pneutune.control.rig.excitation_plan import experiment_protocol, select_segments
from pneutune.control.rig.identification_run import Segment, move_segment
from pneutune.control.rig.simrig import SimRig
from pneutune.control.rig.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[1]
SPY = ROOT / "tests" / "drivers" / "spy_driver.py"
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
PLANT = PlantConfig()
RIG = PLANT.rig
SERVE = (f"{shlex.quote(sys.executable)} -m pneutune.control.driver serve --scenario {{scenario}} "
         f"--seed {{seed}} --sample-period {{sample_period}}")


def _spy(*args: str) -> str:
    return "exec:" + shlex.join([sys.executable, str(SPY), *args])


def _labels(path: Path) -> list[str]:
    return list(read_run_log(path)["/experiment/segment"]["label"])


# --- the protocols and their supervision -----------------------------------------------------


@pytest.fixture(scope="module")
def ident_run():
    """The identification run on the paper's rig at 0.5 ms, supervised (about 6 s)."""
    return record_on_sim("identification", PLANT, seed=1)


def test_identification_run_completes_supervised_with_gentle_contacts(ident_run):
    """The whole run passes the supervisor on the paper's rig, and both end-stop contacts come
    at about the planned 50 mm/s: below CONTACT_WARN_FACTOR = 2 times it (76 and 43 mm/s
    measured; the piston sticks, breaks away and catches up with the ramp), where the full-duty
    drive onto the stops used before reached 170 and 250 mm/s (true velocity). The contacts are
    logged as events."""
    assert ident_run.fault is None and ident_run.complete
    stops = [c.stop for c in ident_run.contacts]
    assert stops == ["x_max", "x_min"]
    for c in ident_run.contacts:
        assert 0.02 < c.speed < CONTACT_WARN_FACTOR * c.planned, c
    codes = [e[2] for e in ident_run.recording.events_]
    assert codes.count("end_stop_contact") == 2


def test_an_unplanned_contact_is_a_fault():
    """A move onto a stop in a segment that does not name it trips the supervisor's
    position_limit: the valves go fail-safe, the log keeps the completed segments only."""
    band = 0.05 * (RIG.x_max - RIG.x_min)
    segs = [Segment("rest:start", "rest", 0.2, {}, np.zeros(4), group="rest"),
            move_segment("stray", "hold", RIG.x_max + band, 0.05, band, RIG.x_max - RIG.x_min,
                         "stray")]
    rig = SimRig(PLANT, seed=1)
    run = execute_protocol(rig, segs, band,
                           supervisor=Supervisor(protocol_settings(PLANT.rig_metadata())))
    assert run.fault is not None and run.fault.code == "position_limit"
    assert run.completed == 1 and run.missing == ["stray"]
    assert run.recording.n == round(0.2 / RIG.Ts)
    assert [s[1] for s in run.recording.segments_] == ["rest:start"]


def test_a_piston_resting_on_a_stop_may_leave_it():
    """A piston that rests on an end stop at the start is not a fault: the stroke limit on
    that side is relaxed until the piston has moved inside it."""
    rig = SimRig(PLANT, x0=RIG.x_min, seed=1)
    segs = select_segments(experiment_protocol("commissioning", PLANT.rig_metadata()),
                           "hold:start_velocity")
    run = execute_protocol(rig, segs, 0.0025,
                           supervisor=Supervisor(protocol_settings(PLANT.rig_metadata())))
    assert run.fault is None and run.complete


def test_segments_select_groups_and_labels():
    """--segments matches groups and label patterns, keeps protocol order, and a pattern that
    matches nothing is bad input naming the groups."""
    segs = experiment_protocol("identification", PLANT.rig_metadata())
    friction = select_segments(segs, "friction")
    assert friction[0].label == "hold:start_friction"
    assert {s.group for s in friction} == {"friction"}
    both = select_segments(segs, "acceleration:*, rest")
    assert both[0].label == "rest:start" and both[-1].label == "rest:end"
    with pytest.raises(PneutuneError, match=r"names no segment.*valves:a"):
        select_segments(segs, "valves:c")


def test_the_sines_swing_30_percent_of_the_stroke_up_to_500_mm_per_s():
    """On the paper's 50 mm stroke every sine swings 15 mm (3 Hz: 15 mm x 2 pi x 3 = 283 mm/s);
    on a 1 m stroke 300 mm at 0.5 Hz would reach 942 mm/s, so each sine's amplitude is
    0.5 m/s / (2 pi f): 159 mm at 0.5 Hz, 26.5 mm at 3 Hz."""
    def sines(rig_meta):
        return {s.params["freq"]: s.params["amplitude"]
                for s in experiment_protocol("identification", rig_meta)
                if s.label.startswith("acceleration:sine")}

    assert sines(PLANT.rig_metadata()) == pytest.approx({0.5: 0.015, 1.0: 0.015, 2.0: 0.015,
                                                          3.0: 0.015})
    long_rig = PlantConfig().with_updates({"rig": {"x_min": 0.0, "x_max": 1.0}}).rig_metadata()
    amp = sines(long_rig)
    assert amp[0.5] == pytest.approx(0.5 / math.pi, rel=1e-12)  # 159 mm
    assert amp[3.0] == pytest.approx(0.5 / (6.0 * math.pi), rel=1e-12)  # 26.5 mm
    assert max(a * 2.0 * math.pi * f for f, a in amp.items()) == pytest.approx(0.5)


# --- the command -----------------------------------------------------------------------------


def test_simulate_experiment_is_record_on_the_simulated_rig(tmp_path, capsys):
    """`simulate --experiment` and `record --rig sim` write the same samples (one code path)."""
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    assert simulate_main(["--experiment", "commissioning", "--seed", "4", "--out", str(a)]) == 0
    assert record_main(["--experiment", "commissioning", "--seed", "4", "--out", str(b)]) == 0
    la, lb = read_run_log(a), read_run_log(b)
    for topic in ("/rig/sensors", "/rig/valves"):
        assert la[topic].equals(lb[topic])
    assert _labels(a) == _labels(b)


def test_the_example_server_gives_the_same_samples_as_in_process(tmp_path, capsys):
    """Through `exec:` at 0.5 ms (the server samples eight times per rig.Ts), the log holds
    bit for bit the samples of the in-process rig, the same labels and the same rig block,
    whose Ts stays the 4 ms control period."""
    common = ["--experiment", "identification", "--seed", "2", "--sample-period", "0.0005",
              "--segments", "rest:start,approach:*,prepare:a"]
    a, b = tmp_path / "in.mcap", tmp_path / "exec.mcap"
    assert record_main([*common, "--out", str(a)]) == 0
    assert record_main([*common, "--rig", f"exec:{SERVE}", "--out", str(b), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["sample_period"] == 0.0005 and summary["control_period"] == RIG.Ts
    la, lb = read_run_log(a), read_run_log(b)
    for topic in ("/rig/sensors", "/rig/valves", "/control/reference"):
        assert la[topic].equals(lb[topic]), topic
    assert la.rig == lb.rig and la.rig["Ts"] == RIG.Ts
    assert float(lb.run["sample_period"]) == 0.0005 and lb.run["rig"] == "exec"
    assert _labels(a) == _labels(b) == ["rest:start", "approach:a:x_max", "prepare:a",
                                        "approach:b:x_min"]


def test_plan_moves_nothing(tmp_path, capsys):
    """--plan asks the driver for its hello and sends no R, W or A; it prints the segments,
    the total time, the peak duty and speed, the contacts and the valve tests' pressures."""
    spy = tmp_path / "ops.txt"
    assert record_main(["--experiment", "identification", "--rig", _spy("--log", str(spy)),
                        "--plan"]) == 0
    assert set(spy.read_text()) <= {"H", "C"}
    text = capsys.readouterr().err
    for needle in ("total: ", "peak duty: 1", "peak planned speed: 283 mm/s",
                   "end-stop contact: x_max in approach:a:x_max, approach at 50 mm/s",
                   "chamber A: 1.01 to 6 bar abs", "supervisor: x within"):
        assert needle in text, needle


def test_a_driver_that_dies_is_a_rig_io_fault_with_a_valid_log(tmp_path, capsys):
    """A driver that exits mid-run: exit 3, the log holds the completed segments and the
    fault event, and reads back."""
    out = tmp_path / "d.mcap"
    code = record_main(["--experiment", "commissioning", "--rig", _spy("--die-at", "1500"),
                        "--out", str(out), "--json"])
    assert code == EXIT_FAULT
    summary = json.loads(capsys.readouterr().out)
    assert summary["fault"]["code"] == "rig_io" and summary["status"] == "fault"
    log = read_run_log(out)
    assert log.run["status"] == "fault" and log.run["fault"] == "rig_io"
    assert len(log["/rig/sensors"]) == summary["samples"] < 1500
    assert "rig_io" in list(log["/rig/events"]["code"])
    assert _labels(out) == [s.label for s in experiment_protocol(
        "commissioning", PLANT.rig_metadata())][:summary["segments"]]


def test_identify_on_a_log_cut_before_any_segment_says_what_stopped_the_run(tmp_path, capsys):
    """A driver that dies at its 5th sample: the log holds the run record and the fault event
    only, and identify's refusal says the run stopped, where, and what to do next."""
    out = tmp_path / "d.mcap"
    assert record_main(["--experiment", "commissioning", "--rig", _spy("--die-at", "5"),
                        "--out", str(out)]) == EXIT_FAULT
    capsys.readouterr()
    with pytest.raises(PneutuneError) as exc:
        read_run_log(out, required_topics=("/rig/sensors", "/rig/valves"))
    message = str(exc.value)
    assert "required topic /rig/sensors has no messages" in message
    assert ("; the run that wrote it stopped with the fault rig_io in segment rest:start after "
            "0/") in message
    assert "record it again once the cause is fixed" in message


def test_ctrl_c_stops_the_run_and_writes_the_log(tmp_path):
    """SIGINT (what Ctrl-C sends) reaches record alone: fail-safe duties, exit 130, the log of
    the completed segments written and valid."""
    out = tmp_path / "i.mcap"
    # a process started in the background of a non-interactive shell inherits SIGINT ignored,
    # and so would record (as a shell's background job should): give it a terminal's default
    proc = subprocess.run([sys.executable, "-m", "pneutune.control.cli.record", "--experiment",
                           "commissioning", "--rig", _spy("--interrupt-at", "3000"), "--out",
                           str(out)], capture_output=True, text=True, timeout=120, check=False,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.returncode == EXIT_INTERRUPTED, proc.stderr
    assert "error: interrupted" in proc.stderr
    log = read_run_log(out)
    assert log.run["status"] == "interrupted"
    assert 0 < len(log["/rig/sensors"]) < 3000
    assert list(log["/rig/events"]["code"])[-1] == "interrupted"


def test_more_ctrl_c_while_the_valves_close_loses_nothing(tmp_path):
    """Ctrl-C at sample 3000, then again at the fail-safe write and at the close (the driver
    sends them, tests/drivers/spy_driver.py): the later ones are told they are ignored, and the
    log is written as after one. Before, the second one lost the whole log."""
    out = tmp_path / "i.mcap"
    proc = subprocess.run([sys.executable, "-m", "pneutune.control.cli.record", "--experiment",
                           "commissioning", "--rig",
                           _spy("--interrupt-at", "3000", "--interrupt-again"), "--out",
                           str(out)], capture_output=True, text=True, timeout=120, check=False,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.returncode == EXIT_INTERRUPTED, proc.stderr
    assert "record: Ctrl-C again ignored: closing the valves and writing the log" in proc.stderr
    assert "error: interrupted at t=" in proc.stderr
    log = read_run_log(out)
    assert log.run["status"] == "interrupted"
    assert 0 < len(log["/rig/sensors"]) < 3000


def test_bad_input_moves_nothing(tmp_path, capsys):
    """A driver whose hello period differs from the one asked for, a stroke too short for the
    protocol, --segments naming nothing, a period that does not divide rig.Ts: each is one
    error (exit 2 from the command), and no R, W or A reached the driver."""
    spy = tmp_path / "ops.txt"
    with pytest.raises(PneutuneError, match=r"hello says Ts = 0.004 s, but --sample-period "
                                            r"asked for 0.0005 s"):
        record_main(["--experiment", "identification", "--rig", _spy("--log", str(spy)),
                     "--sample-period", "0.0005", "--out", str(tmp_path / "x.mcap")])
    with pytest.raises(PneutuneError, match="names no segment"):
        record_main(["--experiment", "identification", "--rig", _spy("--log", str(spy)),
                     "--segments", "nothing", "--out", str(tmp_path / "x.mcap")])
    assert set(spy.read_text()) <= {"H", "C"}
    short = tmp_path / "short.yaml"
    short.write_text("schema: pneutune.plant/1\nrig: {x_min: 0.0, x_max: 0.02}\n")
    with pytest.raises(PneutuneError, match=r"segment constant_speed:\+100mm/s needs a stroke "
                                            r"of at least 28.6 mm.*is 20.0 mm"):
        record_main(["--experiment", "identification", "--rig", f"sim:{short}", "--out",
                     str(tmp_path / "x.mcap")])
    with pytest.raises(PneutuneError, match="must divide"):
        record_main(["--experiment", "identification", "--sample-period", "0.0007", "--out",
                     str(tmp_path / "x.mcap")])
    assert not (tmp_path / "x.mcap").exists()


def test_deploy_refuses_a_driver_sampling_faster_than_rig_ts(tmp_path):
    """deploy runs the controller every sample: a hello Ts below rig.Ts is bad input."""
    with pytest.raises(PneutuneError, match="deploy runs the controller at every sample"):
        deploy_main([str(PAPER_YAML), "--rig", _spy("--sample-period", "0.0005"),
                     "--duration", "0.1", "--log", str(tmp_path / "d.mcap")])


def test_deploy_scales_a_scenario_to_a_short_stroke_and_refuses_a_tiny_one(tmp_path, capsys):
    """A 20 mm stroke cannot hold the paper's ±17.5 mm sine: it runs scaled to 0.7 of the
    10 mm either side of mid-stroke (7 mm, a factor 0.4), with a warning, inside the stroke
    (unscaled it used to hit both stops and report E_p 7.5 mm). A 2 mm stroke is bad input
    before anything runs."""
    short = tmp_path / "short.yaml"
    short.write_text("schema: pneutune.plant/1\nrig: {x_min: 0.0, x_max: 0.02}\n")
    assert deploy_main([str(PAPER_YAML), "--rig", f"sim:{short}", "--json",
                        "--log", str(tmp_path / "d.mcap")]) == 0
    out = json.loads(capsys.readouterr().out)
    scaled = [w for w in out["warnings"] if w["code"] == "reference_scaled"]
    assert len(scaled) == 1 and "scaled by 0.400 to 7.00 mm" in scaled[0]["message"]
    m = out["scenarios"]["sine-0.5hz"]
    assert m["status"] == "ok" and m["E_p_mm"] < 1.0, m
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text("schema: pneutune.plant/1\nrig: {x_min: 0.0, x_max: 0.002}\n")
    with pytest.raises(PneutuneError, match="too short for any scenario"):
        deploy_main([str(PAPER_YAML), "--rig", f"sim:{tiny}", "--log", str(tmp_path / "t.mcap")])
    assert not (tmp_path / "t.mcap").exists()


def test_a_selection_inside_a_group_gets_its_lead_in():
    """--segments 'constant_speed:*' first moves the piston to the ramp's start at the travel
    speed; a valve test alone first approaches its stop gently."""
    segs = experiment_protocol("identification", PLANT.rig_metadata())
    ramps = select_segments(segs, "constant_speed:*", PLANT.rig_metadata())
    assert ramps[0].label == "move:constant_speed:+3mm/s"
    assert ramps[0].params["x"] == ramps[1].params["x_from"]
    charge = select_segments(segs, "valve_charge:b_in:0.50", PLANT.rig_metadata())
    assert [s.kind for s in charge] == ["approach", "prepare", "valve_charge"]
    assert charge[0].contacts == ("x_min",)


# --- the C driver ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def c_driver(tmp_path_factory) -> Path:
    """docs/examples/rig_driver.c compiled with gcc, warning-free."""
    return compile_c_driver(tmp_path_factory.mktemp("c_driver"))


def test_c_driver_runs_a_shortened_protocol(c_driver, tmp_path, capsys):
    """The C driver at 1 ms (four samples per rig.Ts) runs the rest, valve and acceleration
    parts of the identification run: exit 0, a valid MCAP with every selected segment, the
    sample period of the hello, two gentle contacts (43 and 46 mm/s measured on its toy rig)."""
    out = tmp_path / "c.mcap"
    code = record_main(["--experiment", "identification", "--rig",
                        f"exec:{shlex.quote(str(c_driver))} --sample-period {{sample_period}}",
                        "--sample-period", "0.001", "--segments", "rest,valves:*,acceleration",
                        "--out", str(out), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    chosen = select_segments(experiment_protocol("identification", PLANT.rig_metadata()),
                             "rest,valves:*,acceleration")
    assert _labels(out) == [s.label for s in chosen]
    log = read_run_log(out)
    assert float(log.run["sample_period"]) == 0.001 and log.rig["Ts"] == RIG.Ts
    assert len(summary["contacts"]) == 2
    assert all(c["speed"] < CONTACT_WARN_FACTOR * c["planned"] for c in summary["contacts"])


def test_driver_check_takes_the_sample_period(c_driver, capsys):
    """`driver check --sample-period S` fills {sample_period} and requires the hello's Ts = S."""
    cmd = f"{shlex.quote(str(c_driver))} --sample-period {{sample_period}}"
    assert driver_main(["check", cmd, "--sample-period", "0.0005", "--samples", "100"]) == 0
    assert "sampling 8 times per rig.Ts" in capsys.readouterr().out
    assert driver_main(["check", shlex.quote(str(c_driver)), "--sample-period", "0.0005",
                        "--samples", "100"]) == 1
    assert "but --sample-period asked for 0.0005 s" in capsys.readouterr().out


@pytest.mark.slow
def test_identification_through_the_driver_gives_the_same_model(tmp_path):
    """The whole identification run through `exec:` on the example server at 0.5 ms gives a
    model.yaml identical, except `source`, to `simulate --experiment identification` on the
    same plant and seed: the driver protocol carries doubles bit for bit, and the in-process
    run is the same code (about 60 s: two runs, two identifications)."""
    import yaml

    logs = {"sim": tmp_path / "sim.mcap", "exec": tmp_path / "exec.mcap"}
    assert simulate_main(["--experiment", "identification", "--seed", "3", "--out",
                          str(logs["sim"])]) == 0
    assert record_main(["--experiment", "identification", "--seed", "3", "--sample-period",
                        "0.0005", "--rig", f"exec:{SERVE}", "--out", str(logs["exec"])]) == 0
    models = {}
    for name, log in logs.items():
        out = tmp_path / f"id-{name}"
        proc = subprocess.run([sys.executable, "-m", "pneutune.identify.cli", str(log), "--out",
                               str(out)], capture_output=True, text=True, timeout=600,
                              check=False)
        assert proc.returncode == 0, proc.stderr
        models[name] = yaml.safe_load((out / "model.yaml").read_text())
        del models[name]["source"]
    assert models["sim"] == models["exec"]


def test_a_run_interrupted_in_the_friction_ramps_identifies_with_notes(tmp_path, monkeypatch,
                                                                       capsys):
    """Ctrl-C 10 s into the friction ramps of the identification run (4 ms log): exit 130, the
    log keeps the valve tests and the ramps completed, and identify accepts it, saying where the
    run stopped and that the mass is its prior (no acceleration segments)."""
    from pneutune.identify.pipeline import identify

    segs = experiment_protocol("identification", PLANT.rig_metadata())
    first = next(i for i, s in enumerate(segs) if s.group == "friction")
    t_stop = sum(s.duration for s in segs[:first]) + 10.0

    class CtrlC(SimRig):
        def advance(self) -> None:
            if self.t >= t_stop:
                raise KeyboardInterrupt
            super().advance()

    monkeypatch.setattr("pneutune.control.rig.simrig.SimRig", CtrlC)
    out = tmp_path / "cut.mcap"
    assert record_main(["--experiment", "identification", "--sample-period", "0.004",
                        "--out", str(out), "--json"]) == EXIT_INTERRUPTED
    summary = json.loads(capsys.readouterr().out)
    assert summary["status"] == "interrupted"
    assert summary["missing_segments"][0].startswith(("constant_speed:", "hold:"))
    log = read_run_log(out)
    assert log.run["stopped_in"] == summary["missing_segments"][0]
    notes = " ".join(identify(out).model.notes)
    assert f"cut short in segment '{log.run['stopped_in']}'" in notes
    assert "no acceleration segments: the mass is the prior" in notes


@pytest.mark.slow
def test_a_fast_log_without_the_acceleration_segments_is_told_to_record_them(tmp_path, capsys):
    """The friction ramps alone, logged every 0.5 ms (about 100 s of work): the mass is the
    prior, and the note asks for the segments that excite it, not for faster sampling, which
    the log already has. Before, it advised `record --sample-period 0.0005`."""
    from pneutune.identify.pipeline import identify

    out = tmp_path / "rf.mcap"
    assert record_main(["--experiment", "identification", "--segments", "rest,friction",
                        "--sample-period", "0.0005", "--out", str(out)]) == 0
    (note,) = [n for n in identify(out).model.notes if n.startswith("mass: not identifiable")]
    assert ("has none of the segments that excite the mass (acceleration): record them "
            "(record --experiment identification --segments acceleration)") in note
    assert "--sample-period" not in note
