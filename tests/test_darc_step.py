"""The compiled DARC step (control/law/darc.py) against the plain-Python oracle of the paper's
equations (tests/darc_oracle.py), for every variant, and its documented behaviours."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from darc_oracle import DarcOracle, f_pd

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.law.darc import (
    MEAS_SIZE,
    S_A_R_PREV,
    S_CASE,
    S_DF_PD,
    S_STATUS,
    S_THETA,
    S_THETA_DOT,
    STATE_SIZE,
    control_state_record,
    init_state,
    make_meas,
    state_view,
    step,
    step_into,
)
from pneutune.control.law.layout import CFG_LAYOUT, pack
from pneutune.control.physics.pwm import sample_pwm_curve

PAPER = Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml"
VARIANTS = ("modified_darc", "original_darc", "direct_diff", "pid")
X_MID = 0.0235  # trajectories are centred at mid-stroke


def _cfg(variant: str, position_feedback: str = "measured", accel: str = "filtered"):
    base = load_controller(PAPER)
    return base.model_copy(update={"variant": variant, "position_feedback": position_feedback,
                                   "original_darc_accel": accel})


def _measurements(seed: int, n: int = 400) -> np.ndarray:
    """Plausible closed-loop samples: the 0.5 Hz sine of Table 1 (17.5 mm) plus a tracking error
    of a few tenths of a mm, 5 um position noise, chamber pressures wandering in 1.5-5.5 bar
    (kept away from p_s so Eq. 7's regularised top 0.1 % is never reached), supply 6 bar."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.004
    x_r = X_MID + 0.0175 * np.sin(np.pi * t)
    v_r = 0.0175 * np.pi * np.cos(np.pi * t)
    a_r = -0.0175 * np.pi**2 * np.sin(np.pi * t)
    err = 3e-4 * np.sin(2 * np.pi * 1.7 * t + rng.uniform(0, 6)) + rng.normal(0, 5e-6, n)
    p_a = np.clip(3.2e5 + np.cumsum(rng.normal(0, 4e3, n)), 1.5e5, 5.5e5)
    p_b = np.clip(3.0e5 + np.cumsum(rng.normal(0, 4e3, n)), 1.5e5, 5.5e5)
    p_s = 6.0e5 + rng.normal(0, 300, n)
    v_r[50:60] = 0.0  # a pause: |v_r| <= min_ref_speed, adaptation must hold
    return np.column_stack([t, x_r + err, p_a, p_b, p_s, x_r, v_r, a_r])


@pytest.mark.parametrize("position_feedback", ["measured", "filtered"])
@pytest.mark.parametrize("variant", [*VARIANTS, "original_darc/model"])
def test_step_matches_oracle(variant: str, position_feedback: str) -> None:
    """step == plain-Python oracle to ~1e-9 (relative) over 400 plausible steps."""
    variant, _, accel = variant.partition("/")
    cfg = _cfg(variant, position_feedback, accel or "filtered")
    vec = pack(cfg)
    ms = _measurements(seed=10 * VARIANTS.index(variant) + (position_feedback == "filtered")
                      + 100 * (accel == "model"))
    state = init_state(cfg, float(ms[0, 1]), 3.0e5, 3.0e5)
    oracle = DarcOracle(cfg, float(ms[0, 1]))
    cases = set()
    for k, meas in enumerate(ms):
        state, duties = step(state, meas, vec)
        d_ref = oracle.step(meas)
        np.testing.assert_allclose(duties, d_ref, rtol=0, atol=1e-9, err_msg=f"step {k}")
        rec = control_state_record(state)
        for name in ("e1", "e2", "e3", "x_hat", "v_hat", "a_hat", "F_pd", "dF_pd", "Q_Ld"):
            ref = oracle.s.log[name]
            assert rec[name] == pytest.approx(ref, rel=1e-9, abs=1e-9 * (1 + abs(ref))), (
                f"{name} at step {k}")
        np.testing.assert_allclose(rec["theta_hat"], oracle.s.log["theta_hat"], rtol=1e-9,
                                   atol=1e-12)
        cases.add(int(state[S_CASE]))
    assert cases & {2, 4}, "the run should exercise the PWM cases of Eq. (33)"


def test_step_matches_oracle_with_a_curve_per_valve() -> None:
    """Four valves with four timings (minimum pulses 1-3 ms, delays 1-4 ms, as the fleet's), each
    valve inverted on its own curve: the compiled step's duties equal the oracle's, which
    inverts each valve on ``cfg.valve_curves``, over 400 steps; the valves' duties differ for the
    same Eq. (33) fraction."""
    timings = ((1.0e-3, 2.0e-3, 1.0e-3), (3.5e-3, 1.5e-3, 2.5e-3), (2.0e-3, 4.0e-3, 2.0e-3),
               (4.0e-3, 3.0e-3, 3.0e-3))
    data = _cfg("modified_darc").to_dict()
    for name, (d_on, d_off, m_p) in zip(("a_in", "a_out", "b_in", "b_out"), timings, strict=True):
        duty, ratio = sample_pwm_curve(1.0 / 60.0, d_on, d_off, m_p)
        data["valves"][name]["pwm"] = {"duty": [float(x) for x in duty],
                                       "ratio": [float(x) for x in ratio]}
    cfg = ControllerConfig.model_validate(data)
    vec = pack(cfg)
    ms = _measurements(seed=7)
    state = init_state(cfg, float(ms[0, 1]), 3.0e5, 3.0e5)
    oracle = DarcOracle(cfg, float(ms[0, 1]))
    differ = 0
    for k, meas in enumerate(ms):
        state, duties = step(state, meas, vec)
        np.testing.assert_allclose(duties, oracle.step(meas), rtol=0, atol=1e-9,
                                   err_msg=f"step {k}")
        pair = (duties[0], duties[3]) if duties[0] > 0 else (duties[1], duties[2])
        differ += pair[0] != pair[1]
    assert differ > 0


def test_step_into_equals_step() -> None:
    """The zero-allocation form gives the same duties and state."""
    cfg = _cfg("modified_darc")
    vec = pack(cfg)
    ms = _measurements(1, 100)
    s1 = init_state(vec, float(ms[0, 1]), 3e5, 3e5)
    s2 = s1.copy()
    out = np.empty(4)
    for meas in ms:
        _, d = step(s1, meas, vec)
        step_into(s2, meas, vec, out)
        np.testing.assert_array_equal(d, out)
    np.testing.assert_array_equal(s1, s2)


def test_adaptation_holds_below_min_ref_speed() -> None:
    """Sec. 5.3: θ̂ changes only while |v_r| > min_ref_speed (0.001 m/s)."""
    cfg = _cfg("modified_darc")
    vec = pack(cfg)
    s = init_state(cfg, X_MID, 3e5, 3e5)
    theta0 = s[S_THETA:S_THETA + 6].copy()
    for k in range(50):
        step(s, make_meas(k * 0.004, X_MID + 1e-3, 3.5e5, 2.5e5, 6e5, X_MID, 0.0009, 0.0), vec)
    np.testing.assert_array_equal(s[S_THETA:S_THETA + 6], theta0)
    assert np.all(s[S_THETA_DOT:S_THETA_DOT + 6] == 0.0)
    step(s, make_meas(0.2, X_MID + 1e-3, 3.5e5, 2.5e5, 6e5, X_MID, 0.0011, 0.0), vec)
    assert np.any(s[S_THETA:S_THETA + 6] != theta0)


def test_theta_stays_in_bounds_under_extreme_errors() -> None:
    """Eq. (12) line 1 through the step: huge errors for 2 s push θ̂ to its bounds, not beyond."""
    cfg = _cfg("modified_darc")
    vec = pack(cfg)
    rng = np.random.default_rng(99)
    s = init_state(cfg, X_MID, 3e5, 3e5)
    lo = np.array(cfg.adaptation.theta_min)
    hi = np.array(cfg.adaptation.theta_max)
    for k in range(500):
        meas = make_meas(k * 0.004, rng.uniform(-0.0015, 0.0485), rng.uniform(1e5, 6e5),
                         rng.uniform(1e5, 6e5), 6e5, X_MID, rng.choice([-0.3, 0.3]),
                         rng.normal(0, 5))
        s, d = step(s, meas, vec)
        th = s[S_THETA:S_THETA + 6]
        assert np.all(th >= lo) and np.all(th <= hi)
        assert np.all((d >= 0) & (d <= 1))
        assert not (d[0] > 0 and d[1] > 0) and not (d[2] > 0 and d[3] > 0)


@pytest.mark.parametrize("accel", ["filtered", "model"])
def test_original_darc_dfpd_is_the_total_derivative_of_fpd(accel: str) -> None:
    """docs/original_darc.md: dF_pd/dt (calculable) = d/dt F_pd(x1, x2, t, θ̂) along x1' = x2,
    x2' = â ('filtered') or (F_p + θ̂2 - θ̂3 x2 - θ̂4 S_f(x2))/θ̂1 ('model'), θ̂' = effective
    rate: checked against a central finite difference of Eqs. (13), (17), (20). The step's
    backward-difference jerk of the reference is O(Ts) off (|j_r'| Ts/2 θ1 < 0.01 N/s here)."""
    cfg = _cfg("original_darc", accel=accel)
    vec = pack(cfg)
    s = init_state(cfg, X_MID, 3e5, 3e5)
    w = math.pi
    A = 0.0175
    Ts = cfg.rig.Ts

    def ref(t: float) -> tuple[float, float, float]:
        return (X_MID + A * math.sin(w * t), A * w * math.cos(w * t), -A * w**2 * math.sin(w * t))

    ms = _measurements(5, 200)
    for meas in ms[:199]:  # settle the filter and θ̂ on a plausible history
        step(s, meas, vec)
    t = float(ms[199, 0])
    x_r, v_r, a_r = ref(t)
    meas = make_meas(t, float(ms[199, 1]), 3.4e5, 2.9e5, 6e5, x_r, v_r, a_r)
    s[S_A_R_PREV] = ref(t - Ts)[2]
    theta_before = s[S_THETA:S_THETA + 6].copy()
    s, _ = step(s, meas, vec)
    view = state_view(s)
    x1, x2 = float(meas[1]), view["v_hat"]
    th, thdot = theta_before, view["theta_dot"]
    rig = cfg.rig
    F_p = rig.A_a * 3.4e5 - rig.A_b * 2.9e5 - rig.p0 * (rig.A_a - rig.A_b)
    x2dot = (F_p + th[1] - th[2] * x2 - th[3] * 2 / math.pi * math.atan(1000 * x2)) / th[0]
    if accel == "filtered":
        x2dot = view["a_hat"]
    h = 1e-8  # central difference; the atan term is strongly curved, keep h small

    def along(d: float) -> float:
        return f_pd(cfg, th + thdot * d, x1 + x2 * d, x2 + x2dot * d, *ref(t + d))

    fd = (along(h) - along(-h)) / (2 * h)
    assert s[S_DF_PD] == pytest.approx(fd, rel=1e-6, abs=0.05)


def test_direct_diff_is_backward_difference() -> None:
    """Fig. 11 variant: dF_pd = (F_pd[k] - F_pd[k-1]) / Ts; 0 at the first step."""
    cfg = _cfg("direct_diff")
    vec = pack(cfg)
    ms = _measurements(8, 20)
    s = init_state(cfg, float(ms[0, 1]), 3e5, 3e5)
    prev = None
    for meas in ms:
        s, _ = step(s, meas, vec)
        rec = control_state_record(s)
        expected = 0.0 if prev is None else (rec["F_pd"] - prev) / cfg.rig.Ts
        assert rec["dF_pd"] == pytest.approx(expected, rel=1e-12, abs=1e-9)
        prev = rec["F_pd"]


def test_wrong_layout_closes_all_valves() -> None:
    """A cfg vector of another layout: every valve closed, status 1 (no exception)."""
    cfg = _cfg("modified_darc")
    vec = pack(cfg)
    s = init_state(vec, X_MID, 3e5, 3e5)
    bad = vec.copy()
    bad[CFG_LAYOUT] = 0.0
    s, d = step(s, make_meas(0, X_MID + 0.01, 3e5, 3e5, 6e5, X_MID, 0.05, 0), bad)
    np.testing.assert_array_equal(d, 0.0)
    assert s[S_STATUS] == 1.0


def test_non_finite_measurement_closes_all_valves() -> None:
    """A NaN position gives a NaN Q_Ld: Eq. (33) case 3, all valves closed (no exception)."""
    cfg = _cfg("modified_darc")
    vec = pack(cfg)
    s = init_state(vec, X_MID, 3e5, 3e5)
    s, d = step(s, make_meas(0, float("nan"), 3e5, 3e5, 6e5, X_MID, 0.05, 0), vec)
    np.testing.assert_array_equal(d, 0.0)
    assert s[S_CASE] == 3


def test_sizes_and_init() -> None:
    """init_state: θ̂ = θ_0, x̂ = [x0, 0, 0]; sizes as documented."""
    cfg = _cfg("modified_darc")
    s = init_state(cfg, 0.01, 3e5, 3e5)
    assert s.shape == (STATE_SIZE,) and MEAS_SIZE == 8
    view = state_view(s)
    np.testing.assert_array_equal(view["theta_hat"], cfg.adaptation.theta_0)
    np.testing.assert_array_equal(view["x_motion"], [0.01, 0.0, 0.0])
    with pytest.raises(ValueError, match="pack"):
        init_state(np.zeros(3), 0.0, 3e5, 3e5)
