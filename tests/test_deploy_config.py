"""deploy's loading: a table of bad controller.yaml files, each giving
exit status 2 and one `error:` line that names the file and the key; nothing runs (no log)."""

from __future__ import annotations

import copy
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from pneutune.control.cli.common import run_cli
from pneutune.control.cli.deploy import main
from pneutune.control.errors import ExperimentError
from pneutune.control.sim.scenarios import resolve_scenarios

ROOT = Path(__file__).resolve().parents[1]
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"


def _paper() -> dict[str, Any]:
    with open(PAPER_YAML, encoding="utf-8") as fh:
        return yaml.safe_load(fh)


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def edit(d: dict[str, Any]) -> None:
        *head, last = path.split(".")
        for k in head:
            d = d[k]
        d[last] = value
    return edit


def _delete(path: str) -> Callable[[dict[str, Any]], None]:
    def edit(d: dict[str, Any]) -> None:
        *head, last = path.split(".")
        for k in head:
            d = d[k]
        del d[last]
    return edit


def _theta_min_above_max(d: dict[str, Any]) -> None:
    d["adaptation"]["theta_min"][2] = 6000.0  # b_v: theta_max[2] = 5000


def _theta_min_equal_max(d: dict[str, Any]) -> None:
    d["adaptation"]["theta_min"][0] = d["adaptation"]["theta_max"][0]


def _pwm_not_monotone(d: dict[str, Any]) -> None:
    d["pwm"]["ratio"][10] = 0.9


# (id, edit, words the error line must contain: the key path, then the rule's words)
BAD: list[tuple[str, Callable[[dict[str, Any]], None], tuple[str, ...]]] = [
    ("unknown-top-key", _set("gainz", {"k1": 1.0}), ("gainz", "unknown key")),
    ("unknown-nested-key", _set("gains.k4", 1.0), ("gains.k4", "unknown key")),
    ("unknown-limits-key", _set("limits.v_max", 0.1), ("limits.v_max", "unknown key")),
    ("wrong-type-string", _set("gains.k1", "fast"), ("gains.k1", "number")),
    ("wrong-type-bool", _set("gains.k2", True), ("gains.k2",)),
    ("number-in-quotes", _set("rig.p_s", "6.0e+5"), ("rig.p_s", "without them")),
    ("wrong-type-list", _set("kalman.motion.R", [1.0e-10]), ("kalman.motion.R",)),
    ("negative-gain", _set("gains.k1", -65.0), ("gains.k1", "greater than")),
    ("p_max-zero", _set("limits.p_max", 0.0), ("limits.p_max", "greater than")),
    ("timeout-too-long", _set("limits.sensor_timeout_s", 60.0),
     ("limits.sensor_timeout_s", "less than")),
    ("valve-C-zero", _set("valves.a_in.C", 0.0), ("valves.a_in.C", "greater than")),
    ("nan-value", _set("gains.k3", float("nan")), ("gains.k3",)),
    ("theta-min-above-max", _theta_min_above_max, ("adaptation", "theta_min", "b_v")),
    ("theta-min-equal-max", _theta_min_equal_max, ("adaptation", "theta_min", "M")),
    ("theta-vector-length", _set("adaptation.gamma", [1.0, 2.0]), ("adaptation.gamma", "6")),
    ("limits-x-order", _set("limits.x_max", -0.01), ("limits", "x_max > x_min")),
    ("pwm-not-monotone", _pwm_not_monotone, ("pwm", "non-decreasing")),
    ("unknown-variant", _set("variant", "lqr"), ("variant",)),
    ("bad-position-feedback", _set("position_feedback", "raw"), ("position_feedback",)),
    ("missing-block", _delete("kalman"), ("kalman", "missing")),
    ("missing-key", _delete("gains.eps3"), ("gains.eps3", "missing")),
    ("wrong-schema", _set("schema", "pneutune.controller/2"), ("schema",)),
    ("Ts-not-the-rig's", _set("rig.Ts", 0.005), ("rig.Ts", "0.004")),
    ("pwm_hz-not-the-rig's", _set("rig.pwm_hz", 50.0), ("rig.pwm_hz", "60.0")),
]


def _write(tmp_path: Path, edit: Callable[[dict[str, Any]], None]) -> Path:
    data = copy.deepcopy(_paper())
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def _error_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ")
    return lines[0]


@pytest.mark.parametrize(("edit", "words"), [(e, w) for _, e, w in BAD],
                         ids=[i for i, _, _ in BAD])
def test_bad_config_exit_2_naming_the_key(tmp_path, capsys, edit, words):
    """Each bad config: exit 2 through the CLI wrapper, exactly one `error:` line naming the
    file and the key path (and the rule), and no log written (nothing ran)."""
    path = _write(tmp_path, edit)
    log = tmp_path / "never.mcap"
    with pytest.raises(SystemExit) as exc:
        run_cli(main, [str(path), "--duration", "0.1", "--log", str(log)])
    assert exc.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    line = _error_line(captured.err)
    assert str(path) in line
    for w in words:
        assert w in line, (w, line)
    assert not log.exists()


def test_at_least_15_bad_configs():
    assert len(BAD) >= 15


@pytest.mark.parametrize("case", ["unknown-nested-key", "theta-min-above-max",
                                  "Ts-not-the-rig's", "number-in-quotes"])
def test_bad_config_via_the_command(tmp_path, case):
    """The same through the console command in a subprocess (no traceback, exit 2)."""
    _, edit, words = next(b for b in BAD if b[0] == case)
    path = _write(tmp_path, edit)
    proc = subprocess.run([sys.executable, "-m", "pneutune.control.cli.deploy", str(path),
                           "--log", str(tmp_path / "never.mcap")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert proc.stdout == ""
    line = _error_line(proc.stderr)
    assert all(w in line for w in words), line
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "never.mcap").exists()


def test_duplicate_key_and_bad_yaml(tmp_path, capsys):
    """YAML-level problems: a key given twice is named; a syntax error gives its line."""
    dup = tmp_path / "dup.yaml"
    dup.write_text(PAPER_YAML.read_text(encoding="utf-8")
                   + "gains: {k1: 1.0}\n", encoding="utf-8")
    broken = tmp_path / "broken.yaml"
    broken.write_text("schema: [unclosed\n", encoding="utf-8")
    for path, word in ((dup, "duplicate key 'gains'"), (broken, "line")):
        with pytest.raises(SystemExit) as exc:
            run_cli(main, [str(path)])
        assert exc.value.code == 2
        assert word in _error_line(capsys.readouterr().err)


def test_plant_timing_mismatch(tmp_path, capsys):
    """The rig's Ts comes from the plant given with --rig sim:P.yaml: a plant at 5 ms rejects
    the paper's 4 ms controller, naming rig.Ts and the plant file."""
    plant = tmp_path / "plant.yaml"
    plant.write_text("rig: {Ts: 0.005}\n", encoding="utf-8")
    with pytest.raises(SystemExit) as exc:
        run_cli(main, [str(PAPER_YAML), "--rig", f"sim:{plant}"])
    assert exc.value.code == 2
    line = _error_line(capsys.readouterr().err)
    assert "rig.Ts" in line and str(plant) in line and "0.005" in line


def test_another_cylinders_controller_runs_with_a_warning() -> None:
    """Geometry differences run (model error), but each is said: the paper's controller on a
    63 mm bore (A_a 3.117e-3 m^2 against its 7.854e-3: -60 %) with a 40 mm stroke, inside its
    limits [-1.5, 48.5] mm only at the start; on the paper's own rig, nothing."""
    from pneutune.control.contracts.controller import load_controller
    from pneutune.control.contracts.plant import PlantConfig
    from pneutune.control.rig.deploy import geometry_warnings

    paper = load_controller(PAPER_YAML)
    assert geometry_warnings(paper, PlantConfig().rig_metadata(), "c.yaml", "sim") == []
    other = PlantConfig().with_updates({"rig": {"A_a": 3.117e-3, "A_b": 2.803e-3,
                                                "x_min": 0.0, "x_max": 0.04}})
    found = geometry_warnings(paper, other.rig_metadata(), "c.yaml", "plant p.yaml")
    assert len(found) == 2
    assert "A_a 0.007854 against 0.003117 m^2 (+152%)" in found[0]
    assert "V0a" not in found[0]  # the dead volumes are the same
    assert "[-1.50, 48.50] mm of c.yaml reach past the rig's stroke [0.00, 40.00]" in found[1]


@pytest.mark.parametrize(("argv", "word"), [
    (["--scenario", "sine-9hz"], "unknown scenario"),
    (["--scenario", "sine-0.5hz,sine-9hz"], "unknown scenario 'sine-9hz'"),
    (["--rig", "hardware"], "unknown rig"),
    (["--rig", "sim:"], "empty"),
    (["--duration", "-1"], "--duration"),
    (["--seed", "-2"], "--seed"),
    (["--fail-safe", "open"], "invalid choice"),
])
def test_bad_arguments(capsys, argv, word):
    """Bad arguments: exit 2, one error line."""
    with pytest.raises(SystemExit) as exc:
        run_cli(main, [str(PAPER_YAML), *argv])
    assert exc.value.code == 2
    assert word in _error_line(capsys.readouterr().err)


def test_scenario_lists_resolve_in_order_each_once() -> None:
    """``--scenario`` of deploy and simulate takes a comma-separated list (names and groups)."""
    names = [sc.name for sc in resolve_scenarios("square-0.5hz, sine-0.5hz,table1")]
    assert names == ["square-0.5hz", "sine-0.5hz", "sine-0.75hz", "sine-0.5hz-heavy"]
    with pytest.raises(ExperimentError, match="unknown scenario 'sine-9hz'"):
        resolve_scenarios("sine-0.5hz,sine-9hz")
