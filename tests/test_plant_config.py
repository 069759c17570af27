"""plant.yaml (contract 2): bad files are ConfigErrors naming the file and the key; a
partial file merges over the paper defaults; the CLI turns a bad plant into one ``error:`` line
and exit status 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from pneutune.control.contracts.plant import PlantConfig, load_plant
from pneutune.control.errors import ConfigError

SIMULATE = Path(sys.executable).with_name("simulate")

# (id, file text, expected ConfigError.key, text the message must contain).
# The key is the dotted path of the offending value; rules that tie two values together are
# reported on their block (rig, valves.b_out, disturbance) and name both values in the message;
# problems of the file as a whole have an empty key and the message names the problem.
BAD_FILES = [
    ("unknown-top-level-key", "mass: 1.0\nmasss: 2.0\n", "masss", "unknown key"),
    ("misspelt-nested-key", "valves:\n  a_in:\n    delay_onn: 0.001\n",
     "valves.a_in.delay_onn", "unknown key"),
    ("misspelt-block", "frictoin:\n  F_S: 80.0\n", "frictoin", "unknown key"),
    ("number-in-quotes", "rig:\n  p_s: '6.0e5'\n", "rig.p_s", "without them"),
    ("string-number", "mass: '1.05'\n", "mass", "expected a number"),
    ("negative-area", "rig:\n  A_a: -7.854e-3\n", "rig.A_a", "greater than 0"),
    ("x_max-equal-x_min", "rig:\n  x_min: 0.05\n  x_max: 0.05\n", "rig.x_max", "x_max > x_min"),
    ("x_max-below-x_min", "rig:\n  x_min: 0.01\n  x_max: -0.01\n", "rig.x_max", "x_max > x_min"),
    ("min_pulse-above-delay_on", "valves:\n  b_out:\n    min_pulse: 0.003\n    delay_on: 0.002\n",
     "valves.b_out.min_pulse", "min_pulse <= delay_on"),
    ("b-not-below-1", "valves:\n  a_out:\n    b: 1.0\n", "valves.a_out.b", "0.95"),
    ("unknown-pwm_update", "rig:\n  pwm_update: sometimes\n", "rig.pwm_update", "latched"),
    ("force_steps-not-increasing",
     "disturbance:\n  force_steps: [[1.0, 10.0], [1.0, 20.0]]\n", "disturbance.force_steps",
     "force_steps times must increase strictly"),
    ("force_step-not-a-pair", "disturbance:\n  force_steps: [[1.0, 2.0, 3.0]]\n",
     "disturbance.force_steps[0]", "at most 2 items"),
    ("F_S-below-F_C", "friction:\n  F_S: 10.0\n  F_C: 20.0\n", "friction.F_C", "F_C <= F_S"),
    ("seed-not-an-integer", "sim:\n  seed: 1.5\n", "sim.seed", "integer"),
    ("nan-mass", "mass: .nan\n", "mass", "nan"),
    ("block-not-a-mapping", "rig: 5\n", "rig", "dictionary"),
    ("wrong-schema", "schema: pneutune.model/1\n", "schema", "pneutune.plant/1"),
    ("duplicate-key", "mass: 1.0\nmass: 2.0\n", "", "duplicate key 'mass'"),
    ("not-a-mapping", "- 1\n- 2\n", "", "expected a mapping"),
    ("invalid-yaml", "rig: {A_a: 1\n", "", "not valid YAML"),
    # Python reads integers of at most 4300 digits; the parser's ValueError was a traceback
    ("integer-of-5001-digits", "mass: " + "1" * 5001 + "\n", "",
     "a value cannot be read as a number (Exceeds the limit (4300 digits)"),
]


@pytest.mark.parametrize(("text", "key", "needle"), [c[1:] for c in BAD_FILES],
                         ids=[c[0] for c in BAD_FILES])
def test_bad_plant_file_raises_config_error_naming_the_key(tmp_path: Path, text: str, key: str,
                                                           needle: str) -> None:
    path = tmp_path / "plant.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_plant(path)
    err = info.value
    assert isinstance(err, ValueError)  # typed errors subclass a builtin
    assert err.file == str(path)
    assert err.key == key
    message = str(err)
    assert message.startswith(f"{path}: ")
    if key:
        assert f": {key}: " in message
    assert needle in message


def test_missing_plant_file_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "nowhere" / "plant.yaml"
    with pytest.raises(ConfigError, match="no such file") as info:
        load_plant(path)
    assert info.value.file == str(path)
    assert str(path) in str(info.value)


def test_with_updates_validates_like_the_file() -> None:
    """The override path must not skip validation."""
    with pytest.raises(ConfigError) as info:
        PlantConfig().with_updates({"valves": {"a_in": {"C": -1.0}}})
    assert info.value.key == "valves.a_in.C"


def test_partial_file_merges_over_the_defaults(tmp_path: Path) -> None:
    """Contract 2: a partial file is merged over the paper's rig, block by block and valve by
    valve; untouched keys keep the defaults (Sec. 5.1: A_a = 7.854e-3 m^2, p_s = 6 bar,
    C = 8.373e-9 m^3/(s Pa), b = 0.18561; b_v = 3500 N s/m)."""
    path = tmp_path / "plant.yaml"
    path.write_text(
        "schema: pneutune.plant/1\n"
        "mass: 2.0\n"
        "rig: {p_s: 7.0e+5, pwm_update: latched}\n"
        "friction: {F_C: 40.0}\n"
        "valves:\n  a_in: {C: 1.0e-8}\n"
        "disturbance: {force_steps: [[1.0, 30.0], [2.5, -10.0]]}\n",
        encoding="utf-8")
    cfg = load_plant(path)
    default = PlantConfig()
    assert cfg.mass == 2.0 and cfg.payload == default.payload == 0.0
    assert cfg.rig.p_s == 7.0e5 and cfg.rig.pwm_update == "latched"
    assert cfg.rig.A_a == default.rig.A_a == 7.854e-3
    assert cfg.rig.T0 == default.rig.T0 == 283.15
    assert cfg.friction.F_C == 40.0
    assert cfg.friction.F_S == default.friction.F_S
    assert cfg.friction.b_v == default.friction.b_v == 3500.0
    assert cfg.valves.a_in.C == 1.0e-8
    assert cfg.valves.a_in.b == default.valves.a_in.b == 0.18561
    assert cfg.valves.a_in.delay_on == default.valves.a_in.delay_on
    assert cfg.valves.b_out == default.valves.b_out
    assert cfg.valves.b_out.C == 8.373e-9
    assert cfg.disturbance.force_steps == ((1.0, 30.0), (2.5, -10.0))
    assert cfg.sensors == default.sensors and cfg.sim == default.sim


def test_empty_file_is_the_defaults(tmp_path: Path) -> None:
    path = tmp_path / "plant.yaml"
    path.write_text("# nothing here\n", encoding="utf-8")
    assert load_plant(path) == PlantConfig()


def test_cli_bad_plant_is_one_error_line_and_exit_2(tmp_path: Path) -> None:
    """Bad input -> exit status 2, one line ``error: ...`` on stderr naming the file
    and the key, no traceback, nothing on stdout, no log written."""
    plant = tmp_path / "bad-plant.yaml"
    plant.write_text("rig:\n  p_s: -6.0e5\n", encoding="utf-8")
    out = tmp_path / "run.mcap"
    proc = subprocess.run(
        [str(SIMULATE), "--experiment", "identification", "--seed", "1", "--plant", str(plant),
         "--out", str(out), "--json"],
        capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    assert str(plant) in lines[0]
    assert "rig.p_s" in lines[0]
    assert "Traceback" not in proc.stderr
    assert proc.stdout == ""
    assert not out.exists()


def test_an_exponent_without_a_sign_is_a_number(tmp_path: Path) -> None:
    """The files are read as YAML 1.2: ``p_s: 6.0e5`` is 600 kPa, as ``6.0e+5`` is."""
    path = tmp_path / "plant.yaml"
    path.write_text("rig:\n  p_s: 6.0e5\nvalves:\n  a_in: {C: 9e-9}\n", encoding="utf-8")
    plant = load_plant(path)
    assert plant.rig.p_s == 6.0e5
    assert plant.valves.a_in.C == 9.0e-9
