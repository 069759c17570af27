"""The simulated rig against closed-form physics (the paper's Sec. 2, Eqs. 1-7).

Every expected value below is derived in a comment from the equation it tests, with the rig
values of the paper (Sec. 5.1) or of plant.yaml's defaults (contract 2). Sensor noise
is switched off wherever a closed form is compared with. Tolerances: RK4 integrates a constant
right-hand side exactly and an exponential with a local error of (h k)^5 / 120 ~ 1e-17 at
h k ~ 1e-3, so those closed forms are held to ~1e-9 relative (float rounding), not to an
engineering tolerance; where the motion enters, each test states its RK4 error and tolerance.

Three tests guard integrator bugs found and fixed on 2026-11-21: break-away one step late when
the force was already past F_S, and end-stop contact located by a single linear interpolation.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from pneutune.control.constants import A_IN, A_OUT, B_IN, B_OUT, RHO0, T_REF
from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.physics.flow import LIN_WIDTH, iso6358_flow, signed_flow
from pneutune.control.physics.friction import stribeck_force, stribeck_peak, stribeck_stiffness
from pneutune.control.physics.pwm import effective_open_fraction
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import (
    P_DT,
    S_OPEN,
    S_PA,
    S_PB,
    S_STUCK,
    S_V,
    S_X,
    STEP_STIFFNESS,
    PlantParams,
    pack_plant,
)
from pneutune.control.rig.identification_run import position_loop
from pneutune.control.rig.simrig import SimRig
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS

#: Sensors without noise or quantisation: readings equal the true state.
QUIET = {"sensors": {"x_noise": 0.0, "x_step": 0.0, "p_noise": 0.0}}
#: Friction switched off entirely (Eq. 2 with F_S = F_C = b_v = 0).
NO_FRICTION = {"friction": {"F_S": 0.0, "F_C": 0.0, "b_v": 0.0}}

# Paper rig (Sec. 5.1), written out here so the expected values do not come from the code
# under test.
A_A, A_B, P0, PS, T0, N, R = 7.854e-3, 7.54e-3, 101325.0, 6.0e5, 283.15, 1.2, 287.0
X_MIN, X_MAX, V0A, V0B = -0.0015, 0.0485, 5.036e-5, 2.916e-5
C_VALVE, B_VALVE = 8.373e-9, 0.18561
A_R = A_A - A_B
#: Chamber A with the piston on the x_max stop, Eq. (6): V0a + A_a (x_max - x_min) [m^3].
V_A_FULL = V0A + A_A * (X_MAX - X_MIN)


def _params(*updates: dict) -> PlantParams:
    """The paper rig with quiet sensors and the given plant.yaml updates merged in order."""
    cfg = PlantConfig().with_updates(QUIET)
    for u in updates:
        cfg = cfg.with_updates(u)
    return pack_plant(cfg)


def _advance(pp: PlantParams, s: np.ndarray, t: float) -> None:
    plant.advance(pp.vec, s, t, pp.p_s, pp.force_steps)


def _duties(**open_: float) -> np.ndarray:
    d = np.zeros(4)
    for name, u in open_.items():
        d[{"a_in": A_IN, "a_out": A_OUT, "b_in": B_IN, "b_out": B_OUT}[name]] = u
    return d


def _choked_flow(C: float, p_u: float) -> float:
    """Eq. (7), choked branch, written out: C rho0 p_u sqrt(T_ref / T_u) with T_u = T0 [kg/s]."""
    return C * RHO0 * p_u * math.sqrt(T_REF / T0)


def _eq7(C: float, b: float, p_u: float, p_d: float) -> float:
    """Eq. (7) as printed (no regularisation), p_u >= p_d, upstream at T0 [kg/s]."""
    r = p_d / p_u
    if r <= b:
        return _choked_flow(C, p_u)
    return _choked_flow(C, p_u) * math.sqrt(max(0.0, 1.0 - ((r - b) / (1.0 - b)) ** 2))


# --------------------------------------------------------------------------------------------
# A valve charging / discharging a fixed volume (piston held on the x_max stop, B vented)


@pytest.mark.parametrize("b", [B_VALVE, 0.5])
def test_choked_charge_of_fixed_volume_is_linear_after_the_opening_delay(b: float) -> None:
    """Eqs. (5)-(7), choked charge through a_in.

    With the piston on the x_max stop dV_a/dt = 0, so Eq. (5) gives dp_a/dt = n R T0 mdot / V_a.
    While p_a / p_s <= b, Eq. (7) is choked: mdot = C rho0 p_s sqrt(T_ref/T0), a constant, so
    p_a(t) = p0 + k (t - delay_on) for t >= delay_on (p0 before: the valve opens delay_on = 2 ms
    after the command), with k = n R T0 C rho0 p_s sqrt(T_ref/T0) / V_a ~ 1.333e6 Pa/s.
    The paper's b = 0.18561 leaves a 7.5 ms choked window from p0 (to b p_s = 111.4 kPa);
    b = 0.5 widens it to 149 ms. RK4 is exact on a constant slope: tolerance 1e-9 relative.
    """
    delay_on = 2.0e-3
    pp = _params({"valves": {"a_in": {"b": b, "delay_on": delay_on}}})
    k = N * R * T0 * _choked_flow(C_VALVE, PS) / V_A_FULL
    assert k == pytest.approx(1.3332e6, rel=1e-4)  # the figure quoted above
    t_choked_end = delay_on + (b * PS - P0) / k
    s = plant.initial_state(pp.vec, X_MAX, P0, P0)
    plant.set_duties(pp.vec, s, 0.0, _duties(a_in=1.0, b_out=1.0))
    times = [0.5e-3, 1.9e-3, *np.linspace(delay_on + 1e-4, t_choked_end - 1e-5, 12)]
    for t in times:
        _advance(pp, s, t)
        expected = P0 + k * max(0.0, t - delay_on)
        assert s[S_PA] == pytest.approx(expected, rel=1e-9, abs=1e-6), t
        assert s[S_PB] == pytest.approx(P0, rel=1e-12)
        assert s[S_X] == X_MAX  # the stop holds the piston: V_a is fixed
    # and past the choked window the rise is slower than the linear law (subsonic branch)
    t_late = t_choked_end + 0.1 * (PS - b * PS) / k
    _advance(pp, s, t_late)
    assert s[S_PA] < P0 + k * (t_late - delay_on) - 1.0


@pytest.mark.parametrize("b", [B_VALVE, 0.5])
def test_choked_discharge_of_fixed_volume_is_exponential(b: float) -> None:
    """Eqs. (5)-(7), choked discharge through a_out to ambient.

    Upstream is the chamber: while p0 / p_a <= b, mdot = C rho0 p_a sqrt(T_ref/T0), so
    dp_a/dt = -lam p_a with lam = n R T0 C rho0 sqrt(T_ref/T0) / V_a ~ 2.222 1/s and
    p_a(t) = p_s exp(-lam (t - delay_on)) from p_a(0) = p_s. Choked down to p0 / b: 545.9 kPa
    (42 ms) with the paper's b, 202.65 kPa (0.49 s) with b = 0.5. RK4 error on the exponential
    at lam h ~ 1e-3 is ~1e-17 per step: tolerance 1e-9 relative.
    """
    delay_on = 2.0e-3
    pp = _params({"valves": {"a_out": {"b": b, "delay_on": delay_on}}})
    lam = N * R * T0 * _choked_flow(C_VALVE, 1.0) / V_A_FULL
    assert lam == pytest.approx(2.2220, rel=1e-4)
    t_choked_end = delay_on + math.log(PS * b / P0) / lam
    s = plant.initial_state(pp.vec, X_MAX, PS, P0)
    plant.set_duties(pp.vec, s, 0.0, _duties(a_out=1.0, b_out=1.0))
    for t in [1.5e-3, *np.linspace(delay_on + 1e-4, t_choked_end - 1e-5, 12)]:
        _advance(pp, s, t)
        expected = PS * math.exp(-lam * max(0.0, t - delay_on))
        assert s[S_PA] == pytest.approx(expected, rel=1e-9), t
        assert s[S_X] == X_MAX


# --------------------------------------------------------------------------------------------
# Closed valves: polytropic compression


def test_closed_valves_conserve_p_v_to_the_n() -> None:
    """Eqs. (5)-(6) with mdot = 0: dp/dt = -n p dV/dt / V  =>  p V^n = const for each chamber.

    Friction and leak are zero so a 100 N force step sets the piston oscillating on the two
    air springs (stiffness ~1.8e5 N/m: ~0.5 mm swings, ~65 Hz). The exact ODE conserves
    p_a V_a^n and p_b V_b^n; RK4 at omega h ~ 0.16 keeps them to ~1e-9 relative over 0.5 s:
    tolerance 1e-7.
    """
    pp = _params(NO_FRICTION, {"disturbance": {"force_steps": [[0.01, 100.0]]}})
    x0 = 0.5 * (X_MIN + X_MAX)
    pa0, pb0 = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, x0, pa0, pb0)

    def invariants(x: float, pa: float, pb: float) -> tuple[float, float]:
        va = V0A + A_A * (x - X_MIN)  # Eq. (6)
        vb = V0B + A_B * (X_MAX - x)
        return pa * va**N, pb * vb**N

    ia0, ib0 = invariants(x0, pa0, pb0)
    xs = []
    for t in np.arange(1, 501) * 1e-3:
        _advance(pp, s, t)
        xs.append(s[S_X])
        ia, ib = invariants(s[S_X], s[S_PA], s[S_PB])
        assert ia == pytest.approx(ia0, rel=1e-7), t
        assert ib == pytest.approx(ib0, rel=1e-7), t
    # the test means something only if the volumes really changed
    assert max(xs) - min(xs) > 2.0e-4


def test_seal_leak_conserves_air_and_follows_iso6358_with_b_zero() -> None:
    """The A<->B seal leak (ISO 6358 form with b = 0), valves closed.

    * At t = 0, piston held on the x_max stop (p_a = 5 bar > p_b = 2 bar pushes it there):
      mdot = C rho0 p_a sqrt(T_ref/T0) sqrt(1 - (p_b/p_a)^2) out of A and into B.
    * With n = 1, Eq. (5) makes p_a V_a + p_b V_b = R T0 (m_a + m_b), which a leak between the
      chambers conserves whatever the piston does; here it starts unbalanced at mid-stroke and
      oscillates (friction off, ~4 mm swings, no stop reached): tolerance 1e-8 at
      sim.dt = 0.1 ms (see below). The leak must also really act:
      |p_a - p_b| falls by more than half in 1 s (time constant ~V / (n R T0 C rho0) ~ 0.2 s).
    """
    c_leak = 5.0e-9
    # Friction off: the stiff viscous mode (b_v / M ~ 3.3e3 1/s, h b_v / M ~ 1.3) would add
    # RK4 truncation error (~1e-6) to the invariant during the initial jerk. The invariant is
    # quadratic in the state, so RK4 keeps it only to its truncation error: ~2e-7 over 1 s of
    # these 4 mm swings at dt = 0.4 ms, ~4e-10 at 0.1 ms (measured; O(h^4)), used here.
    pp = _params(NO_FRICTION, {"leak": {"C": c_leak}, "rig": {"n": 1.0}, "sim": {"dt": 1e-4}})
    s = plant.initial_state(pp.vec, X_MAX, 5.0e5, 2.0e5)
    out = np.zeros(6)
    plant.truth(pp.vec, s, pp.p_s, pp.force_steps, out)
    leak = _choked_flow(c_leak, 5.0e5) * math.sqrt(1.0 - (2.0 / 5.0) ** 2)
    assert out[4] == pytest.approx(-leak, rel=1e-12)  # mdot_a
    assert out[5] == pytest.approx(leak, rel=1e-12)  # mdot_b

    x0 = 0.5 * (X_MIN + X_MAX)
    s = plant.initial_state(pp.vec, x0, 3.0e5, 4.0e5)

    def air(x: float, pa: float, pb: float) -> float:
        return pa * (V0A + A_A * (x - X_MIN)) + pb * (V0B + A_B * (X_MAX - x))

    m0 = air(x0, 3.0e5, 4.0e5)
    for t in np.arange(1, 11) * 0.1:
        _advance(pp, s, t)
        assert air(s[S_X], s[S_PA], s[S_PB]) == pytest.approx(m0, rel=1e-8), t
    assert abs(s[S_X] - x0) > 1e-3  # the volumes changed
    assert abs(s[S_PA] - s[S_PB]) < 0.5e5


def test_constant_pressure_disturbances_d_a_d_b() -> None:
    """Eq. (5)'s D_a, D_b terms: with the valves closed and the piston on the x_max stop
    (dV = 0, mdot = 0), dp_i/dt = D_i, so p_i(t) = p_i(0) + D_i t exactly (RK4 on a constant:
    tolerance 1e-9 relative). D_a = +1e5 Pa/s, D_b = -2e4 Pa/s keep the piston on the stop."""
    pp = _params({"disturbance": {"D_a": 1.0e5, "D_b": -2.0e4}})
    s = plant.initial_state(pp.vec, X_MAX, 3.0e5, 2.0e5)
    for t in (0.1, 0.5, 1.0):
        _advance(pp, s, t)
        assert s[S_PA] == pytest.approx(3.0e5 + 1.0e5 * t, rel=1e-9)
        assert s[S_PB] == pytest.approx(2.0e5 - 2.0e4 * t, rel=1e-9)
        assert s[S_X] == X_MAX


@pytest.mark.parametrize("payload", [0.0, 1.136])
def test_acceleration_uses_mass_plus_payload(payload: float) -> None:
    """Eq. (1) with M = mass + payload (sine-0.5hz-heavy carries 1.136 kg): friction
    off, a 50 N step from a balanced rest gives a = 50 N / M the instant it acts. Read 0.1 ms
    later, the air spring has only taken k x = k a t^2 / 2 ~ 0.05 N of it: tolerance 0.2 %."""
    pp = _params(NO_FRICTION, {"payload": payload,
                               "disturbance": {"force_steps": [[0.01, 50.0]]}})
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, 0.02, pa, pb)
    _advance(pp, s, 0.0101)
    out = np.zeros(6)
    plant.truth(pp.vec, s, pp.p_s, pp.force_steps, out)
    assert out[1] == pytest.approx(50.0 / (1.05 + payload), rel=2e-3)


# --------------------------------------------------------------------------------------------
# Motion, Eq. (1), stiction and end stops


@pytest.mark.parametrize(("p_b", "f_n"), [(P0, 0.0), (3.0e5, 0.0), (5.0e5, 150.0),
                                          (3.0e5, -150.0)])
def test_static_force_balance_keeps_piston_at_rest(p_b: float, f_n: float) -> None:
    """Eq. (1) at rest: M a = p_a A_a - p_b A_b - p0 A_r + F_n = 0
    => p_a = (p_b A_b + p0 A_r - F_n) / A_a.

    With F_S = F_C = 0 stiction cannot hide an imbalance. The balanced piston must not move
    (|dx| < 1e-9 m over 0.5 s) and its acceleration from Eq. (1) must be zero; a 1 N imbalance
    (p_a + 1/A_a) must move it by more than 1 um (1 N on the ~1.8e5 N/m air spring: ~5 um).
    """
    pp = _params({"friction": {"F_S": 0.0, "F_C": 0.0}, "disturbance": {"F_n": f_n}})
    pa, pb = plant.balanced_pressures(pp.vec, p_b, f_n)
    assert pb == p_b
    assert pa == pytest.approx((p_b * A_B + P0 * A_R - f_n) / A_A, rel=1e-14)
    # Eq. (1) by hand: zero net force, zero acceleration
    assert abs(pa * A_A - p_b * A_B - P0 * A_R + f_n) < 1e-9
    assert abs(plant.applied_force(pp.vec, pa, pb, f_n)) < 1e-9
    x0 = 0.02
    s = plant.initial_state(pp.vec, x0, pa, pb)
    out = np.zeros(6)
    plant.truth(pp.vec, s, pp.p_s, pp.force_steps, out)
    assert abs(out[1]) < 1e-9  # a [m/s^2]
    assert out[3] == f_n  # F_ext
    _advance(pp, s, 0.5)
    assert abs(s[S_X] - x0) < 1e-9
    assert abs(s[S_V]) < 1e-9

    s = plant.initial_state(pp.vec, x0, pa + 1.0 / A_A, pb)
    _advance(pp, s, 0.5)
    assert s[S_X] - x0 > 1e-6


def _air_spring(pa: float, pb: float, x: float) -> float:
    """Stiffness of the two closed chambers, from Eqs. (5)-(6) linearised:
    k = n p_a A_a^2 / V_a + n p_b A_b^2 / V_b [N/m]."""
    return (N * pa * A_A**2 / (V0A + A_A * (x - X_MIN))
            + N * pb * A_B**2 / (V0B + A_B * (X_MAX - x)))


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("excess", [-0.1, 0.1, 10.0])
def test_stick_below_and_slip_above_the_stiction_force(sign: float, excess: float) -> None:
    """Eq. (2), the F_e branch: at rest friction balances any applied force up to F_S = 75 N.

    From a balanced rest (valves closed, p_b = 3 bar, mid-stroke) a force step F = F_S + excess
    (either sign) at t = 10 ms:

    * excess -0.1 N: the piston stays exactly where it was, stuck, with F_friction = F.
    * excess +0.1 N: it breaks away but only creeps (v <~ 0.1 N / b_v = 3e-5 m/s << v_s, so
      friction stays ~F_S + b_v v, overdamped): it comes to rest where the air spring has taken
      the excess up, dx = (F - F_S) / k ~ 0.55 um, k = the linearised stiffness ~1.8e5 N/m
      (good to well under 5 % for so small a move).
    * excess +10 N: it slides, friction drops towards F_C = 50 N (Stribeck), so it overshoots
      the creep equilibrium (F - F_S) / k ~ 55 um and sticks again where |F_app| <= F_S: at
      59.6 um, where an independent solution of Eqs. (1)-(2) with closed chambers
      (``scipy.integrate.solve_ivp``, rtol 1e-10, stopped where v reaches 0) stops it. (An
      earlier version expected more than 1.5 times 55 um: the plant then missed the stop and
      crept on, see test_a_sliding_piston_stops_where_its_velocity_reaches_zero.)
    """
    f_s = 75.0
    x0 = 0.5 * (X_MIN + X_MAX)
    force = sign * (f_s + excess)
    pp = _params({"friction": {"F_S": f_s, "F_C": 50.0},
                  "disturbance": {"force_steps": [[0.01, force]]}})
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, x0, pa, pb)
    _advance(pp, s, 0.009)
    assert s[S_X] == x0 and s[S_STUCK] == 1.0
    _advance(pp, s, 0.3)
    dx = s[S_X] - x0
    f_app = plant.applied_force(pp.vec, s[S_PA], s[S_PB], force)
    k = _air_spring(pa, pb, x0)
    assert k == pytest.approx(1.8e5, rel=0.05)
    if excess < 0.0:
        assert dx == 0.0, "piston moved below F_S"
        assert s[S_STUCK] == 1.0
        out = np.zeros(6)
        plant.truth(pp.vec, s, pp.p_s, pp.force_steps, out)
        assert out[2] == pytest.approx(force, abs=1e-6)  # F_friction = F_e
        assert out[0] == 0.0 and out[1] == 0.0
    elif excess < 1.0:
        assert sign * dx == pytest.approx(excess / k, rel=0.05), "no break-away above F_S"
        assert abs(s[S_V]) < 1e-9  # at rest (the creep decays exponentially, tau ~ b_v / k)
        assert abs(f_app) == pytest.approx(f_s, abs=1e-3)
    else:
        assert sign * dx > 1.05 * excess / k, "no Stribeck drop: slid no further than a creep"
        assert sign * dx == pytest.approx(_slide_reference(force, pa, pb, x0, f_s), rel=0.005)
        assert s[S_STUCK] == 1.0 and s[S_V] == 0.0
        assert abs(f_app) <= f_s


def _slide_reference(force: float, pa0: float, pb0: float, x0: float, f_s: float,
                     f_c: float = 50.0, v_s: float = 0.005, alpha: float = 2.0,
                     b_v: float = 3500.0, mass: float = 1.05) -> float:
    """Distance [m] a piston at rest slides under ``force`` (> F_S) until v = 0: Eqs. (1)-(2),
    chambers closed (p V^n constant), by default F_C 50 N, v_s 5 mm/s, alpha 2, b_v 3500 N s/m,
    M 1.05 kg, integrated by solve_ivp independently of the plant."""
    sign = math.copysign(1.0, force)
    va0, vb0 = V0A + A_A * (x0 - X_MIN), V0B + A_B * (X_MAX - x0)

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        x, v = y
        pa = pa0 * (va0 / (V0A + A_A * (x - X_MIN))) ** N
        pb = pb0 * (vb0 / (V0B + A_B * (X_MAX - x))) ** N
        f_app = pa * A_A - pb * A_B - P0 * A_R + force
        friction = (f_c + (f_s - f_c) * math.exp(-(abs(v) / v_s) ** alpha)) * sign + b_v * v
        return [v, (f_app - friction) / mass]

    def stop(t: float, y: np.ndarray) -> float:
        return y[1] if t > 1.0e-6 else sign

    stop.terminal = True  # type: ignore[attr-defined]
    sol = solve_ivp(rhs, (0.0, 0.3), [x0, sign * 1e-12], events=stop, rtol=1e-10, atol=1e-14,
                    max_step=1e-5)
    return abs(float(sol.y[0, -1]) - x0)


@pytest.mark.parametrize("alpha", [0.7, 1.0, 2.0, 4.75])
@pytest.mark.parametrize("u_over_vs", [0.0, 0.5, 1.0, 3.0])
def test_stribeck_stiffness_is_the_steepest_slope_at_or_above_u(alpha: float,
                                                                 u_over_vs: float) -> None:
    """``stribeck_stiffness(u)`` = max over |v| >= u of |dF_f/dv| of Eq. (2), the speeds no lower
    than 1e-3 v_s: against central differences of ``stribeck_force`` on a dense grid (the
    analytic peak at r* = ((alpha-1)/alpha)^(1/alpha) must be the grid's maximum to 0.1 %)."""
    f_s, f_c, v_s, b_v = 150.0, 50.0, 2.5e-3, 3500.0
    u = u_over_vs * v_s
    v = np.geomspace(max(u, 1.0e-3 * v_s), 50.0 * v_s, 200_001)
    hv = 1.0e-9 * v
    slope = np.array([(stribeck_force(a + h, 1.0, f_s, f_c, v_s, alpha, b_v)
                       - stribeck_force(a - h, 1.0, f_s, f_c, v_s, alpha, b_v)) / (2.0 * h)
                      for a, h in zip(v[::50], hv[::50], strict=True)])
    expected = float(np.max(np.abs(slope)))
    got = stribeck_stiffness(u, f_s, f_c, v_s, alpha, b_v, stribeck_peak(alpha))
    assert got == pytest.approx(expected, rel=1.0e-3)


def test_the_papers_friction_never_shortens_the_step() -> None:
    """Paper rig: the steepest |dF_f/dv| is b_v = 3500 N s/m (the Stribeck slope peaks at
    25 N * sqrt(2/e) / 5 mm/s = 4289 N s/m, minus b_v = 789), so STEP_STIFFNESS M / k =
    2 * 1.05 / 3500 = 600 us >= sim.dt = 400 us: the run keeps the fixed 0.4 ms grid at every
    speed (as it did with the earlier factor 1.4: 420 us)."""
    pp = _params()
    assert STEP_STIFFNESS == 2.0
    assert plant._sliding_step(pp.vec, 0.0) == pytest.approx(6.0e-4, rel=1e-9)
    assert plant._sliding_step(pp.vec, 0.0) >= pp.vec[P_DT]


def test_a_steep_law_slides_as_solve_ivp_with_the_default_step() -> None:
    """A steep Stribeck law, F_S = 150 N, F_C = 50 N, v_s = 2.5 mm/s (the falling branch's
    eigenvalue reaches ((F_S - F_C) max|g'| - b_v)/M = (100 * 0.858 / 2.5e-3 - 3500)/1.05 =
    2.9e4 1/s, so RK4 needs steps of 2 M / k = 68 us there), sim.dt = 400 us: a force step of
    F_S + 10 N breaks the piston away; where it sticks again (506.2 um) matches solve_ivp (rtol
    1e-10) to 0.01 % (measured: 1.1e-5, and 2e-6 with the earlier factor 1.4; with 0.4 ms steps
    throughout, the step not following the speed, it is 0.09 % off). The step follows the
    speed: short at the break-away, 0.4 ms while stuck."""
    f_s, f_c, v_s = 150.0, 50.0, 2.5e-3
    x0 = 0.5 * (X_MIN + X_MAX)
    force = f_s + 10.0
    law = {"friction": {"F_S": f_s, "F_C": f_c, "v_s": v_s}}
    pp = _params(law, {"disturbance": {"force_steps": [[0.01, force]]}})
    assert pp.vec[P_DT] == 4.0e-4
    assert plant._sliding_step(pp.vec, 0.0) == pytest.approx(
        STEP_STIFFNESS * 1.05 / (100.0 * 2.0 * math.sqrt(0.5) * math.exp(-0.5) / v_s - 3500.0),
        rel=1e-6)
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, x0, pa, pb)
    _advance(pp, s, 0.3)
    dx = s[S_X] - x0
    assert s[S_STUCK] == 1.0 and s[S_V] == 0.0
    assert dx == pytest.approx(_slide_reference(force, pa, pb, x0, f_s, f_c, v_s), rel=1.0e-4)


def test_a_steep_law_tracks_as_with_a_10_us_step() -> None:
    """Closed loop (paper's DARC, sine-0.5hz, seed 1) on the paper's rig with F_S = 101.5 N,
    F_C = 54.6 N, v_s = 1.81 mm/s, alpha = 3.19 (2 M/k_max = 64 us): the default step, shortened
    near v = 0 only, gives E_p and E_rms of a fixed 10 us step within 0.01 and 0.005 mm. (The
    loop stick-slips: fixed steps of 200, 100, 50, 25, 10 and 5 us give E_rms 0.1004, 0.0997,
    0.1004, 0.0996, 0.0995 and 0.0995 mm and E_p 0.328-0.334 mm; the default step gives
    0.0970 and 0.329 mm. A smoke check that the varying step biases nothing; the step rule
    itself is test_a_steep_law_slides_as_solve_ivp_with_the_default_step.)"""
    ctl = load_controller(Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml")
    cfg = PlantConfig().with_updates({"friction": {
        "F_S": 101.5, "F_C": 54.6, "v_s": 1.81e-3, "alpha": 3.19, "b_v": 3520.0}})
    default = simulate_scenario(ctl, SCENARIOS["sine-0.5hz"], cfg).metrics
    fine = simulate_scenario(ctl, SCENARIOS["sine-0.5hz"],
                             cfg.with_updates({"sim": {"dt": 1.0e-5}})).metrics
    assert default.E_p_mm == pytest.approx(fine.E_p_mm, abs=0.01)
    assert default.E_rms_mm == pytest.approx(fine.E_rms_mm, abs=0.005)


def test_a_slow_move_sticks_alike_at_any_step_size() -> None:
    """Stick-slip does not depend on the integration step (the plant is converged in
    dt). The commissioning run's ±2 and ±5 mm/s moves on the paper's rig, noise-free: the time
    stuck and the distance agree between dt = 0.4 ms (the default) and 0.05 ms, and the
    distance equals ∫v dt of /sim/truth (sampled every 0.5 ms: a slip lasts a few ms, which
    the 4 ms control rate's rectangle rule misses by up to 2 %).

    Before the friction direction was frozen inside each RK4 step, a stage straddling v = 0
    flipped the friction and pushed v back: the stop was missed and the piston crept with v
    changing sign every step (stuck 78 % of the +2 mm/s move at 0.4 ms, 30 % at 0.1 ms, none at
    25 us; ∫v dt 20.7 mm for 16.1 mm travelled at 5 mm/s)."""
    from pneutune.control.rig.commissioning_run import simulate_commissioning

    results = []
    for dt in (4.0e-4, 5.0e-5):
        p = PlantConfig().with_updates({"sim": {"dt": dt}, "sensors": {
            "x_noise": 0.0, "x_step": 0.0, "p_noise": 0.0}})
        rec = simulate_commissioning(p, seed=1, record_truth=True, sample_period=5.0e-4)
        v, x = rec.truth_[:, 0], rec.sensors_[:, 0]
        seg = rec.segments_
        row = []
        for i, (ts, _, kind, params) in enumerate(seg):
            if kind != "constant_speed" or abs(params["speed"]) > 0.006:
                continue
            k0, k1 = round(ts / rec.Ts), round(seg[i + 1][0] / rec.Ts)
            mid = slice(k0 + (k1 - k0) // 5, k1 - (k1 - k0) // 5)
            dist = abs(x[mid][-1] - x[mid][0])
            assert abs(np.sum(v[mid]) * rec.Ts) == pytest.approx(dist, rel=0.01), (dt, i)
            row.append((np.mean(v[mid] == 0.0), dist))
        results.append(np.array(row))
    assert len(results[0]) == 4
    assert results[0][:, 0] == pytest.approx(results[1][:, 0], abs=0.02)  # time stuck
    assert results[0][:, 1] == pytest.approx(results[1][:, 1], rel=0.01)  # distance


def test_a_sliding_piston_stops_where_its_velocity_reaches_zero() -> None:
    """Sliding at 3 mm/s with the applied force 60 N, below F_S = 75 N and opposing the motion
    (valves shut): friction F_C + b_v v ~ 60 N decelerates it at ~100 m/s² (1.05 kg), so it
    stops within 0.1 ms, after ~0.2 um, and sticks. (The RK4 stage straddling v = 0 used to
    flip the friction and let it creep on.)"""
    x0 = 0.5 * (X_MIN + X_MAX)
    pp = _params({"friction": {"F_S": 75.0, "F_C": 50.0}})
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    f_push = -60.0  # applied force against the motion
    pp = _params({"friction": {"F_S": 75.0, "F_C": 50.0},
                  "disturbance": {"force_steps": [[0.0, f_push]]}})
    s = plant.initial_state(pp.vec, x0, pa, pb)
    s[S_V] = 3.0e-3
    s[S_STUCK] = 0.0
    _advance(pp, s, 0.004)
    assert s[S_STUCK] == 1.0 and s[S_V] == 0.0
    assert 0.0 < s[S_X] - x0 < 1.0e-6


@pytest.mark.parametrize(("duties", "stop", "f_push"), [
    (_duties(a_in=1.0, b_out=1.0), X_MAX, 500.0),
    (_duties(a_out=1.0, b_in=1.0), X_MIN, -500.0),
])
def test_end_stops_hold(duties: np.ndarray, stop: float, f_push: float) -> None:
    """End stops: x stays in [x_min, x_max] (the stroke is [-1.5, 48.5] mm) and,
    once driven at full duty into a stop (mode 1 -> x_max, mode 2 -> x_min), the piston stays
    on it with v = 0, also when an extra 500 N pushes it into the stop from t = 0.6 s.
    Checked every 0.1 ms, so an overshoot between samples would show.
    """
    pp = _params({"disturbance": {"force_steps": [[0.6, f_push]]}})
    x0 = 0.5 * (X_MIN + X_MAX)
    pa, pb = plant.balanced_pressures(pp.vec, P0)
    s = plant.initial_state(pp.vec, x0, pa, pb)
    plant.set_duties(pp.vec, s, 0.0, duties)
    arrived = None
    for k in range(1, 10001):
        t = k * 1e-4
        _advance(pp, s, t)
        assert X_MIN <= s[S_X] <= X_MAX, (t, s[S_X])
        if arrived is None and s[S_X] == stop:
            arrived = t
        elif arrived is not None:
            assert s[S_X] == stop and s[S_V] == 0.0, t
    # a loaded-free 50 mm stroke at full duty takes ~0.2-0.3 s
    assert arrived is not None and arrived < 0.5
    # the chamber pushing into the stop is charged close to the supply, the other vented
    p_push, p_vent = (s[S_PA], s[S_PB]) if stop == X_MAX else (s[S_PB], s[S_PA])
    assert p_push > 0.95 * PS
    assert p_vent < P0 + 0.01 * PS


def _reference_motion(x0: float, force: float, t_end: float, friction: bool,
                      stop: float | None = None) -> tuple[float, float | None]:
    """Eqs. (1), (2), (5), (6) with the valves closed, integrated independently of the plant:
    chambers at p V^n = const from a balanced rest at x0 (p_b = 3 bar), a force step ``force``
    at t = 0, Stribeck friction of the plant defaults (F_S 75, F_C 50 N, v_s 5 mm/s, alpha 2,
    b_v 3500 N s/m; breaking away towards the force) or none; scipy LSODA, rtol 1e-10.

    Returns x(t_end) [m] and the time the piston reaches ``stop`` (None if it does not).
    """
    pb0 = 3.0e5
    pa0 = (pb0 * A_B + P0 * A_R) / A_A
    ca = pa0 * (V0A + A_A * (x0 - X_MIN)) ** N
    cb = pb0 * (V0B + A_B * (X_MAX - x0)) ** N

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        x, v = y
        pa = ca / (V0A + A_A * (x - X_MIN)) ** N
        pb = cb / (V0B + A_B * (X_MAX - x)) ** N
        f_f = 0.0
        if friction:
            d = math.copysign(1.0, v) if v != 0.0 else math.copysign(1.0, force)
            f_f = (50.0 + 25.0 * math.exp(-((v / 0.005) ** 2))) * d + 3500.0 * v
        return [v, (pa * A_A - pb * A_B - P0 * A_R + force - f_f) / 1.05]

    events = []
    if stop is not None:
        def hit(_t: float, y: np.ndarray) -> float:
            return y[0] - stop
        hit.terminal = True
        events.append(hit)
    sol = solve_ivp(rhs, (0.0, t_end), [x0, 0.0], method="LSODA", rtol=1e-10, atol=1e-13,
                    max_step=1e-6, events=events or None)
    t_hit = float(sol.t_events[0][0]) if events and len(sol.t_events[0]) else None
    return float(sol.y[0, -1]), t_hit


def test_break_away_starts_at_the_force_step() -> None:
    """Eq. (2): a stuck piston breaks away the instant |F_app| exceeds F_S, whatever the
    caller's step grid (plant.py: "stick/slip does not depend on the step grid").

    From a balanced rest at x = 20 mm, a 3000 N step at t = 10 ms (F_S = 75 N). Reference: the
    same motion integrated by scipy (:func:`_reference_motion`), 0.436 mm after 0.8 ms.
    Advanced in 0.1 ms pieces (RK4 steps of 0.1 ms: h b_v / M = 0.33) the plant must match it
    to 1 um; in one call (0.4 ms steps, h b_v / M = 1.3: RK4 is a few um off on the viscous
    transient) to 10 um.
    """
    pp = _params({"disturbance": {"force_steps": [[0.01, 3000.0]]}})
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    x0 = 0.02
    x_ref, _ = _reference_motion(x0, 3000.0, 8e-4, friction=True)
    assert x_ref - x0 == pytest.approx(4.36e-4, rel=0.01)

    pieces = plant.initial_state(pp.vec, x0, pa, pb)
    for t in 0.01 + np.arange(9) * 1e-4:
        _advance(pp, pieces, t)
    one_call = plant.initial_state(pp.vec, x0, pa, pb)
    _advance(pp, one_call, 0.0108)
    assert pieces[S_X] == pytest.approx(x_ref, abs=1e-6), "break-away late (0.1 ms pieces)"
    assert one_call[S_X] == pytest.approx(x_ref, abs=1e-5), "break-away late (one call)"


def test_frictionless_piston_pushed_onto_a_stop_reaches_it() -> None:
    """End stops with friction off: valves closed, balanced at x = 0 (1.5 mm from x_min), a
    -3000 N step at t = 0. The reference (:func:`_reference_motion`) reaches the stop at
    1.04 ms (the air spring takes at most ~700 N off the push: a >= 2140 m/s^2, arrival
    <= 1.2 ms). At 4 ms the piston must be on the stop (x == x_min) and stay there.
    """
    pp = _params(NO_FRICTION, {"disturbance": {"force_steps": [[0.0, -3000.0]]}})
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, 0.0, pa, pb)
    _, t_hit = _reference_motion(0.0, -3000.0, 0.01, friction=False, stop=X_MIN)
    assert t_hit is not None and 0.9e-3 < t_hit < 1.2e-3
    _advance(pp, s, 0.004)
    assert s[S_X] == X_MIN, f"piston {s[S_X] - X_MIN:.3g} m short of the stop"
    _advance(pp, s, 0.1)
    assert s[S_X] == X_MIN and s[S_V] == 0.0


def test_end_stop_impact_keeps_p_v_to_the_n() -> None:
    """Eqs. (5)-(6) through an impact: the stop stops the piston, not the gas, so with the
    valves closed p_a V_a^n is the same before and after the piston hits x_min. A -3000 N
    step drives it from x = 0 onto the stop (~0.6 m/s at impact), advanced in Ts = 4 ms pieces
    as the rig does, with sim.dt = 0.1 ms so that RK4 resolves the viscous mode (h b_v / M =
    0.33; at the default 0.4 ms its error on this jerk alone is ~1e-4). Without an impact the
    same step keeps the invariant to ~4e-8 at this dt; with a contact located on the stop
    ~5e-7 (V_a is smallest there). Tolerance 2e-6.
    """
    pp = _params({"disturbance": {"force_steps": [[0.0, -3000.0]]}, "sim": {"dt": 1e-4}})
    pa, pb = plant.balanced_pressures(pp.vec, 3.0e5)
    s = plant.initial_state(pp.vec, 0.0, pa, pb)
    inv0 = pa * (V0A + A_A * (0.0 - X_MIN)) ** N
    for k in range(1, 26):
        _advance(pp, s, k * 0.004)
    assert s[S_X] == X_MIN
    inv = s[S_PA] * (V0A + A_A * (s[S_X] - X_MIN)) ** N
    assert inv == pytest.approx(inv0, rel=2e-6)


# --------------------------------------------------------------------------------------------
# PWM: the effective open fraction measured physically


def _expected_fraction(duty: float, period: float, delay_on: float, delay_off: float,
                       min_pulse: float) -> float:
    """Open fraction derived from the valve model (valves.py docstring): a command pulse of
    length u T opens the valve delay_on after its start and closes it delay_off after its end,
    so the valve is open u T + delay_off - delay_on per period, clipped to [0, T]; a pulse
    shorter than min_pulse never opens it; u >= 1 is always open."""
    if duty <= 0.0 or duty * period < min_pulse:
        return 0.0
    if duty >= 1.0:
        return 1.0
    return min(max(duty + (delay_off - delay_on) / period, 0.0), 1.0)


DUTY_GRID = (0.0, 0.05, 0.085, 0.095, 0.15, 0.17, 0.19, 0.25, 0.5, 0.7, 0.9, 0.93, 0.95,
             0.98, 1.0)


@pytest.mark.parametrize("mode", ["immediate", "latched"])
@pytest.mark.parametrize("valve", [
    {"delay_on": 2.0e-3, "delay_off": 3.0e-3, "min_pulse": 1.5e-3},  # plant defaults
    {"delay_on": 4.0e-3, "delay_off": 1.0e-3, "min_pulse": 3.0e-3},  # slow opener
])
def test_measured_open_fraction_matches_delays_and_min_pulse(mode: str, valve: dict) -> None:
    """The PWM curve measured as identify would: a_in charges a 0.1 m^3 dead volume (piston on
    the x_max stop, B vented) with the duty rewritten every Ts = 4 ms as a controller does.
    Choked flow (p_a stays below b p_s = 111 kPa, Eq. 7) is constant while the valve is open,
    so the pressure gain over 12 whole PWM periods (0.1 s .. 0.3 s, after the switching
    transient) divided by the full-duty gain is the open fraction. Expected: the closed form
    above (defaults: dead zone below duty 0.09, u + 0.06 above, saturation at 0.94), which
    effective_open_fraction must also give. Exact up to float rounding: tolerance 1e-6.
    """
    pp = _params({"rig": {"pwm_update": mode, "V0a": 0.1}, "valves": {"a_in": valve}})
    period = 1.0 / 60.0
    ts = 0.004
    t1, t2 = 0.1, 0.3  # 6 and 18 PWM periods, 25 and 75 samples

    def gain(duty: float) -> float:
        s = plant.initial_state(pp.vec, X_MAX, P0, P0)
        d = _duties(a_in=duty, b_out=1.0)
        p1 = None
        for k in range(75):
            if abs(k * ts - t1) < 1e-12:
                p1 = s[S_PA]
            plant.set_duties(pp.vec, s, k * ts, d)
            _advance(pp, s, (k + 1) * ts)
        assert p1 is not None
        assert s[S_PA] < B_VALVE * PS  # still choked
        return s[S_PA] - p1

    full = gain(1.0)
    # full duty: choked flow for 0.2 s into 0.1004 m^3: n R T0 mdot 0.2 / V ~ 1.18 kPa
    assert full == pytest.approx(
        N * R * T0 * _choked_flow(C_VALVE, PS) * (t2 - t1) / (0.1 + A_A * (X_MAX - X_MIN)),
        rel=1e-9)
    measured = np.array([gain(u) / full for u in DUTY_GRID])
    expected = np.array([_expected_fraction(u, period, **valve) for u in DUTY_GRID])
    closed_form = effective_open_fraction(np.array(DUTY_GRID), period, **valve)
    np.testing.assert_allclose(closed_form, expected, atol=1e-12)
    np.testing.assert_allclose(measured, expected, atol=1e-6)
    # the grid really covers the dead zone, and the saturation when delay_off > delay_on
    assert any(e == 0.0 for u, e in zip(DUTY_GRID, expected, strict=True) if u > 0.0)
    if valve["delay_off"] > valve["delay_on"]:
        assert any(e == 1.0 for u, e in zip(DUTY_GRID, expected, strict=True) if u < 1.0)


@pytest.mark.parametrize(("mode", "opens_at"), [
    ("immediate", 0.3 / 60.0 + 2.0e-3),  # the comparator uses the new duty at once
    ("latched", 1.0 / 60.0 + 2.0e-3),  # from the next period start
])
def test_pwm_update_mode_decides_when_a_new_duty_acts(mode: str, opens_at: float) -> None:
    """rig.pwm_update: duty 0.5 written at 0.3 T. Immediate: carrier phase 0.3 <
    0.5, the command goes on at once and the valve opens delay_on = 2 ms later. Latched: the
    duty takes effect at the next period start T, the valve opens at T + 2 ms."""
    pp = _params({"rig": {"pwm_update": mode}})
    s = plant.initial_state(pp.vec, X_MAX, P0, P0)
    t_write = 0.3 / 60.0
    _advance(pp, s, t_write)
    plant.set_duties(pp.vec, s, t_write, _duties(a_in=0.5))
    first_open = None
    for t in t_write + np.arange(1, 2001) * 1e-5:  # to 0.3 T + 20 ms, past both instants
        _advance(pp, s, t)
        if s[S_OPEN + A_IN] == 1.0:
            first_open = t
            break
    assert first_open == pytest.approx(opens_at, abs=1.01e-5)


# --------------------------------------------------------------------------------------------
# ISO 6358, Eq. (7)


def test_iso6358_choked_and_subsonic_values() -> None:
    """Eq. (7) with the paper's valve (C = 8.373e-9 m^3/(s Pa), b = 0.18561) at T0 = 283.15 K:
    choked at 6 bar -> 1 atm: C rho0 p_u sqrt(293.15/283.15) = 6.0574e-3 kg/s; subsonic at
    p_d / p_u = 0.5: times sqrt(1 - ((0.5 - b)/(1 - b))^2) = 0.92248 -> 5.5878e-3 kg/s."""
    choked = iso6358_flow(C_VALVE, B_VALVE, PS, P0, T0)
    assert choked == pytest.approx(8.373e-9 * 1.185 * 6.0e5 * math.sqrt(293.15 / 283.15),
                                   rel=1e-12)
    assert choked == pytest.approx(6.0574e-3, rel=1e-4)
    # anywhere below b it is the same choked value
    assert iso6358_flow(C_VALVE, B_VALVE, PS, 0.1 * PS, T0) == choked
    sub = iso6358_flow(C_VALVE, B_VALVE, PS, 0.5 * PS, T0)
    assert sub == pytest.approx(choked * math.sqrt(1.0 - ((0.5 - B_VALVE) / (1 - B_VALVE)) ** 2),
                                rel=1e-12)
    assert sub == pytest.approx(5.5878e-3, rel=1e-4)
    # the upstream temperature enters as sqrt(T_ref / T_u)
    assert iso6358_flow(C_VALVE, B_VALVE, PS, P0, T_REF) == pytest.approx(
        8.373e-9 * 1.185 * 6.0e5, rel=1e-12)
    # no flow without a pressure difference
    assert iso6358_flow(C_VALVE, B_VALVE, PS, PS, T0) == 0.0


def test_iso6358_reverse_flow_is_antisymmetric() -> None:
    """Eq. (7) applies with the ports' roles swapped when the pressure difference reverses
    (both ports at T0): flow(1 -> 2) = -flow(2 -> 1), for choked, subsonic and linear ratios."""
    for p1, p2 in [(PS, P0), (3.0e5, 2.5e5), (2.0e5, 1.9999e5), (P0, PS), (4.0e5, 4.0e5)]:
        fwd = signed_flow(C_VALVE, B_VALVE, p1, p2, T0)
        rev = signed_flow(C_VALVE, B_VALVE, p2, p1, T0)
        assert fwd == -rev
        assert np.sign(fwd) == np.sign(p1 - p2)
        assert abs(fwd) == iso6358_flow(C_VALVE, B_VALVE, max(p1, p2), min(p1, p2), T0)


def test_iso6358_continuity_at_b_and_at_the_linear_segment() -> None:
    """Eq. (7) is continuous at p_d/p_u = b (the square root is 1 there, slope 0): the jump
    across b +- 1e-9 is below 1e-12 of the choked flow. At r0 = 1 - LIN_WIDTH the linear
    segment starts at Eq. (7)'s value (flow.py): the jump across r0 +- 1e-10 is bounded by
    Eq. (7)'s slope there, |d mdot/dr| = s / sqrt(1 - s^2) / (1 - b) ~ 25 choked per unit r,
    so below 1e-8 of the choked flow. Inside the segment the flow is the straight line to 0."""
    choked = _choked_flow(C_VALVE, PS)

    def f(r: float) -> float:
        return iso6358_flow(C_VALVE, B_VALVE, PS, r * PS, T0)

    assert abs(f(B_VALVE + 1e-9) - f(B_VALVE - 1e-9)) < 1e-12 * choked
    assert f(B_VALVE) == choked
    r0 = 1.0 - LIN_WIDTH
    q0 = _eq7(C_VALVE, B_VALVE, PS, r0 * PS)
    # ~5 % of choked at r0 (flow.py docstring): sqrt(1 - s^2), s = (r0 - b)/(1 - b)
    assert 0.04 * choked < q0 < 0.06 * choked
    assert f(r0) == pytest.approx(q0, rel=1e-9)
    assert abs(f(r0 + 1e-10) - f(r0 - 1e-10)) < 1e-8 * choked
    for frac in (0.25, 0.5, 0.9):
        assert f(r0 + frac * LIN_WIDTH) == pytest.approx(q0 * (1.0 - frac), rel=1e-6)
    # below r0 the code is Eq. (7) as printed
    for r in (0.3, 0.6, 0.9, 0.99, 0.998):
        assert f(r) == pytest.approx(_eq7(C_VALVE, B_VALVE, PS, r * PS), rel=1e-12)


@settings(max_examples=200, derandomize=True, deadline=None)
@given(p1=st.floats(5.0e4, 1.6e6), p2=st.floats(5.0e4, 1.6e6), b=st.floats(0.0, 0.9))
def test_iso6358_flow_properties(p1: float, p2: float, b: float) -> None:
    """Eq. (7) properties for any pressures: |mdot| <= the choked flow of the higher pressure,
    antisymmetric in the ports, monotone non-increasing in the downstream pressure."""
    hi = max(p1, p2)
    q = signed_flow(C_VALVE, b, p1, p2, T0)
    assert abs(q) <= _choked_flow(C_VALVE, hi) * (1 + 1e-12)
    assert signed_flow(C_VALVE, b, p2, p1, T0) == -q
    lo = min(p1, p2)
    assert iso6358_flow(C_VALVE, b, hi, lo, T0) >= iso6358_flow(
        C_VALVE, b, hi, lo + 0.5 * (hi - lo), T0)


def _charge_times(targets: tuple[float, ...]) -> np.ndarray:
    """Times at which the plant charges chamber A (piston on the x_max stop) from p0 through
    a_in to each fraction of p_s; linear interpolation between 0.1 ms samples."""
    pp = _params()
    s = plant.initial_state(pp.vec, X_MAX, P0, P0)
    plant.set_duties(pp.vec, s, 0.0, _duties(a_in=1.0, b_out=1.0))
    out = np.full(len(targets), np.nan)
    t, prev = 0.0, P0
    while t < 2.0 and np.isnan(out).any():
        t += 1e-4
        _advance(pp, s, t)
        for i, r in enumerate(targets):
            if np.isnan(out[i]) and s[S_PA] >= r * PS:
                out[i] = t - 1e-4 + 1e-4 * (r * PS - prev) / (s[S_PA] - prev)
        prev = s[S_PA]
    return out


def test_flow_regularisation_is_small() -> None:
    """flow.py replaces Eq. (7) by a straight line over the last LIN_WIDTH = 1e-3 of pressure
    ratio. Reference: Eq. (7) as printed, integrated with scipy (DOP853, rtol 1e-12) for the
    same charge of chamber A (Eq. 5 with dV = 0, valve open at delay_on = 2 ms).

    * To 99 % of p_s the regularisation does not act (r < 1 - LIN_WIDTH): times agree to
      1e-6 relative (both integrators' error).
    * To 99.95 % of p_s, half-way into the linear segment, it acts: Eq. (7) as printed reaches
      0.9995 in ~5.3 ms from 0.999 (d eps/dt ~ -sqrt(eps)), the line in ~6.3 ms
      (d eps/dt ~ -110 eps): ~1 ms on a ~0.53 s charge. Must stay below 1 %.
    """
    targets = (0.99, 0.9995)
    k = N * R * T0 / V_A_FULL

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        return [k * _eq7(C_VALVE, B_VALVE, PS, y[0])]

    def event(r: float):
        def ev(_t: float, y: np.ndarray) -> float:
            return y[0] - r * PS
        ev.terminal = r == targets[-1]
        return ev

    sol = solve_ivp(rhs, (2.0e-3, 3.0), [P0], method="DOP853", rtol=1e-12, atol=1e-9,
                    events=[event(r) for r in targets])
    ref = np.array([ev[0] for ev in sol.t_events])
    got = _charge_times(targets)
    assert 0.4 < ref[0] < 0.7
    assert got[0] == pytest.approx(ref[0], rel=1e-6)
    assert got[1] == pytest.approx(ref[1], rel=1e-2)
    assert got[1] > ref[1]  # the line has less flow than the square root near r = 1


# --------------------------------------------------------------------------------------------
# Step-size convergence (halving the step moves a tracking metric by <= 0.005 mm)


def _tracking_metrics(dt: float, mode: str) -> tuple[float, float]:
    """E_p = max |e| and E_rms over the last three periods (the paper's Sec. 5.1 indices) [mm] of
    17.5 sin(pi t) mm around mid-stroke, 10 s, tracked by the proportional position loop of
    the identification run (band 2.5 mm) through the SimRig (default sensor noise, seed 1)."""
    cfg = PlantConfig().with_updates({"sim": {"dt": dt}, "rig": {"pwm_update": mode}})
    mid = 0.5 * (cfg.rig.x_min + cfg.rig.x_max)
    rig = SimRig(cfg, x0=mid)
    n = round(10.0 / rig.Ts)
    e = np.empty(n)
    for k in range(n):
        x_r = mid + 0.0175 * math.sin(math.pi * k * rig.Ts)
        y = rig.read()
        e[k] = y[0] - x_r
        rig.write(position_loop(float(y[0]), x_r, 0.0025))
        rig.advance()
    last = e[round(4.0 / rig.Ts):] * 1e3
    return float(np.max(np.abs(last))), float(np.sqrt(np.mean(last**2)))


@pytest.mark.parametrize("mode", ["immediate", "latched"])
def test_tracking_metric_converges_in_the_step_size(mode: str) -> None:
    """sim.dt = 0.4 ms (the default) and 0.2 ms give E_p and E_rms within 0.005 mm.
    The loop must actually track (E_p of a few mm at most), or the comparison is empty."""
    assert PlantConfig().sim.dt == 4.0e-4
    ep1, erms1 = _tracking_metrics(4.0e-4, mode)
    ep2, erms2 = _tracking_metrics(2.0e-4, mode)
    assert 0.1 < ep1 < 5.0 and 0.05 < erms1 < 3.0
    assert abs(ep1 - ep2) <= 0.005
    assert abs(erms1 - erms2) <= 0.005


# --------------------------------------------------------------------------------------------
# Properties under random duty sequences


duty_blocks = st.lists(
    st.tuples(st.lists(st.sampled_from([0.0, 0.0, 0.03, 0.1, 0.3, 0.5, 0.8, 0.97, 1.0]),
                       min_size=4, max_size=4),
              st.integers(1, 60)),
    min_size=1, max_size=12)


@settings(max_examples=40, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(blocks=duty_blocks, x_frac=st.floats(0.0, 1.0), pb_frac=st.floats(0.0, 1.0),
       mode=st.sampled_from(["immediate", "latched"]))
def test_random_duty_sequences_keep_the_state_physical(blocks, x_frac, pb_frac, mode) -> None:
    """Any duty sequence (held 1..60 samples each, up to 0.9 s): x stays in the stroke, the
    pressures stay finite and positive and do not exceed the supply by more than polytropic
    compression can (bound 2 p_s; seen at most ~1.03 p_s), velocities stay finite."""
    pp = _params({"rig": {"pwm_update": mode}})
    duties = np.vstack([np.tile(np.array(d, dtype=float), (n, 1)) for d, n in blocks])
    n = duties.shape[0]
    x0 = X_MIN + x_frac * (X_MAX - X_MIN)
    pa0, pb0 = plant.balanced_pressures(pp.vec, P0 + pb_frac * (PS - P0))
    s = plant.initial_state(pp.vec, x0, pa0, pb0)
    sensors = np.zeros((n, 4))
    truth = np.zeros((n, 6))
    plant.run_open_loop(pp.vec, s, duties, np.full(n, PS), pp.force_steps, np.zeros((n, 4)),
                        0.004, sensors, truth)
    assert np.isfinite(sensors).all() and np.isfinite(truth).all()
    assert (sensors[:, 0] >= X_MIN).all() and (sensors[:, 0] <= X_MAX).all()
    assert X_MIN <= s[S_X] <= X_MAX
    p = np.concatenate([sensors[:, 1:3].ravel(), [s[S_PA], s[S_PB]]])
    assert (p > 0.0).all() and (p < 2.0 * PS).all()


def test_exp_neg_is_exp_to_the_last_bit_across_its_underflow_shortcut() -> None:
    """exp_neg(q) returns 0.0 without calling exp past EXP_UNDERFLOW (746): it must equal
    math.exp(-q) everywhere, through the subnormal range (708-745) and past the point where
    exp(-q) rounds to 0.0 (745.13); and stribeck_level, which also skips the power once its
    logarithm passes LOG_EXP_UNDERFLOW, must equal Eq. (2) computed plainly."""
    from pneutune.control.physics.friction import EXP_UNDERFLOW, exp_neg, stribeck_level

    qs = np.concatenate([np.linspace(0.0, 800.0, 40001), np.linspace(744.0, 747.0, 3001),
                         np.geomspace(1e-12, 1e12, 2001)])
    assert all(exp_neg(q) == math.exp(-q) for q in qs)
    assert math.exp(-EXP_UNDERFLOW) == 0.0
    rng = np.random.default_rng(7)
    for _ in range(20000):
        av = 10.0 ** rng.uniform(-8.0, 1.0)
        v_s = 10.0 ** rng.uniform(-4.0, -1.0)
        alpha = float(rng.choice([1.0, 2.0, rng.uniform(0.3, 10.0)]))
        r = av / v_s
        g = (math.exp(-r * r) if alpha == 2.0 else math.exp(-r) if alpha == 1.0
             else math.exp(-math.exp(alpha * math.log(r))))
        assert stribeck_level(av, 120.0, 80.0, v_s, alpha) == 80.0 + 40.0 * g


def test_stribeck_level_past_its_flat_ratio_is_eq2_to_the_last_bit() -> None:
    """From stribeck_flat_ratio on, stribeck_level returns F_C without computing the Stribeck
    term: Eq. (2) computed plainly must give F_C there to the last bit, and the level with the
    ratio must equal the level without it at any speed (below, at and above the ratio), over
    levels from 1 mN to 10 kN, Stribeck speeds of 0.1-100 mm/s and exponents of 0.3-10."""
    from pneutune.control.physics.friction import stribeck_flat_ratio, stribeck_level

    rng = np.random.default_rng(11)
    flat_seen = 0
    for _ in range(4000):
        f_c = 10.0 ** rng.uniform(-3.0, 4.0)
        f_s = f_c * float(rng.choice([1.0, 1.0 + 10.0 ** rng.uniform(-12.0, 1.0)]))
        v_s = 10.0 ** rng.uniform(-4.0, -1.0)
        alpha = float(rng.choice([1.0, 2.0, rng.uniform(0.3, 10.0)]))
        r_flat = stribeck_flat_ratio(f_s, f_c, alpha)
        assert 0.0 <= r_flat < math.inf
        for r in (r_flat * rng.uniform(0.5, 1.0), r_flat, np.nextafter(r_flat, np.inf),
                  r_flat * rng.uniform(1.0, 50.0)):
            av = r * v_s
            if av <= 0.0:  # F_S = F_C: the ratio is 0, and v = 0 is no sliding speed
                continue
            ratio = av / v_s
            plain = (f_c + (f_s - f_c) * (math.exp(-ratio * ratio) if alpha == 2.0 else
                                          math.exp(-ratio) if alpha == 1.0 else
                                          math.exp(-math.exp(alpha * math.log(ratio)))))
            got = stribeck_level(av, f_s, f_c, v_s, alpha, r_flat)
            assert got == stribeck_level(av, f_s, f_c, v_s, alpha) == plain
            if ratio >= r_flat:
                assert got == f_c
                flat_seen += 1
    assert flat_seen > 4000  # the shortcut was taken, not only checked
    # no flat ratio where no speed gives F_C exactly
    assert stribeck_flat_ratio(50.0, 0.0, 2.0) == math.inf
    assert stribeck_flat_ratio(40.0, 50.0, 2.0) == math.inf
    assert stribeck_flat_ratio(60.0, 50.0, 0.0) == math.inf
    assert stribeck_flat_ratio(math.nan, 50.0, 2.0) == math.inf
