"""Duty logic of Eqs. (32)-(33) (corrected: Q_L,F = sum of the active mode's fully-open terms,
Eq. 33 divides by Q_L,F) and the inverse of the PWM duty curve."""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.control.constants import RHO0, T_REF
from pneutune.control.law.duty import (
    CASE_A_FILL,
    CASE_A_FILL_NO_FLOW,
    CASE_B_FILL,
    CASE_B_FILL_NO_FLOW,
    CASE_CLOSED,
    duties_into,
    eq33_into,
    fully_open_q_l,
    pwm_inverse,
)
from pneutune.control.physics.pwm import effective_open_fraction, sample_pwm_curve

# Sec. 5.1 rig values.
A_A, A_B, P0, PS, T0, N, R = 7.854e-3, 7.54e-3, 101325.0, 6.0e5, 283.15, 1.2, 287.0
C = np.full(4, 8.373e-9)
B = np.full(4, 0.18561)
# Default plant valves (plant_config.ValveConfig) at 60 Hz.
PERIOD, D_ON, D_OFF, MIN_PULSE = 1.0 / 60.0, 2.0e-3, 3.0e-3, 1.5e-3
DUTY, RATIO = (np.array(v) for v in sample_pwm_curve(PERIOD, D_ON, D_OFF, MIN_PULSE, 41))


def _choked(p_u: float) -> float:
    """Eq. (7), choked branch: C rho0 p_u sqrt(T_ref/T_u)."""
    return 8.373e-9 * RHO0 * p_u * np.sqrt(T_REF / T0)


def test_eq32_mode1_is_sum_of_fully_open_terms() -> None:
    """Eq. (32), Q_Ld > 0: nRT0 [A_a mdot_a,in / V_a + A_b mdot_b,out / V_b], and Q_Ld < 0:
    nRT0 [A_a mdot_a,out / V_a + A_b mdot_b,in / V_b], with mdot from Eq. (7) written out here
    (pressure ratios 0.3 and 0.25: both on the subsonic branch since b = 0.18561)."""
    p_a, p_b, V_a, V_b = 1.8e5, 4.0e5, 2.0e-4, 2.5e-4
    q = fully_open_q_l(1.0, p_a, p_b, PS, P0, T0, N * R, A_A, A_B, V_a, V_b, C, B)

    def eq7(p_u: float, p_d: float) -> float:
        r = p_d / p_u
        if r <= 0.18561:
            return _choked(p_u)
        return _choked(p_u) * np.sqrt(1 - ((r - 0.18561) / (1 - 0.18561)) ** 2)

    expected = N * R * T0 * (A_A * eq7(PS, p_a) / V_a + A_B * eq7(p_b, P0) / V_b)
    assert q == pytest.approx(expected, rel=1e-9)
    q2 = fully_open_q_l(-1.0, p_a, p_b, PS, P0, T0, N * R, A_A, A_B, V_a, V_b, C, B)
    expected2 = N * R * T0 * (A_A * eq7(p_a, P0) / V_a + A_B * eq7(PS, p_b) / V_b)
    assert q2 == pytest.approx(expected2, rel=1e-9)
    assert fully_open_q_l(0.0, p_a, p_b, PS, P0, T0, N * R, A_A, A_B, V_a, V_b, C, B) == 0.0


def test_eq32_zero_when_no_pressure_difference() -> None:
    """Eq. (32): Q_L,F = 0 when p_a = p_s and p_b = p0 in mode 1 (no flow possible)."""
    q = fully_open_q_l(1.0, PS, P0, PS, P0, T0, N * R, A_A, A_B, 2e-4, 2e-4, C, B)
    assert q == 0.0


@pytest.mark.parametrize(
    ("name", "q_ld", "q_lf", "case", "u"),
    [
        ("case1: Q_Ld>0, Q_LF=0 -> u(a_in,b_out)=1", 500.0, 0.0, CASE_A_FILL_NO_FLOW,
         [1, 0, 0, 1]),
        ("case2: Q_Ld>0, Q_LF!=0 -> sat(Q_Ld/Q_LF)", 500.0, 2000.0, CASE_A_FILL,
         [0.25, 0, 0, 0.25]),
        ("case2 saturated", 5000.0, 2000.0, CASE_A_FILL, [1, 0, 0, 1]),
        ("case3: Q_Ld=0 -> all closed", 0.0, 2000.0, CASE_CLOSED, [0, 0, 0, 0]),
        ("case4: Q_Ld<0, Q_LF!=0 -> sat(-Q_Ld/Q_LF)", -300.0, 1000.0, CASE_B_FILL,
         [0, 0.3, 0.3, 0]),
        ("case4 saturated", -3000.0, 1000.0, CASE_B_FILL, [0, 1, 1, 0]),
        ("case5: Q_Ld<0, Q_LF=0 -> u(a_out,b_in) full (the paper's -1)", -300.0, 0.0,
         CASE_B_FILL_NO_FLOW, [0, 1, 1, 0]),
        ("non-finite Q_Ld -> closed", float("nan"), 1000.0, CASE_CLOSED, [0, 0, 0, 0]),
    ],
)
def test_eq33_five_cases(name: str, q_ld: float, q_lf: float, case: int, u: list) -> None:
    """Eq. (33), each case; the ratio divides by Q_L,F (the paper's typo Q_L corrected)."""
    out = np.empty(4)
    assert eq33_into(q_ld, q_lf, out) == case, name
    np.testing.assert_allclose(out, u, rtol=1e-12, atol=0)


def test_pwm_curve_samples_the_plant_formula() -> None:
    """The sampled curve equals valves.effective_open_fraction at every sample off the jump."""
    for d, r in zip(DUTY, RATIO, strict=True):
        if abs(d - MIN_PULSE / PERIOD) > 1e-12:
            assert r == pytest.approx(
                effective_open_fraction(d, PERIOD, D_ON, D_OFF, MIN_PULSE), abs=1e-12)
    assert DUTY[0] == 0.0 and RATIO[0] == 0.0
    assert np.all(np.diff(DUTY) >= 0) and np.all(np.diff(RATIO) >= 0)


@pytest.mark.parametrize("ratio", np.linspace(0.151, 0.999, 37))
def test_pwm_inverse_inverts_the_plant_curve(ratio: float) -> None:
    """Between the dead zone and saturation, the plant's effective fraction of the commanded
    duty is the wanted ratio (the curve is linear there: ratio = duty + (delay_off-delay_on)/T)."""
    d = pwm_inverse(ratio, DUTY, RATIO)
    assert effective_open_fraction(d, PERIOD, D_ON, D_OFF, MIN_PULSE) == pytest.approx(
        ratio, abs=1e-12)


def test_pwm_inverse_dead_zone_and_saturation() -> None:
    """Smallest duty achieving the ratio: 0 -> 0; inside the dead zone (0, 0.15] -> the minimum
    pulse duty 0.09 = 1.5 ms * 60 Hz; >= 1 (the curve's top, reached at 0.94 = 1 - (3 ms -
    2 ms) * 60 Hz) -> 1, the valve always on (duty.py: one curve, four valves' delays);
    just below the top the curve's own duty."""
    assert pwm_inverse(0.0, DUTY, RATIO) == 0.0
    assert pwm_inverse(-0.3, DUTY, RATIO) == 0.0
    for r in (1e-9, 0.01, 0.1, 0.15):
        assert pwm_inverse(r, DUTY, RATIO) == pytest.approx(0.09, abs=1e-12)
    for r in (1.0, 1.5):
        assert pwm_inverse(r, DUTY, RATIO) == 1.0
    assert pwm_inverse(0.999, DUTY, RATIO) < 0.94
    # monotone non-decreasing
    rs = np.linspace(0, 1.2, 500)
    ds = np.array([pwm_inverse(r, DUTY, RATIO) for r in rs])
    assert np.all(np.diff(ds) >= 0)


def test_pwm_inverse_flat_segment_takes_smallest_duty() -> None:
    """A flat run of the curve: the inverse returns its left end (smallest duty)."""
    duty = np.array([0.0, 0.2, 0.5, 1.0])
    ratio = np.array([0.0, 0.4, 0.4, 0.9])
    assert pwm_inverse(0.4, duty, ratio) == pytest.approx(0.2, abs=1e-15)
    assert pwm_inverse(0.2, duty, ratio) == pytest.approx(0.1, abs=1e-15)
    assert pwm_inverse(0.65, duty, ratio) == pytest.approx(0.75, abs=1e-15)


def test_duties_into_applies_the_inverse() -> None:
    """Eq. (33) case 2 with u = 0.5 gives duty 0.44 on a_in and b_out (0.5 - 0.06)."""
    u, duties = np.empty(4), np.empty(4)
    n = len(DUTY)
    case = duties_into(1000.0, 2000.0, np.full(4, float(n)), np.tile(DUTY, 4), np.tile(RATIO, 4),
                       n, u, duties)
    assert case == CASE_A_FILL
    np.testing.assert_allclose(duties, [0.44, 0.0, 0.0, 0.44], atol=1e-12)


def test_duties_into_inverts_each_valve_on_its_own_curve() -> None:
    """One curve per valve: a_in on the shared curve (u = 0.5 -> 0.44, as above), b_out on the
    identity curve r = d (u = 0.5 -> 0.5), read from a stride longer than either curve."""
    stride = 64
    n_pts = np.array([len(DUTY), 2.0, 2.0, 2.0])
    duty_pts = np.zeros(4 * stride)
    ratio_pts = np.zeros(4 * stride)
    duty_pts[:len(DUTY)], ratio_pts[:len(RATIO)] = DUTY, RATIO
    for i in (1, 2, 3):
        duty_pts[i * stride:i * stride + 2] = ratio_pts[i * stride:i * stride + 2] = (0.0, 1.0)
    u, duties = np.empty(4), np.empty(4)
    duties_into(1000.0, 2000.0, n_pts, duty_pts, ratio_pts, stride, u, duties)
    np.testing.assert_allclose(duties, [0.44, 0.0, 0.0, 0.5], atol=1e-12)
