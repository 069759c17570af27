"""The flows into the chambers: the valves (Eq. 7, the seal leak) and, on a real rig, the
armature lag, the lines and the heat each flow carries (numba).

:func:`chamber_flows` is the paper's model (every valve fully open or closed, straight into its
chamber); :func:`rig_flows` adds the real-rig effects of contract 2 (module docstring of
:mod:`pneutune.control.plant.dynamics`): each valve's open fraction (:func:`open_fraction`)
scales its flow, and a line's conductance meets the valves at a junction of negligible volume
whose pressure balances their flows (:func:`line_flow`).
"""

from __future__ import annotations

import math

import numpy as np

from pneutune.control.numba_cache import njit
from pneutune.control.physics.flow import signed_flow, signed_flow_k, signed_flow_t
from pneutune.control.plant.illinois import illinois_update
from pneutune.control.plant.params import (
    P_B,
    P_C,
    P_KT,
    P_LEAKC,
    P_LINEB,
    P_LINEC,
    P_P0,
    P_T0,
    P_TAUOFF,
    P_TAUON,
    P_VLAG,
    S_OPEN,
    S_PJ,
    S_TY,
    S_Y0,
)


# inlined into dynamics._rk4 (with dynamics._deriv) by numba: as calls, four times a step,
# they cost a quarter of a run (docs/integration.md, "What a step costs")
@njit(cache=True, inline="always")
def chamber_flows(p: np.ndarray, s: np.ndarray, pa: float, pb: float,
                  p_s: float) -> tuple[float, float]:
    """Net mass flows into chambers A and B [kg/s] with the valves as they are in ``s``
    (the paper's model: every valve fully open or closed, straight into its chamber)."""
    k_T = p[P_KT]  # sqrt(T_ref / T0), computed once per plant
    p0 = p[P_P0]
    ma = 0.0
    mb = 0.0
    if s[S_OPEN + 0] > 0.5:
        ma += signed_flow_k(p[P_C + 0], p[P_B + 0], p_s, pa, k_T)
    if s[S_OPEN + 1] > 0.5:
        ma -= signed_flow_k(p[P_C + 1], p[P_B + 1], pa, p0, k_T)
    if s[S_OPEN + 2] > 0.5:
        mb += signed_flow_k(p[P_C + 2], p[P_B + 2], p_s, pb, k_T)
    if s[S_OPEN + 3] > 0.5:
        mb -= signed_flow_k(p[P_C + 3], p[P_B + 3], pb, p0, k_T)
    if p[P_LEAKC] > 0.0:
        leak = signed_flow_k(p[P_LEAKC], 0.0, pa, pb, k_T)
        ma -= leak
        mb += leak
    return ma, mb


@njit(cache=True)
def open_fraction(p: np.ndarray, s: np.ndarray, i: int, t: float) -> float:
    """How far valve ``i`` is open at time ``t``, 0..1.

    Without armature time constants it is the switching state (0 or 1). With them, from the
    last transition at ``s[S_TY + i]`` the fraction moves exponentially from where it was then
    (``s[S_Y0 + i]``) towards the new state, with ``tau_open`` or ``tau_close``.
    """
    o = s[S_OPEN + i]
    if p[P_VLAG] < 0.5:
        return o
    tau = p[P_TAUON + i] if o > 0.5 else p[P_TAUOFF + i]
    if tau <= 0.0:
        return o
    r = (t - s[S_TY + i]) / tau
    if r > 20.0:  # settled to within 2e-9: the valve is where it switched to
        return o
    return o + (s[S_Y0 + i] - o) * math.exp(-r)


@njit(cache=True)
def enthalpy_flow(m: float, T_in: float, T_out: float) -> float:
    """``m`` times the temperature of the gas it carries: ``T_in`` flowing in, else ``T_out``."""
    return m * (T_in if m > 0.0 else T_out)


@njit(cache=True)
def junction_balance(p: np.ndarray, side: int, y_in: float, y_out: float, p_sup: float,
                      pj: float, pc: float, Tc: float) -> float:
    """Net mass flow into a line's junction at pressure ``pj`` [kg/s]: from the inlet valve,
    less the exhaust valve's and the line's."""
    T0 = p[P_T0]
    i_in = 2 * side
    f = -signed_flow_t(p[P_LINEC + side], p[P_LINEB + side], pj, pc, T0, Tc)
    if y_in > 0.0:
        f += y_in * signed_flow(p[P_C + i_in], p[P_B + i_in], p_sup, pj, T0)
    if y_out > 0.0:
        f -= y_out * signed_flow(p[P_C + i_in + 1], p[P_B + i_in + 1], pj, p[P_P0], T0)
    return f


@njit(cache=True)
def line_flow(p: np.ndarray, s: np.ndarray, side: int, y_in: float, y_out: float, p_sup: float,
               pc: float, Tc: float) -> tuple[float, float, float]:
    """One chamber's valves, and its line: (mass flow into the chamber, that flow times the
    temperature it carries, mass flow drawn from the supply) [kg/s, kg K/s, kg/s].

    Without a line conductance the valves feed the chamber directly. With one, the valves meet
    the line at a junction of negligible volume (gas at T0), whose pressure balances the
    valves' net flow against the line's: found by the Illinois variant of regula falsi on that
    balance, which falls monotonically with the junction pressure.
    """
    T0 = p[P_T0]
    p0 = p[P_P0]
    i_in = 2 * side
    i_out = i_in + 1
    CL = p[P_LINEC + side]
    if CL <= 0.0:
        m_in = 0.0
        m_out = 0.0
        if y_in > 0.0:
            m_in = y_in * signed_flow_t(p[P_C + i_in], p[P_B + i_in], p_sup, pc, T0, Tc)
        if y_out > 0.0:
            m_out = y_out * signed_flow_t(p[P_C + i_out], p[P_B + i_out], pc, p0, Tc, T0)
        h = enthalpy_flow(m_in, T0, Tc) - enthalpy_flow(m_out, Tc, T0)
        return m_in - m_out, h, m_in
    if y_in <= 0.0 and y_out <= 0.0:
        return 0.0, 0.0, 0.0
    # the balance is >= 0 below every port's pressure and <= 0 above them all; the bracket
    # starts as a narrow one around the last solution (it moves little between calls)
    lo = min(p_sup, p0, pc)
    hi = max(p_sup, p0, pc)
    a, b = lo, hi
    last = s[S_PJ + side]
    fa = 1.0
    fb = -1.0
    if lo < last < hi:
        a = max(lo, last * (1.0 - 2.0e-4))
        b = min(hi, last * (1.0 + 2.0e-4))
        fa = junction_balance(p, side, y_in, y_out, p_sup, a, pc, Tc)
        fb = junction_balance(p, side, y_in, y_out, p_sup, b, pc, Tc)
        if fa < 0.0:  # the solution is below the narrow bracket
            b, fb = a, fa
            a = lo
            fa = junction_balance(p, side, y_in, y_out, p_sup, a, pc, Tc)
        elif fb > 0.0:  # above it
            a, fa = b, fb
            b = hi
            fb = junction_balance(p, side, y_in, y_out, p_sup, b, pc, Tc)
    else:
        fa = junction_balance(p, side, y_in, y_out, p_sup, a, pc, Tc)
        fb = junction_balance(p, side, y_in, y_out, p_sup, b, pc, Tc)
    tol = 1.0e-7 * hi  # 0.06 Pa at 6 bar: far below the sensor noise
    pj = a
    prev = b
    side_ = 0
    for _ in range(60):
        pj = 0.5 * (a + b) if fb == fa else (a * fb - b * fa) / (fb - fa)
        f = junction_balance(p, side, y_in, y_out, p_sup, pj, pc, Tc)
        if f == 0.0 or abs(pj - prev) < tol:
            break
        prev = pj
        a, fa, b, fb, side_ = illinois_update(a, fa, b, fb, pj, f, side_)
    s[S_PJ + side] = pj
    m_line = signed_flow_t(CL, p[P_LINEB + side], pj, pc, T0, Tc)
    m_sup = y_in * signed_flow(p[P_C + i_in], p[P_B + i_in], p_sup, pj, T0) if y_in > 0.0 else 0.0
    return m_line, enthalpy_flow(m_line, T0, Tc), m_sup


@njit(cache=True)
def rig_flows(p: np.ndarray, s: np.ndarray, pa: float, pb: float, p_sup: float, ta: float,
           tb: float, t: float) -> tuple[float, float, float, float, float]:
    """Flows with the real-rig effects: (into A, into B, their enthalpy terms, from the
    supply) [kg/s, kg/s, kg K/s, kg K/s, kg/s]; ``ta``/``tb`` are T0 without heat transfer."""
    ma, ha, msa = line_flow(p, s, 0, open_fraction(p, s, 0, t), open_fraction(p, s, 1, t), p_sup,
                             pa, ta)
    mb, hb, msb = line_flow(p, s, 1, open_fraction(p, s, 2, t), open_fraction(p, s, 3, t), p_sup,
                             pb, tb)
    if p[P_LEAKC] > 0.0:
        leak = signed_flow_t(p[P_LEAKC], 0.0, pa, pb, ta, tb)
        hl = enthalpy_flow(leak, ta, tb)
        ma -= leak
        mb += leak
        ha -= hl
        hb += hl
    return ma, mb, ha, hb, msa + msb


__all__ = ["chamber_flows", "enthalpy_flow", "junction_balance", "line_flow", "open_fraction",
           "rig_flows"]
