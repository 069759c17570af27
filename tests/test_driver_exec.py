"""Any driver program on the command line (``deploy --rig exec:"CMD ARGS"``) and
the driver author's conformance check (``python -m pneutune.control.driver check "CMD"``).

Run against three drivers nobody wrote for these tests alone: the shipped
example server, the minimal C driver of docs/examples/rig_driver.c (compiled here with gcc),
and tests/drivers/broken_driver.py, whose modes each break one conformance check.
"""

from __future__ import annotations

import json
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest
from rig_helpers import compile_c_driver

from pneutune.control import driver
from pneutune.control.cli.common import run_cli
from pneutune.control.cli.deploy import main as deploy_main
from pneutune.control.errors import ExperimentError
from pneutune.control.logs.reader import read_run_log
from pneutune.control.rig.conformance import CHECKS, check_driver
from pneutune.control.rig.exec_rig import exec_command

ROOT = Path(__file__).resolve().parents[1]
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
C_DRIVER = ROOT / "docs" / "examples" / "rig_driver.c"
BROKEN = Path(__file__).resolve().parent / "drivers" / "broken_driver.py"
PY = shlex.quote(sys.executable)
#: The example server as an exec: command, its scenario and seed filled in per run.
EXAMPLE_SERVER = f"{PY} -m pneutune.control.driver serve --scenario {{scenario}} --seed {{seed}}"
#: Reply timeout of the checks on the broken driver [s]: its replies take microseconds, but the
#: machine may be busy; the late mode's reply comes after LATE_DELAY (within the check's
#: patience of 5 timeouts, so that it is reported as late, not as missing).
CHECK_TIMEOUT = 1.5
LATE_DELAY = 4.0
#: Each broken mode and the one check it must fail (tests/drivers/broken_driver.py).
BROKEN_MODES = {
    "bad_hello": "hello",
    "stamp_future": "sequence",
    "clock": "clock",
    "accept_duty": "bad_duty",
    "accept_opcode": "unknown_opcode",
    "ignore_eof": "end_of_input",
    "ignore_close": "close",
    "late": "latency",
}


def _broken(mode: str) -> list[str]:
    return [sys.executable, str(BROKEN), "--mode", mode, "--delay", str(LATE_DELAY)]


def _cli_error(capsys, argv: list[str]) -> str:
    """Run deploy as its console script does; expect exit 2 and one ``error:`` line."""
    with pytest.raises(SystemExit) as exc:
        run_cli(deploy_main, argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


# --- deploy --rig exec: --------------------------------------------------------------------


def test_exec_example_server_reproduces_sim(tmp_path, capsys):
    """`deploy --rig exec:"<example server> --scenario {scenario} --seed {seed}"` gives the
    samples and figures of `--rig sim` with the same seed, bit for bit (doubles cross the pipe
    as IEEE 754 bits), and logs the driver's rig block and command, without /sim/truth."""
    got = {}
    for name, rig in (("sim", "sim"), ("exec", f"exec:{EXAMPLE_SERVER}")):
        assert deploy_main([str(PAPER_YAML), "--rig", rig, "--seed", "3", "--duration", "1",
                            "--json", "--log", str(tmp_path / f"{name}.mcap")]) == 0
        got[name] = json.loads(capsys.readouterr().out)
    sim, ex = (got[k]["scenarios"]["sine-0.5hz"] for k in ("sim", "exec"))
    assert ex["samples"] == sim["samples"] == 250
    for key in ("E_p_mm", "E_rms_mm", "switches_per_s", "p_a_max_Pa", "p_b_min_Pa"):
        assert ex[key] == sim[key], key
    assert got["exec"]["faults"] == [] and got["exec"]["seed"] == 3
    a, b = read_run_log(tmp_path / "sim.mcap"), read_run_log(tmp_path / "exec.mcap")
    for topic in ("/rig/sensors", "/rig/valves", "/control/state"):
        np.testing.assert_array_equal(a[topic].to_numpy(), b[topic].to_numpy())
    assert b.rig == a.rig
    assert b.run["rig"] == "exec" and b.run["rig_command"] == EXAMPLE_SERVER
    assert b.run["seed"] == "3"  # the command used {seed}
    with pytest.raises(KeyError, match="/sim/truth"):
        b["/sim/truth"]


def test_exec_command_placeholders():
    """{scenario} and {seed} are replaced per run, then the text is split like a shell would;
    anything else in braces, unbalanced quotes or an empty command is refused."""
    assert exec_command("drv --scenario {scenario} --seed {seed} 'a b'", "square-0.5hz", 7) == [
        "drv", "--scenario", "square-0.5hz", "--seed", "7", "a b"]
    assert exec_command("./rig_driver", "sine-0.5hz", 1) == ["./rig_driver"]
    for bad, needle in (("drv {port}", "unknown placeholder {port}"),
                        ("drv 'open", "No closing quotation"), ("  ", "empty")):
        with pytest.raises(ExperimentError, match=re.escape(needle)):
            exec_command(bad, "sine-0.5hz", 1)


def test_exec_missing_driver_exits_2(tmp_path, capsys):
    """A driver that is not there: exit 2, one `error:` line naming the command, no log."""
    missing = tmp_path / "no_such_driver"
    line = _cli_error(capsys, [str(PAPER_YAML), "--rig", f"exec:{missing} --port X",
                               "--duration", "1", "--log", str(tmp_path / "m.mcap")])
    assert "cannot start the rig driver" in line and str(missing) in line
    assert "No such file" in line
    assert not (tmp_path / "m.mcap").exists()


def test_exec_driver_dying_at_once_exits_2_with_its_stderr(tmp_path, capsys):
    """A driver that dies before its hello: exit 2, one `error:` line with its exit status and
    the tail of its stderr (its last lines, so the reason it gave is on the screen)."""
    script = tmp_path / "dies.py"
    script.write_text("import sys\n"
                      "sys.stderr.write('opening /dev/daq0\\n')\n"
                      "sys.stderr.write('no DAQ card found on /dev/daq0\\n')\n"
                      "sys.exit(3)\n", encoding="utf-8")
    line = _cli_error(capsys, [str(PAPER_YAML), "--rig", f"exec:{PY} {script}",
                               "--duration", "1", "--log", str(tmp_path / "d.mcap")])
    assert "failed at its hello" in line and "(exit status 3)" in line
    assert "opening /dev/daq0 | no DAQ card found on /dev/daq0" in line
    assert not (tmp_path / "d.mcap").exists()


def test_exec_bad_hello_and_bad_command_exit_2(tmp_path, capsys):
    """A hello without a complete rig block, or a placeholder deploy does not know: exit 2
    before anything runs."""
    line = _cli_error(capsys, [str(PAPER_YAML), "--rig",
                               f"exec:{shlex.join(_broken('bad_hello'))}", "--duration", "1",
                               "--log", str(tmp_path / "h.mcap")])
    assert "failed at its hello" in line and "lacks pwm_update" in line
    line = _cli_error(capsys, [str(PAPER_YAML), "--rig", "exec:./drv --port {port}"])
    assert "unknown placeholder {port}" in line


def test_exec_driver_failing_for_a_later_scenario_is_a_fault(tmp_path, capsys):
    """The driver runs the first scenario and dies at the start of the second: the first run
    and its log stand, the second is a rig_io fault with the driver's stderr, exit 3 (not 2:
    something ran)."""
    script = tmp_path / "second_fails.py"
    script.write_text("import runpy, sys\n"
                      "if sys.argv[1] != 'sine-0.5hz':\n"
                      "    sys.exit('the valve terminal is not powered')\n"
                      f"sys.argv = [{str(BROKEN)!r}]\n"
                      f"runpy.run_path({str(BROKEN)!r}, run_name='__main__')\n",
                      encoding="utf-8")
    code = deploy_main([str(PAPER_YAML), "--rig", f"exec:{PY} {script} {{scenario}}",
                        "--scenario", "table1", "--duration", "0.2", "--json",
                        "--log", str(tmp_path / "t.mcap")])
    cap = capsys.readouterr()
    assert code == 3, cap.err
    obj = json.loads(cap.out)
    assert list(obj["scenarios"]) == ["sine-0.5hz"]
    assert obj["not_run"] == ["sine-0.75hz", "sine-0.5hz-heavy", "square-0.5hz"]
    (fault,) = obj["faults"]
    assert fault["scenario"] == "sine-0.75hz" and fault["code"] == "rig_io"
    assert "the valve terminal is not powered" in fault["message"]
    errors = [ln for ln in cap.err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and errors[0].endswith("(log: none written)")
    assert (tmp_path / "t-sine-0.5hz.mcap").is_file()


def test_exec_late_reply_is_a_rig_io_fault(tmp_path, capsys):
    """A reply later than the timeout (2 s) during the run: as for pipe-sim, a rig_io fault,
    fail-safe duties, the log written, exit 3 with one `error:` line."""
    log = tmp_path / "late.mcap"
    cmd = shlex.join([sys.executable, str(BROKEN), "--mode", "late", "--delay", "3"])
    assert deploy_main([str(PAPER_YAML), "--rig", f"exec:{cmd}", "--duration", "1",
                        "--log", str(log)]) == 3
    errors = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "rig_io" in errors[0] and "no reply" in errors[0]
    run = read_run_log(log)
    assert run.run["status"] == "fault" and list(run["/rig/events"]["code"]) == ["rig_io"]


@pytest.mark.parametrize(("mode", "reply", "after", "last"),
                         [("clock_nan", "A", "later than", "0.116"),  # 29 Ts, then the 30th A
                          ("clock_back", "R", "at or after", "0.12")])  # R after 30 A
def test_exec_broken_clock_is_a_rig_io_fault(mode, reply, after, last, tmp_path, capsys):
    """A driver whose A reply carries t = NaN, or whose R reply runs its clock back (at sample
    30, tests/drivers/broken_driver.py): a rig_io fault naming the reply and the time, the
    fail-safe duties written through the driver (it still answers), the log kept, exit 3."""
    log = tmp_path / "clock.mcap"
    cmd = shlex.join(_broken(mode))
    assert deploy_main([str(PAPER_YAML), "--rig", f"exec:{cmd}", "--duration", "1",
                        "--log", str(log)]) == 3
    errors = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "rig_io" in errors[0], errors
    assert f"the driver's {reply} reply carries t = " in errors[0]
    assert f"expected a finite time {after} the last one, {last} s" in errors[0]
    assert "failed too" not in errors[0]
    run = read_run_log(log)
    assert run.run["status"] == "fault" and list(run["/rig/events"]["code"]) == ["rig_io"]


def test_a_unix_time_clock_conforms_and_its_stale_channel_is_caught(tmp_path, capsys):
    """A driver whose clock starts at 1.7e9 s (a hardware clock in Unix time) conforms: the
    check and the client count from its first t. Its sample times are judged on that clock:
    x's frozen from sample 30 (0.12 s) is stale once older than limits.sensor_timeout_s
    (20 ms in data/controller-paper.yaml): at 0.14 s or the sample after (at 1.7e9 s a double
    resolves 0.24 us, so the age at 0.14 s is 20 ms give or take that). Before, the ages were
    t - 1.7e9 < 0 and nothing was ever stale."""
    report = check_driver(_broken("clock_unix"), samples=60, timeout=CHECK_TIMEOUT)
    assert report.passed, report.format()
    log = tmp_path / "unix.mcap"
    cmd = shlex.join(_broken("stale_unix"))
    assert deploy_main([str(PAPER_YAML), "--rig", f"exec:{cmd}", "--duration", "1",
                        "--log", str(log)]) == 3
    errors = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "fault sensor_stale" in errors[0], errors
    assert re.search(r"sensor x: no new sample for 0\.0(200|240) s at t=0\.14(0|4)0 s",
                     errors[0]), errors[0]


@pytest.mark.parametrize("mode", ["clock_nan", "clock_back"])
def test_check_catches_a_broken_clock(mode, capsys):
    """The conformance check fails a NaN or backward time as ``clock`` (a read whose t runs
    back also has sample times after its t, which ``sequence`` fails)."""
    cmd = shlex.join(_broken(mode))
    code = driver.main(["check", cmd, "--samples", "60", "--timeout", str(CHECK_TIMEOUT)])
    out = capsys.readouterr().out
    assert code == 1, out
    expected = ["sequence", "clock"] if mode == "clock_back" else ["clock"]
    assert re.findall(r"^FAIL  (\w+)", out, re.MULTILINE) == expected, out


# --- driver check ----------------------------------------------------------------------------


def test_check_passes_the_example_server(capsys):
    """`python -m pneutune.control.driver check "<example server>"`: every check passes,
    exit 0 (six server processes; fewer samples than the default to keep it quick, and
    generous timeouts: a busy 2-core machine may recompile the simulator at startup)."""
    code = driver.main(["check", EXAMPLE_SERVER, "--samples", "100", "--timeout", "5",
                        "--startup-timeout", "60"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "8 of 8 checks passed: the driver conforms" in out
    for name in CHECKS:
        assert re.search(rf"^PASS  {name}\b", out, re.MULTILINE), name


def test_broken_driver_conforms_in_its_ok_mode():
    """The broken driver without a fault passes, so each mode below fails by its fault only."""
    report = check_driver(_broken("ok"), samples=120, timeout=CHECK_TIMEOUT)
    assert report.passed, report.format()


def test_every_check_is_caught_by_a_broken_mode():
    assert sorted(BROKEN_MODES.values()) == sorted(CHECKS)


@pytest.mark.parametrize(("mode", "check"), list(BROKEN_MODES.items()))
def test_check_catches_the_broken_driver(mode, check, capsys):
    """Each deliberate fault fails exactly the check it breaks: exit 1, the report names it."""
    cmd = shlex.join(_broken(mode))
    code = driver.main(["check", cmd, "--samples", "120", "--timeout", str(CHECK_TIMEOUT)])
    out = capsys.readouterr().out
    assert code == 1, out
    failed = re.findall(r"^FAIL  (\w+)", out, re.MULTILINE)
    assert failed == [check], out
    assert out.rstrip().endswith(f"the driver fails {check}")


def test_check_on_a_missing_or_silent_driver(tmp_path, capsys):
    """No driver, or one that never answers its hello: exit 1, every check failed (or not
    run), and no waiting for five more hellos."""
    code = driver.main(["check", str(tmp_path / "nothing_here")])
    out = capsys.readouterr().out
    assert code == 1 and "0 of 8 checks passed" in out and "cannot start" in out
    report = check_driver([sys.executable, "-c", "import time; time.sleep(60)"], samples=10,
                          timeout=0.5, startup_timeout=0.5)
    assert report.failed() == list(CHECKS)
    assert "no reply" in report.results[0].detail
    assert all("not run" in r.detail for r in report.results[1:-1])


def test_check_bad_arguments_exit_2(capsys):
    assert driver.main(["check", "drv {port}"]) == 2
    assert capsys.readouterr().err.startswith("error: driver command 'drv {port}': unknown")
    assert driver.main(["check", "drv", "--timeout", "0"]) == 2


# --- the C driver of docs/deploy.md ----------------------------------------------------------


@pytest.fixture(scope="module")
def c_driver(tmp_path_factory) -> Path:
    """docs/examples/rig_driver.c compiled with gcc, as docs/deploy.md says."""
    return compile_c_driver(tmp_path_factory.mktemp("c_driver"))


def test_c_driver_passes_check(c_driver, capsys):
    """The protocol is language-neutral: the C driver conforms (the default 500 samples)."""
    code = driver.main(["check", shlex.quote(str(c_driver))])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "8 of 8 checks passed" in out


def test_c_driver_runs_under_deploy(c_driver, tmp_path, capsys):
    """`deploy --rig exec:./rig_driver --duration 2`: 500 samples, exit 0; the log's rig block
    is the one of the driver's hello, and the run records no seed (the command has none)."""
    log = tmp_path / "c.mcap"
    assert deploy_main([str(PAPER_YAML), "--rig", f"exec:{shlex.quote(str(c_driver))}",
                        "--duration", "2", "--json", "--log", str(log)]) == 0
    res = json.loads(capsys.readouterr().out)["scenarios"]["sine-0.5hz"]
    assert res["samples"] == 500 and res["status"] == "ok"
    run = read_run_log(log)
    assert run.rig["pwm_update"] == "immediate" and run.rig["V0a"] == 5.036e-5
    assert "seed" not in run.run and run.run["rig"] == "exec"
    assert np.ptp(run["/rig/sensors"]["x"].to_numpy()) > 1e-4  # the toy piston moved


def test_docs_show_the_c_driver_verbatim():
    """docs/deploy.md shows the whole C driver; it must be the file the tests compile."""
    text = (ROOT / "docs" / "deploy.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```c\n(.*?)```", text, re.DOTALL)
    assert C_DRIVER.read_text(encoding="utf-8") in blocks
