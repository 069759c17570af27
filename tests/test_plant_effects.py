"""The simulator's real-rig effects (contract 2: valve lag, lines, heat transfer, LuGre
pre-sliding, sensor lags, IO delay, supply droop): off by default and then bit for bit the paper's
model; each one, switched on alone, checked against a value derived from its physics."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from plant_golden import GOLDEN, golden_outputs

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ConfigError
from pneutune.control.physics.flow import signed_flow
from pneutune.control.physics.friction import stribeck_force
from pneutune.control.plant import dynamics, flows, params
from pneutune.control.plant.params import (
    P_AA,
    P_AB,
    P_ALPHA,
    P_B,
    P_BV,
    P_C,
    P_DON,
    P_FC,
    P_FS,
    P_GAMMA,
    P_P0,
    P_PERIM,
    P_R,
    P_T0,
    P_V0A,
    P_V0B,
    P_VS,
    P_XMIN,
    S_OPEN,
    S_PA,
    S_PAF,
    S_PB,
    S_STUCK,
    S_TA,
    S_V,
    S_X,
    PlantParams,
    pack_plant,
)
from pneutune.control.sim.closed_loop import ClosedLoopResult, simulate_scenario
from pneutune.control.sim.scenarios import SCENARIOS, Scenario

ROOT = Path(__file__).resolve().parents[1]
P_S = 6.0e5  # supply [Pa abs] (Sec. 5.1)
#: Noise-free, unquantised sensors: readings are the (lagged) true values.
QUIET: dict[str, Any] = {"sensors": {"p_noise": 0.0, "x_noise": 0.0, "x_step": 0.0}}
#: Stiction far above any pressure force (|6e5 - 1e5| Pa x A_a = 3.9 kN < 1e4 N): a piston at
#: x_min charged from A cannot break away, so the chambers are rigid.
HELD: dict[str, Any] = {"friction": {"F_S": 1.0e4, "F_C": 50.0}}
#: Dead volumes of 0.1 m^3: a piston travel of 1 cm changes the chamber pressures by ~0.1 %.
HUGE: dict[str, Any] = {"rig": {"V0a": 0.1, "V0b": 0.1}}
A_IN = np.array([1.0, 0.0, 0.0, 0.0])
SHUT = np.zeros(4)


def _plant(*updates: dict[str, Any]) -> PlantParams:
    """The paper's plant with quiet sensors and ``updates`` merged in, in order."""
    cfg = PlantConfig().with_updates(QUIET)
    for u in updates:
        cfg = cfg.with_updates(u)
    return pack_plant(cfg)


def _advance(pp: PlantParams, s: np.ndarray, t_end: float) -> None:
    dynamics.advance(pp.vec, s, t_end, P_S, pp.force_steps)


def _measure(pp: PlantParams, s: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    dynamics.measure(pp.vec, s, P_S, np.zeros(4), out)
    return out


def _truth(pp: PlantParams, s: np.ndarray) -> np.ndarray:
    out = np.zeros(6)
    dynamics.truth(pp.vec, s, P_S, pp.force_steps, out)
    return out


def _pressures_for(p: np.ndarray, force: float, p_b: float = 2.0e5) -> tuple[float, float]:
    """(p_a, p_b) whose applied force p_a A_a - p_b A_b - p0 (A_a - A_b) is ``force`` [N]."""
    p_a = (force + p_b * p[P_AB] + p[P_P0] * (p[P_AA] - p[P_AB])) / p[P_AA]
    return p_a, p_b


# --- 1. everything off: the paper's model, bit for bit ----------------------------------------

def test_all_effects_off_reproduce_the_golden_outputs_bit_for_bit(monkeypatch) -> None:
    """tests/data/plant_golden.npz was written before the effects existed (tests/plant_golden.py),
    when the step rule's factor was 1.4; with every effect at its default and that factor the
    simulator must return exactly those arrays. With today's factor (2) the paper's rig and the
    open-loop run still do (their friction never shortens a step); the golden's second plant,
    whose steep Stribeck branch the factor limits near v = 0, may not.

    Bit for bit holds on a CPU like the one that wrote the file. On another, numpy's vectorised
    power (the smooth square's quintic edges) may round a reference sample one ULP apart, and
    the square's arrays then differ at about 1e-15 relative (measured: 4e-15 on the sensors,
    1.2e-13 on the duties); there they must agree within 1e-11 relative, far below any effect
    (the weakest, a 31 Pa pressure quantum, is 1e-4 of the pressures)."""
    assert PlantConfig().effects == ()
    today = golden_outputs()
    monkeypatch.setattr(params, "STEP_STIFFNESS", 1.4)
    got = golden_outputs()

    def same(a: np.ndarray, b: np.ndarray, key: str) -> None:
        if key.startswith("square-"):
            np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11 * float(np.max(np.abs(b))),
                                       err_msg=key)
        else:
            assert np.array_equal(a, b), key

    with np.load(GOLDEN) as golden:
        assert sorted(golden.files) == sorted(got)
        for key in golden.files:
            assert got[key].dtype == golden[key].dtype, key
            same(got[key], golden[key], key)
            if "/latched/" not in key:
                same(today[key], golden[key], key)


# --- 2. configuration -------------------------------------------------------------------------

EFFECT_KEYS = [
    ({"valves": {"a_in": {"tau_open": 5.0e-4}}}, "valve lag"),
    ({"valves": {"b_out": {"tau_close": 7.0e-4}}}, "valve lag"),
    ({"lines": {"a": {"delay": 1.0e-3}}}, "lines"),
    ({"lines": {"b": {"volume": 3.8e-6}}}, "lines"),
    ({"lines": {"a": {"C": 1.7e-8}}}, "lines"),
    ({"heat": {"h": 0.0}}, "heat transfer"),  # 0 is the adiabatic energy equation, not "off"
    ({"heat": {"h": 30.0}}, "heat transfer"),
    ({"friction": {"sigma0": 2.5e6}}, "pre-sliding"),
    ({"sensors": {"x_lag": 1.6e-4}}, "sensor lag"),
    ({"sensors": {"p_lag": 4.5e-4}}, "sensor lag"),
    ({"sensors": {"p_step": 31.0}}, "sensor lag"),
    ({"sensors": {"p_at": "valves"}}, "transmitters at the valves"),
    ({"io": {"delay": 5.0e-4}}, "IO delay"),
    ({"supply": {"C": 3.0e-8}}, "supply droop"),
]


@pytest.mark.parametrize(("updates", "name"), EFFECT_KEYS,
                         ids=[f"{n}-{i}" for i, (_, n) in enumerate(EFFECT_KEYS)])
def test_each_effect_key_switches_on_its_effect(updates: dict[str, Any], name: str) -> None:
    """Contract 2: PlantConfig.effects lists exactly the effects whose keys are set."""
    assert PlantConfig().effects == ()
    assert PlantConfig().with_updates(updates).effects == (name,)


def test_parameters_that_only_shape_an_effect_do_not_switch_it_on() -> None:
    """heat.gamma, lines.*.b, supply.b/volume and friction.sigma1 act only with their switch."""
    cfg = PlantConfig().with_updates({"heat": {"gamma": 1.2}, "lines": {"a": {"b": 0.5}},
                                      "supply": {"b": 0.4, "volume": 1.0e-3},
                                      "friction": {"sigma1": 100.0}})
    assert cfg.effects == ()


BAD_VALUES = [
    ({"lines": {"a": {"delay": -1}}}, "lines.a.delay"),
    ({"lines": {"b": {"volume": -1.0e-6}}}, "lines.b.volume"),
    ({"lines": {"a": {"C": 0.0}}}, "lines.a.C"),
    ({"lines": {"b": {"b": 1.0}}}, "lines.b.b"),
    ({"heat": {"hh": 30.0}}, "heat.hh"),
    ({"heat": {"h": -1.0}}, "heat.h"),
    ({"heat": {"gamma": 2.0}}, "heat.gamma"),
    ({"valves": {"a_in": {"tau_open": -1.0e-3}}}, "valves.a_in.tau_open"),
    ({"valves": {"b_in": {"tau_close": 0.5}}}, "valves.b_in.tau_close"),
    ({"friction": {"sigma0": -1.0}}, "friction.sigma0"),
    ({"friction": {"sigma1": -1.0}}, "friction.sigma1"),
    ({"sensors": {"p_lag": -1.0e-3}}, "sensors.p_lag"),
    ({"sensors": {"x_lag": 1.0}}, "sensors.x_lag"),
    ({"sensors": {"p_step": -250.0}}, "sensors.p_step"),
    ({"io": {"delay": 0.02}}, "io.delay"),
    ({"supply": {"C": 0.0}}, "supply.C"),
    ({"supply": {"volume": 0.0}}, "supply.volume"),
]


@pytest.mark.parametrize(("updates", "key"), BAD_VALUES, ids=[k for _, k in BAD_VALUES])
def test_bad_effect_value_is_a_config_error_naming_the_key(updates: dict[str, Any],
                                                           key: str) -> None:
    """Out-of-range values and misspelt keys of the effect blocks are ConfigErrors naming the key
    (contract 2: no silent fallback to a default)."""
    with pytest.raises(ConfigError) as info:
        PlantConfig().with_updates(updates)
    assert info.value.key == key
    assert f": {key}: " in str(info.value)


def test_lugre_without_coulomb_friction_is_a_config_error() -> None:
    """sigma0 > 0 needs F_C > 0: the bristles relax at sigma0 |v| / g(v) with g >= F_C."""
    with pytest.raises(ConfigError) as info:
        PlantConfig().with_updates({"friction": {"sigma0": 1.0e6, "F_C": 0.0}})
    assert info.value.key == "friction"
    assert "F_C" in str(info.value) and "sigma0" in str(info.value)


def test_valve_delay_plus_line_delay_over_four_pwm_periods_names_the_valve() -> None:
    """At 400 Hz, 4 periods are 10 ms: a_out's 3 ms closing delay plus a 7.5 ms line (10.5 ms)
    breaks the pending-transition bound; a_in with 2 ms delays (9.5 ms) does not."""
    base = {"rig": {"pwm_hz": 400.0},
            "valves": {"a_in": {"delay_on": 2.0e-3, "delay_off": 2.0e-3}}}
    assert PlantConfig().with_updates(base).effects == ()  # 3 ms alone is allowed
    with pytest.raises(ConfigError) as info:
        PlantConfig().with_updates(base).with_updates({"lines": {"a": {"delay": 7.5e-3}}})
    message = str(info.value)
    assert "valves.a_out" in message and "lines.a.delay" in message
    assert "valves.a_in" not in message
    assert info.value.key == "valves.a_out"  # the rule across blocks names its key, not ""


# --- 3. valve armature lag ------------------------------------------------------------------

def test_valve_lag_opens_and_closes_exponentially() -> None:
    """open fraction = 1 - exp(-(t - t_on)/tau_open) from t_on = delay_on, then from the closing
    transition t_off it is y(t_off) exp(-(t - t_off)/tau_close) (valve docstring, contract 2).

    a_in: delay_on 2 ms, delay_off 1 ms, min_pulse 1.5 ms; duty 1 at t = 0, duty 0 at 1.6 ms
    (a 1.6 ms pulse, longer than min_pulse): opens at 2.0 ms, closes at 2.6 ms, when the fraction
    has reached 1 - exp(-0.6/0.5) = 0.699 only.
    """
    tau_on, tau_off = 5.0e-4, 7.0e-4
    pp = _plant({"valves": {"a_in": {"tau_open": tau_on, "tau_close": tau_off,
                                     "delay_off": 1.0e-3}}})
    p = pp.vec
    s = dynamics.initial_state(p, 0.02, 2.0e5, 2.0e5)
    dynamics.set_duties(p, s, 0.0, A_IN)
    _advance(pp, s, 1.5e-3)
    assert dynamics.open_fraction(p, s, 0, 1.5e-3) == 0.0  # before delay_on
    _advance(pp, s, 1.6e-3)
    assert dynamics.open_fraction(p, s, 0, 1.6e-3) == 0.0
    dynamics.set_duties(p, s, 1.6e-3, SHUT)
    t_on, t_off = 2.0e-3, 2.6e-3
    _advance(pp, s, t_on + tau_on)
    y = dynamics.open_fraction(p, s, 0, t_on + tau_on)
    assert y == pytest.approx(1.0 - math.exp(-1.0), abs=1e-9)
    # the flow of Eq. (7) is scaled by the open fraction (the chamber barely moved since t_on)
    mdot = signed_flow(p[P_C], p[P_B], P_S, s[S_PA], p[P_T0])
    assert _truth(pp, s)[4] == pytest.approx(y * mdot, rel=1e-9)
    y_off = 1.0 - math.exp(-(t_off - t_on) / tau_on)
    for dt in (tau_off, 2.0 * tau_off, 5.0 * tau_off):
        _advance(pp, s, t_off + dt)
        assert dynamics.open_fraction(p, s, 0, t_off + dt) == pytest.approx(
            y_off * math.exp(-dt / tau_off), abs=1e-9)


# --- 4. line delay and volume ---------------------------------------------------------------

def _opening_instant_brackets(pp: PlantParams, t_open: float) -> None:
    """Duty 1 on a_in at t = 0: closed (and no flow) 20 us before ``t_open``, open just after."""
    s = dynamics.initial_state(pp.vec, 0.02, 2.0e5, 2.0e5)
    dynamics.set_duties(pp.vec, s, 0.0, A_IN)
    _advance(pp, s, t_open - 2.0e-5)
    assert s[S_OPEN] == 0.0
    assert _truth(pp, s)[4] == 0.0
    _advance(pp, s, t_open + 2.0e-5)
    assert s[S_OPEN] == 1.0
    assert _truth(pp, s)[4] > 0.0


def test_line_delay_postpones_the_valve_opening() -> None:
    """The pressure wave needs lines.a.delay to reach the chamber: opening at delay_on + 1 ms."""
    pp = _plant({"lines": {"a": {"delay": 1.0e-3}}})
    _opening_instant_brackets(pp, pp.config.valves.a_in.delay_on + 1.0e-3)


def test_line_volume_adds_to_the_dead_volume() -> None:
    """P_V0A = rig.V0a + lines.a.volume, P_V0B = rig.V0b + lines.b.volume (exact float sums)."""
    pp = _plant({"lines": {"a": {"volume": 3.8e-6}, "b": {"volume": 1.0e-5}}})
    rig = pp.config.rig
    assert pp.vec[P_V0A] == rig.V0a + 3.8e-6
    assert pp.vec[P_V0B] == rig.V0b + 1.0e-5


# --- 5. line conductance --------------------------------------------------------------------

@pytest.mark.parametrize("C_line", [1.7e-8, 8.0e-9])
def test_line_conductance_conserves_mass_and_restricts_the_flow(C_line: float) -> None:
    """One open inlet valve (6 bar) and a line into a chamber at ambient: the junction has no
    volume, so what the valve draws from the supply is what the line delivers; the series
    restriction passes less than the valve alone (Eq. 7 with the valve's C, b)."""
    pp = _plant({"lines": {"a": {"C": C_line}}})
    p = pp.vec
    p0, T0 = p[P_P0], p[P_T0]
    s = dynamics.initial_state(p, 0.02, p0, p0)
    m_in, h, m_sup = flows.line_flow(p, s, 0, 1.0, 0.0, P_S, p0, T0)
    alone = signed_flow(p[P_C], p[P_B], P_S, p0, T0)
    assert m_in == pytest.approx(m_sup, rel=1e-6)
    assert h == pytest.approx(m_in * T0, rel=1e-12)  # inflow carries the junction's T0
    assert 0.0 < m_in < alone


def test_wide_line_approaches_the_valve_alone() -> None:
    """With C_line = 1e-6 >> C_valve = 8.4e-9 the junction sits at the chamber's pressure and the
    valve alone sets the flow (within 1 %)."""
    pp = _plant({"lines": {"a": {"C": 1.0e-6}}})
    p = pp.vec
    p0, T0 = p[P_P0], p[P_T0]
    s = dynamics.initial_state(p, 0.02, p0, p0)
    m_in, _, m_sup = flows.line_flow(p, s, 0, 1.0, 0.0, P_S, p0, T0)
    alone = signed_flow(p[P_C], p[P_B], P_S, p0, T0)
    assert m_in == pytest.approx(alone, rel=0.01)
    assert m_sup == pytest.approx(m_in, rel=1e-6)


# --- 6. heat transfer -----------------------------------------------------------------------

def _charge_a(pp: PlantParams, t_charge: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Held piston at x_min, chambers at ambient, a_in fully open from t = 0; p_a and the state
    sampled at n equal steps up to ``t_charge``."""
    p = pp.vec
    s = dynamics.initial_state(p, p[P_XMIN], p[P_P0], p[P_P0])
    dynamics.set_duties(p, s, 0.0, A_IN)
    pa = np.empty(n)
    for k in range(n):
        _advance(pp, s, (k + 1) * t_charge / n)
        pa[k] = s[S_PA]
    assert s[S_STUCK] == 1.0 and s[S_X] == p[P_XMIN]  # the piston never moved
    return pa, s


def test_adiabatic_charging_equals_the_polytropic_model_with_n_gamma() -> None:
    """Pure inflow at T0 into a rigid chamber: the energy equation gives dp/dt = gamma R T0 mdot
    / V, the paper's Eq. (5) n R T0 mdot / V, so heat.h = 0, gamma = 1.2 is rig.n = 1.2 (same
    p_a(t) within 1e-6) while the gas heats up (adiabatic filling: T -> gamma T0)."""
    paper = _plant(HELD, {"rig": {"n": 1.2}})
    heat = _plant(HELD, {"rig": {"n": 1.2}, "heat": {"h": 0.0, "gamma": 1.2}})
    pa_paper, _ = _charge_a(paper, 0.03, 30)
    pa_heat, s = _charge_a(heat, 0.03, 30)
    assert pa_paper[-1] > 3.0e5  # charged well above ambient
    np.testing.assert_allclose(pa_heat, pa_paper, rtol=1e-6, atol=0.0)
    assert s[S_TA] > heat.vec[P_T0] + 10.0


@pytest.mark.parametrize("h", [0.0, 30.0])
def test_closed_chamber_cools_to_the_walls_with_the_convective_time_constant(h: float) -> None:
    """After the valve closes, a rigid chamber keeps its mass m: p/T stays constant and
    m c_v dT/dt = h A_w (T0 - T), c_v = R/(gamma - 1), A_w = 2 A_a + perimeter V / A_a. So
    T - T0 decays as exp(-t/tau), tau = m R / ((gamma - 1) h A_w), and p follows T; with h = 0
    both stay constant (exactly: every derivative is zero)."""
    pp = _plant(HELD, {"heat": {"h": h, "gamma": 1.4}})
    p = pp.vec
    _, s = _charge_a(pp, 0.02, 1)
    dynamics.set_duties(p, s, 0.02, SHUT)
    t1 = 0.03  # the valve closed at 0.02 + delay_off = 0.023 s
    _advance(pp, s, t1)
    assert s[S_OPEN:S_OPEN + 4].sum() == 0.0
    p1, T1 = s[S_PA], s[S_TA]
    T0 = p[P_T0]
    assert T1 > T0 + 20.0
    V = p[P_V0A]
    area = 2.0 * p[P_AA] + p[P_PERIM] * V / p[P_AA]
    mass = p1 * V / (p[P_R] * T1)
    for dt in (0.1, 0.3, 1.0):
        _advance(pp, s, t1 + dt)
        if h == 0.0:
            assert s[S_TA] == T1 and s[S_PA] == p1
            continue
        tau = mass * p[P_R] / ((p[P_GAMMA] - 1.0) * h * area)  # 0.25 s here
        assert s[S_TA] == pytest.approx(T0 + (T1 - T0) * math.exp(-dt / tau), rel=1e-6)
        assert s[S_PA] / s[S_TA] == pytest.approx(p1 / T1, rel=1e-9)  # mass conserved
        assert s[S_PA] < p1
    if h > 0.0:
        assert s[S_TA] - T0 < 0.05 * (T1 - T0)  # 1 s = 4 tau: within 2 % of the walls


# --- 7. LuGre friction ----------------------------------------------------------------------

@pytest.mark.parametrize("force", [10.0, 30.0])
def test_lugre_pre_sliding_creeps_on_the_bristles_and_stops(force: float) -> None:
    """Applied force F < F_C, valves shut, huge dead volumes: at rest sigma0 z = F. Along the
    creep dz/dx = 1 - sigma0 z / g(v); its speed stays below F/(sigma1 + b_v) = 1.5-4.5 mm/s
    < v_s = 5 mm/s, so g stays near F_S (measured: within 1.2 %) and the displacement is
    x = -(F_S / sigma0) ln(1 - F / F_S) (= F/sigma0 to first order in F/F_S: 7 % above it at
    10 N, 28 % at 30 N). Checked to 3 %. The Stribeck plant, below F_S, does not move at all."""
    sigma0 = 1.0e6
    lugre = _plant(HUGE, {"friction": {"sigma0": sigma0, "sigma1": 3.2e3}})
    stribeck = _plant(HUGE)
    p = lugre.vec
    p_a, p_b = _pressures_for(p, force)
    x0 = 0.02
    s = dynamics.initial_state(p, x0, p_a, p_b)
    _advance(lugre, s, 0.2)
    creep = s[S_X] - x0
    expected = -(p[P_FS] / sigma0) * math.log(1.0 - force / p[P_FS])
    assert creep == pytest.approx(expected, rel=0.03)
    if force <= 10.0:
        assert creep == pytest.approx(force / sigma0, rel=0.15)
    _advance(lugre, s, 0.5)  # and no further sliding
    assert abs(s[S_X] - x0 - creep) < 1e-3 * creep
    assert abs(s[S_V]) < 1e-9
    s = dynamics.initial_state(stribeck.vec, x0, p_a, p_b)
    _advance(stribeck, s, 0.5)
    assert s[S_X] == x0 and s[S_STUCK] == 1.0


def test_lugre_steady_sliding_is_the_stribeck_law() -> None:
    """In steady sliding dz/dt = 0 gives sigma0 z = g(v), so F_f = g(v) + b_v v: Eq. (2). An
    applied 400 N on huge volumes slides at v ~ (F - F_C)/b_v = 0.1 m/s on both plants; after
    0.1 s (300 viscous time constants M/b_v) the speeds agree within 1 % and the friction the
    truth reports is stribeck_force(v)."""
    force = 400.0
    speeds = []
    for pp in (_plant(HUGE), _plant(HUGE, {"friction": {"sigma0": 2.5e6, "sigma1": 3.2e3}})):
        p = pp.vec
        s = dynamics.initial_state(p, 0.0, *_pressures_for(p, force))
        _advance(pp, s, 0.1)
        v = s[S_V]
        assert v == pytest.approx((force - p[P_FC]) / p[P_BV], rel=0.02)
        f_ff = _truth(pp, s)[2]
        assert f_ff == pytest.approx(
            stribeck_force(v, 1.0, p[P_FS], p[P_FC], p[P_VS], p[P_ALPHA], p[P_BV]), rel=0.01)
        speeds.append(v)
    assert speeds[1] == pytest.approx(speeds[0], rel=0.01)


# --- 8. sensor lag and quantum --------------------------------------------------------------

def test_pressure_sensor_lag_is_first_order() -> None:
    """tau dy/dt = p_a - y with p_a constant (piston stuck at balance, valves shut): from
    y(0) = p_a - 1e5 the reading after one tau is p_a - 1e5 exp(-1)."""
    tau = 1.0e-3
    pp = _plant({"sensors": {"p_lag": tau}})
    p = pp.vec
    p_a, p_b = dynamics.balanced_pressures(p, 2.0e5)
    s = dynamics.initial_state(p, 0.02, p_a, p_b)
    s[S_PAF] = p_a - 1.0e5
    _advance(pp, s, tau)
    assert s[S_PA] == p_a  # the true pressure did not move
    reading = _measure(pp, s)
    assert reading[1] == pytest.approx(p_a - 1.0e5 * math.exp(-1.0), rel=1e-6)
    assert reading[2] == p_b  # its lag started settled


#: Chamber A behind a line of 1.7e-8 m^3/(s Pa) (0.3 m of 4 mm tube), its transmitter at the
#: valves' side of it.
AT_VALVES: dict[str, Any] = {"lines": {"a": {"C": 1.7e-8}}, "sensors": {"p_at": "valves"}}


def test_transmitter_at_the_valves_reads_the_junction_while_air_flows() -> None:
    """Held piston, chambers at ambient, a_in open: while the line carries air the transmitter
    reads the junction, where the valve's Eq. (7) flow equals the line's (the balance is zero
    to the solver's 1e-7 tolerance) and which leads the chamber toward the supply. With the
    valve shut again no air flows: it reads the chamber's pressure, as chamber B's does all
    along, and as the same plant with its transmitters at the chamber reads throughout."""
    pp = _plant(HELD, AT_VALVES)
    at_chamber = _plant(HELD, {"lines": AT_VALVES["lines"]})
    p = pp.vec
    s = dynamics.initial_state(p, p[P_XMIN], p[P_P0], p[P_P0])
    s_c = s.copy()
    dynamics.set_duties(p, s, 0.0, A_IN)
    dynamics.set_duties(at_chamber.vec, s_c, 0.0, A_IN)
    t_open = p[P_DON] + 5.0e-3  # 5 ms after the valve opened
    _advance(pp, s, t_open)
    _advance(at_chamber, s_c, t_open)
    assert np.array_equal(s, s_c)  # where the transmitter sits changes no physics
    reading = _measure(pp, s)
    pc = s[S_PA]
    assert pc + 1.0e4 < reading[1] < P_S  # the junction leads the chamber by > 0.1 bar
    balance = flows.junction_balance(p, 0, 1.0, 0.0, P_S, reading[1], pc, p[P_T0])
    m_line, _, _ = flows.line_flow(p, s.copy(), 0, 1.0, 0.0, P_S, pc, p[P_T0])
    assert abs(balance) < 1.0e-5 * m_line
    assert reading[2] == s[S_PB]
    assert _measure(at_chamber, s_c)[1] == pc
    dynamics.set_duties(p, s, t_open, SHUT)
    _advance(pp, s, t_open + 0.02)  # past the closing delay
    assert s[S_OPEN] == 0.0
    assert _measure(pp, s)[1] == s[S_PA]


def test_lagged_transmitter_at_the_valves_follows_the_junction() -> None:
    """With p_lag the lag filters what the transmitter reads: a lag of 1 us, far below the
    junction's milliseconds, leaves the reading at the junction's pressure (within 0.2 %),
    not at the chamber's, which lies more than 0.1 bar below it."""
    lagged = _plant(HELD, AT_VALVES, {"sensors": {"p_lag": 1.0e-6}})
    plain = _plant(HELD, AT_VALVES)
    s = dynamics.initial_state(lagged.vec, lagged.vec[P_XMIN], lagged.vec[P_P0],
                               lagged.vec[P_P0])
    dynamics.set_duties(lagged.vec, s, 0.0, A_IN)
    _advance(lagged, s, lagged.vec[P_DON] + 5.0e-3)
    junction = _measure(plain, s)[1]
    assert junction > s[S_PA] + 1.0e4
    assert _measure(lagged, s)[1] == pytest.approx(junction, rel=2.0e-3)


def test_pressure_quantum_rounds_every_pressure_reading() -> None:
    """sensors.p_step = 250 Pa: p_a, p_b and p_s readings (noise on) are multiples of 250 Pa."""
    pp = pack_plant(PlantConfig().with_updates({"sensors": {"p_step": 250.0}}))
    rng = np.random.default_rng(5)
    n = 300
    duties = rng.uniform(0.0, 1.0, (n, 4)) * (rng.uniform(0.0, 1.0, (n, 1)) > 0.3)
    s = dynamics.initial_state(pp.vec, 0.02, 2.0e5, 2.0e5)
    sensors = np.zeros((n, 4))
    truth = np.zeros((n, 6))
    dynamics.run_open_loop(pp.vec, s, duties, np.full(n, P_S), pp.force_steps,
                           rng.standard_normal((n, 4)), 0.004, sensors, truth)
    steps = sensors[:, 1:] / 250.0
    assert np.ptp(sensors[:, 1]) > 1.0e4  # the run did move the pressures
    np.testing.assert_allclose(steps, np.round(steps), rtol=0.0, atol=1e-9)


# --- 9. IO delay ----------------------------------------------------------------------------

def test_io_delay_postpones_the_duty() -> None:
    """A duty written at t = 0 acts at io.delay = 1 ms: the valve opens at delay_on + 1 ms."""
    pp = _plant({"io": {"delay": 1.0e-3}})
    _opening_instant_brackets(pp, pp.config.valves.a_in.delay_on + 1.0e-3)


def test_io_delay_holds_for_every_valid_sample_period() -> None:
    """Duty 1 written every rig.Ts = 0.25 ms from t = 0 with io.delay = 10 ms: the first write
    must act at 10 ms, so a_in opens at 10 ms + delay_on = 12 ms."""
    pp = _plant({"rig": {"Ts": 2.5e-4}, "io": {"delay": 1.0e-2}})
    p = pp.vec
    s = dynamics.initial_state(p, 0.02, 2.0e5, 2.0e5)
    Ts = pp.config.rig.Ts
    t_open = 1.0e-2 + pp.config.valves.a_in.delay_on
    k = 0
    while (k + 1) * Ts < t_open - 1.0e-6:
        dynamics.set_duties(p, s, k * Ts, A_IN)
        _advance(pp, s, (k + 1) * Ts)
        assert s[S_OPEN] == 0.0, f"a_in open by t = {(k + 1) * Ts:.5f} s"
        k += 1


# --- 10. supply droop -----------------------------------------------------------------------

def test_supply_line_droops_while_charging_and_recovers() -> None:
    """A supply line (C = 3e-8) into a 0.5 l manifold feeding a_in: while chamber A charges the
    manifold, read by the supply sensor, sags below rig.p_s (the line needs a pressure drop to
    pass the valve's flow), the chamber charges more slowly than from a stiff supply, and after
    the valve closes the manifold refills to p_s (its linearised time constant is ~3 ms)."""
    results = []
    for updates in ({}, {"supply": {"C": 3.0e-8, "volume": 5.0e-4}}):
        pp = _plant(HELD, updates)
        p = pp.vec
        s = dynamics.initial_state(p, p[P_XMIN], p[P_P0], p[P_P0])
        dynamics.set_duties(p, s, 0.0, A_IN)
        ps_min = np.inf
        for k in range(1, 41):
            _advance(pp, s, k * 1.0e-3)
            ps_min = min(ps_min, _measure(pp, s)[3])
        pa_charged = s[S_PA]
        dynamics.set_duties(p, s, 0.04, SHUT)
        _advance(pp, s, 0.54)
        results.append((ps_min, pa_charged, _measure(pp, s)[3]))
    (stiff_min, stiff_pa, _), (droop_min, droop_pa, droop_end) = results
    assert stiff_min == P_S
    assert droop_min < P_S - 1.0e3
    assert abs(droop_end - P_S) < 100.0
    assert droop_pa < stiff_pa


# --- 11. closed loop with every effect ------------------------------------------------------

ALL_EFFECTS: dict[str, Any] = {
    "valves": {name: {"tau_open": 5.0e-4, "tau_close": 7.0e-4}
               for name in ("a_in", "a_out", "b_in", "b_out")},
    "lines": {side: {"delay": 9.0e-4, "volume": 3.8e-6, "C": 1.7e-8} for side in ("a", "b")},
    "heat": {"h": 30.0},
    "friction": {"sigma0": 2.5e6, "sigma1": 3.2e3},
    "sensors": {"p_lag": 4.5e-4, "x_lag": 1.6e-4, "p_step": 31.0},
    "io": {"delay": 5.0e-4},
    "supply": {"C": 3.0e-8, "volume": 5.0e-4},
}


def _sine_3s() -> Scenario:
    base = SCENARIOS["sine-0.5hz"]
    return Scenario(base.name + "-3s", base.description, 3.0, base.period, base.reference)


@pytest.fixture(scope="module")
def all_effects_runs() -> tuple[ClosedLoopResult, ClosedLoopResult]:
    """The paper's controller on a 3 s sine with every effect on, twice with seed 3."""
    ctl = load_controller(ROOT / "data" / "controller-paper.yaml")
    cfg = PlantConfig().with_updates(ALL_EFFECTS)
    assert len(cfg.effects) == 7
    return (simulate_scenario(ctl, _sine_3s(), cfg, seed=3),
            simulate_scenario(ctl, _sine_3s(), cfg, seed=3))


def test_closed_loop_with_every_effect_tracks(
        all_effects_runs: tuple[ClosedLoopResult, ClosedLoopResult]) -> None:
    """Typical magnitudes of every effect leave the paper's controller tracking the 0.5 Hz sine
    (the paper's Table 1 reports E_rms of a few tenths of a mm on the rig): E_rms < 1 mm."""
    r, _ = all_effects_runs
    assert r.metrics.status == "ok"
    assert r.sensors.shape == (750, 4)  # 3 s at Ts = 4 ms
    assert np.all(np.isfinite(r.sensors))
    assert r.metrics.E_rms_mm < 1.0


def test_closed_loop_with_every_effect_is_reproducible(
        all_effects_runs: tuple[ClosedLoopResult, ClosedLoopResult]) -> None:
    """The same seed gives the same arrays, bit for bit."""
    a, b = all_effects_runs
    assert np.array_equal(a.sensors, b.sensors)
    assert np.array_equal(a.duties, b.duties)
    assert np.array_equal(a.control_state, b.control_state)


def test_reading_the_truth_does_not_change_the_trajectory() -> None:
    """truth() observes the plant; calling it at every sample must not change the run."""
    pp = _plant({"lines": {"a": {"C": 1.7e-8}, "b": {"C": 1.7e-8}}})
    p = pp.vec
    rng = np.random.default_rng(0)
    n = 300
    duties = rng.uniform(0.0, 1.0, (n, 4)) * (rng.uniform(0.0, 1.0, (n, 1)) > 0.3)
    finals = []
    for observe in (False, True):
        s = dynamics.initial_state(p, 0.02, 2.0e5, 2.0e5)
        for k in range(n):
            if observe:
                _truth(pp, s)
            dynamics.set_duties(p, s, k * 0.004, duties[k])
            _advance(pp, s, (k + 1) * 0.004)
        finals.append(s[[S_X, S_V, S_PA, S_PB]])
    assert np.array_equal(finals[0], finals[1])
