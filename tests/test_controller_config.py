"""controller.yaml (contract 4): strict loading, errors naming the key, round trip, schema, pack."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from pneutune.control.contracts.controller import (
    ControllerConfig,
    load_controller,
    save_controller,
)
from pneutune.control.contracts.json_schemas import schema_path, schema_text
from pneutune.control.contracts.yamlio import validate_model
from pneutune.control.errors import ConfigError
from pneutune.control.law.kalman import motion_model
from pneutune.control.law.layout import (
    CFG_DZ_DUTY,
    CFG_DZ_RATIO,
    CFG_GAMMA,
    CFG_K2,
    CFG_KM_A,
    CFG_KM_WQW,
    CFG_LAYOUT,
    CFG_LAYOUT_ID,
    CFG_PWM_DUTY,
    CFG_PWM_N,
    CFG_PWM_RATIO,
    CFG_SIZE,
    CFG_THETA_0,
    CFG_VALVE_C,
    CFG_VARIANT,
    PWM_STRIDE,
    pack,
)

PAPER = Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml"


def _paper_dict() -> dict[str, Any]:
    with open(PAPER, encoding="utf-8") as fh:
        return yaml.safe_load(fh)


def test_paper_config_has_the_sec51_values() -> None:
    """data/controller-paper.yaml holds Sec. 5.1: gains, Γ, θ̇_M, bounds, θ_0, Kalman Q/R in SI
    (the paper's Q = 3100, R = 1e-4 read in mm: 3.1e-3 m^2/s^4 and 1e-10 m^2)."""
    cfg = load_controller(PAPER)
    g = cfg.gains
    assert (g.k1, g.k2, g.k3, g.h2, g.h3, g.eps2, g.eps3, g.r2, g.r3) == (
        65.0, 6700.0, 50.0, 10.0, 100.0, 0.05, 250.0, 1.0, 0.1)
    a = cfg.adaptation
    assert a.gamma == (0.2, 300.0, 2000.0, 500.0, 100.0, 100.0)
    assert a.rate_max == (50.0, 500.0, 2000.0, 100.0, 50.0, 50.0)
    assert a.theta_min == (0.5, -10.0, 2000.0, -50.0, -20.0, -20.0)
    assert a.theta_max == (5.0, 10.0, 5000.0, 200.0, 20.0, 20.0)
    assert a.theta_0 == (0.9389, 0.0, 3500.0, 100.0, 0.0, 0.0)
    assert a.min_ref_speed == 0.001  # Sec. 5.3
    assert cfg.kalman.motion.Q == pytest.approx(3100 * 1e-6, rel=1e-12)
    assert cfg.kalman.motion.R == pytest.approx(1e-4 * 1e-6, rel=1e-12)
    assert cfg.rig.Ts == 0.004 and cfg.rig.pwm_hz == 60.0
    assert cfg.valves.a_in.C == 8.373e-9 and cfg.valves.b_out.b == 0.18561
    assert cfg.variant == "modified_darc" and cfg.position_feedback == "measured"


def test_round_trip_record_yaml_record(tmp_path: Path) -> None:
    """Record -> controller.yaml -> record unchanged (and dict unchanged)."""
    cfg = load_controller(PAPER)
    cfg = cfg.model_copy(update={"provenance": None})
    out = tmp_path / "c.yaml"
    save_controller(cfg, out, header="round trip")
    again = load_controller(out)
    assert again == cfg
    assert again.to_dict() == cfg.to_dict()
    np.testing.assert_array_equal(pack(again), pack(cfg))


def test_round_trip_with_provenance(tmp_path: Path) -> None:
    """Provenance (optional) survives the round trip."""
    data = _paper_dict()
    data["provenance"] = {"model_sha256": "ab" * 32, "study": "s", "trial": 3,
                          "objective": 0.25, "created": "2024-01-01T00:00:00Z", "version": "0.1"}
    p = tmp_path / "in.yaml"
    p.write_text(yaml.safe_dump(data), encoding="utf-8")
    cfg = load_controller(p)
    save_controller(cfg, tmp_path / "out.yaml")
    assert load_controller(tmp_path / "out.yaml") == cfg


def _set(data: dict, path: str, value: Any) -> dict:
    data = copy.deepcopy(data)
    keys = path.split(".")
    node = data
    for k in keys[:-1]:
        node = node[k]
    if value is _DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


_DELETE = object()

BAD = [
    # (what, key path to change, new value, key the error must name, text in the message)
    ("unknown top-level key", "gain", {"k1": 1.0}, "gain", "unknown key"),
    ("unknown nested key", "gains.k4", 1.0, "gains.k4", "unknown key"),
    ("misspelt valve", "valves.a_inn", {"C": 1e-9, "b": 0.2}, "valves.a_inn", "unknown key"),
    ("missing block", "kalman", _DELETE, "kalman", "missing"),
    ("missing key", "gains.k1", _DELETE, "gains.k1", "missing"),
    ("wrong type", "gains.k2", "fast", "gains.k2", "number"),
    ("number in quotes", "rig.p_s", "6.0e+5", "rig.p_s", "without them"),
    ("bool for a float", "gains.k3", True, "gains.k3", "number"),
    ("out of range, k1 <= 0", "gains.k1", -1.0, "gains.k1", "greater than 0"),
    ("out of range, Kalman R", "kalman.motion.R", 0.0, "kalman.motion.R", "greater than 0"),
    ("negative gamma", "adaptation.gamma", [0.2, -300.0, 2000.0, 500.0, 100.0, 100.0],
     "adaptation.gamma[1]", "greater than or equal to 0"),
    ("theta_min >= theta_max", "adaptation.theta_min", [0.5, -10.0, 6000.0, -50.0, -20.0, -20.0],
     "adaptation", "theta_min < theta_0 < theta_max"),
    ("theta_0 on a bound", "adaptation.theta_0", [0.5, 0.0, 3500.0, 100.0, 0.0, 0.0],
     "adaptation", "M (index 0)"),
    ("vector too short", "adaptation.rate_max", [50.0, 500.0, 2000.0, 100.0, 50.0],
     "adaptation.rate_max", "expected 6 values"),
    ("vector too long", "adaptation.theta_0", [0.9, 0.0, 3500.0, 100.0, 0.0, 0.0, 1.0],
     "adaptation.theta_0", "expected 6 values"),
    ("non-finite", "gains.k2", float("nan"), "gains.k2", "finite"),
    ("pwm not monotone in ratio", "pwm.ratio", [0.0, 0.5, 0.4, 1.0], "pwm",
     "non-decreasing"),
    ("pwm not monotone in duty", "pwm.duty", [0.0, 0.6, 0.5, 1.0], "pwm", "non-decreasing"),
    ("pwm not from (0, 0)", "pwm.ratio", [0.1, 0.2, 0.5, 1.0], "pwm", "(0, 0)"),
    ("pwm ratio above 1", "pwm.ratio", [0.0, 0.2, 0.5, 1.2], "pwm.ratio[3]",
     "less than or equal to 1"),
    ("pwm lengths differ", "pwm.ratio", [0.0, 0.5, 1.0], "pwm", "same length"),
    ("bad variant", "variant", "fancy_darc", "variant", "modified_darc"),
    ("bad position_feedback", "position_feedback", "raw", "position_feedback", "measured"),
    ("bad schema", "schema", "pneutune.controller/2", "schema", "pneutune.controller/1"),
    ("limits x_max <= x_min", "limits.x_max", -0.01, "limits", "x_max > x_min"),
    # a p_max below ambient passed, then deploy stopped at t = 0 with an "overpressure" fault
    ("limits p_max <= p0", "limits.p_max", 5.0e4, "", "limits.p_max > rig.p0"),
    ("rig rule", "rig.A_b", 9e-3, "rig.A_b", "A_b <= A_a"),
    ("pid negative gain", "pid.kp", -1.0, "pid.kp", "greater than or equal to 0"),
]


@pytest.mark.parametrize(("what", "path", "value", "key", "text"), BAD,
                         ids=[b[0] for b in BAD])
def test_bad_configs_raise_config_error_naming_the_key(tmp_path: Path, what: str, path: str,
                                                       value: Any, key: str, text: str) -> None:
    """Each bad controller.yaml raises ConfigError naming the key path and the rule."""
    data = _paper_dict()
    data["pwm"] = {"duty": [0.0, 0.3, 0.6, 1.0], "ratio": [0.0, 0.3, 0.7, 1.0]}
    data = _set(data, path, value)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_controller(p)
    assert exc.value.key == key, str(exc.value)
    assert text in exc.value.message, str(exc.value)
    assert str(p) in str(exc.value)


def test_literal_6_0e5_in_yaml_text(tmp_path: Path) -> None:
    """`p_s: 6.0e5` is the number 6e5: the files are read as YAML 1.2 (YAML 1.1 read a
    mantissa with an unsigned exponent as a string)."""
    text = PAPER.read_text(encoding="utf-8").replace("p_s: 6.0e+5", "p_s: 6.0e5")
    assert "p_s: 6.0e5" in text
    p = tmp_path / "c.yaml"
    p.write_text(text, encoding="utf-8")
    assert load_controller(p).rig.p_s == 6.0e5


def test_yaml_1_2_words_are_strings_and_aliases_are_refused(tmp_path: Path) -> None:
    """YAML 1.2: `yes` is a string, not true, so a boolean key given `yes` names the key; an
    anchor and alias (whose nesting expands exponentially) is refused with its line."""
    text = PAPER.read_text(encoding="utf-8")
    p = tmp_path / "c.yaml"
    p.write_text(text.replace("variant: modified_darc", "variant: yes"), encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_controller(p)
    assert exc.value.key == "variant"
    lines = ["a: &x [1, 2]", "b: [*x, *x]", "c: [*x, *x]"]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"an anchor \(&x\) at line 1; .*not allowed"):
        load_controller(p)
    # an anchor nothing refers to is refused as well: a contract file has no use for one
    p.write_text(text.replace("variant: modified_darc", "variant: &v modified_darc"),
                 encoding="utf-8")
    with pytest.raises(ConfigError, match=r"an anchor \(&v\) at line \d+; "):
        load_controller(p)


def test_duplicate_key_rejected(tmp_path: Path) -> None:
    """A key given twice is an error (yamlio), not a silent overwrite."""
    text = PAPER.read_text(encoding="utf-8") + "variant: pid\n"
    p = tmp_path / "c.yaml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match="duplicate key"):
        load_controller(p)


def test_committed_schema_is_current() -> None:
    """control/contracts/schemas/controller.schema.json == the models' schema. Regenerate with
    `python -m pneutune.control.contracts.json_schemas`."""
    assert schema_path("controller").read_text(encoding="utf-8") == schema_text("controller")
    schema = json.loads(schema_text("controller"))
    assert schema["additionalProperties"] is False
    assert {"position_feedback", "pid", "provenance"} <= set(schema["properties"])


def test_pack_layout() -> None:
    """pack(): values at the documented CFG_* indices, Eq. (34) matrices precomputed."""
    cfg = load_controller(PAPER)
    v = pack(cfg)
    assert v.shape == (CFG_SIZE,) and v.dtype == np.float64
    assert v[CFG_LAYOUT] == CFG_LAYOUT_ID
    assert v[CFG_VARIANT] == 0 and v[CFG_K2] == 6700.0
    np.testing.assert_array_equal(v[CFG_GAMMA:CFG_GAMMA + 6], cfg.adaptation.gamma)
    np.testing.assert_array_equal(v[CFG_THETA_0:CFG_THETA_0 + 6], cfg.adaptation.theta_0)
    np.testing.assert_array_equal(v[CFG_VALVE_C:CFG_VALVE_C + 4], [8.373e-9] * 4)
    A, W, _ = motion_model(0.004)
    np.testing.assert_allclose(v[CFG_KM_A:CFG_KM_A + 9].reshape(3, 3), A, rtol=1e-15)
    np.testing.assert_allclose(v[CFG_KM_WQW:CFG_KM_WQW + 9].reshape(3, 3),
                               3.1e-3 * np.outer(W, W), rtol=1e-12)
    for i in range(4):  # no valve has a curve of its own: each slot holds the shared one
        m, at = int(v[CFG_PWM_N + i]), i * PWM_STRIDE
        assert m == len(cfg.pwm.duty)
        np.testing.assert_array_equal(v[CFG_PWM_DUTY + at:CFG_PWM_DUTY + at + m], cfg.pwm.duty)
        np.testing.assert_array_equal(v[CFG_PWM_RATIO + at:CFG_PWM_RATIO + at + m],
                                      cfg.pwm.ratio)


def test_a_valve_with_its_own_pwm_curve(tmp_path: Path) -> None:
    """``valves.<v>.pwm`` (added by pneutune): b_out's own curve is packed in b_out's slot, the
    others keep the top-level curve; the file round-trips, and a valve without a curve of its
    own is written without the key (no ``pwm: null``)."""
    raw = _paper_dict()
    own = {"duty": [0.0, 0.15, 0.15, 1.0], "ratio": [0.0, 0.0, 0.2, 1.0]}
    raw["valves"]["b_out"]["pwm"] = own
    cfg = ControllerConfig.model_validate(raw)
    assert cfg.valve_curves[3].duty == tuple(own["duty"])
    assert cfg.valve_curves[0] is cfg.pwm
    assert cfg.top_duties == (cfg.pwm.top_duty,) * 3 + (1.0,)
    v = pack(cfg)
    at = 3 * PWM_STRIDE
    assert v[CFG_PWM_N + 3] == 4 and v[CFG_PWM_N] == len(cfg.pwm.duty)
    np.testing.assert_array_equal(v[CFG_PWM_RATIO + at:CFG_PWM_RATIO + at + 4], own["ratio"])
    assert (v[CFG_DZ_DUTY + 3], v[CFG_DZ_RATIO + 3]) == (0.15, 0.2)
    save_controller(cfg, tmp_path / "c.yaml")
    text = (tmp_path / "c.yaml").read_text(encoding="utf-8")
    assert "pwm: null" not in text and text.count("pwm:") == 2
    assert load_controller(tmp_path / "c.yaml") == cfg
    bad = copy.deepcopy(raw)
    bad["valves"]["a_in"]["pwm"] = {"duty": [0.0, 0.5], "ratio": [0.1, 1.0]}
    with pytest.raises(ConfigError, match=r"valves\.a_in\.pwm"):
        validate_model(ControllerConfig, bad, "c.yaml")


def test_model_is_frozen() -> None:
    """Records are frozen."""
    cfg = load_controller(PAPER)
    with pytest.raises(Exception, match="frozen"):
        cfg.variant = "pid"  # type: ignore[misc]
    assert isinstance(cfg, ControllerConfig)
