"""An independent simulator of the servo-pneumatic rig, speaking ``pneutune.rig/1`` on a pipe.

    .venv/bin/python tests/drivers/other_sim_driver.py [--plant PLANT.yaml] --scenario NAME
        --seed N [--x0 X] [--sample-period S]
    .venv/bin/python tests/drivers/other_sim_driver.py [--plant PLANT.yaml] --scenario NAME
        --print-plant

A second simulator of the physics of the paper's Sec. 2 (Qian et al., 2014), written apart from
pneutune's own, so that ``deploy --rig exec:`` -> ``identify`` -> ``tune`` can be checked against
a plant that pneutune did not write. It imports nothing of pneutune; the tests and
``benchmarks/other_sim.py`` run it as a program. It reads requests on stdin and writes replies on
stdout, binary and little-endian, as docs/deploy.md ("The pipe protocol") specifies: ``H``
hello, ``R`` read, ``W`` write, ``A`` advance, ``T`` truth, ``C`` close; an ``E`` reply (bad
duty, unknown opcode) closes the valves and exits 1; end of input closes the valves and exits 0.
``--print-plant`` serves nothing: it prints the truth a client compares an identified model with,
as one line of JSON (``{"plant": <the complete plant>, "moving_mass": <kg, payload included>}``),
and exits 0.

The model (SI units; valve order a_in, a_out, b_in, b_out)
------------------------------------------------------------
State ``[x, v, p_a, p_b, z]``.

* Motion (paper Eq. 1): ``M a = p_a A_a - p_b A_b - p0 (A_a - A_b) - F_f - F_ext + F_stop``;
  the rod term is ``p0 A_r`` with ``A_r = A_a - A_b``. ``F_ext`` > 0 opposes positive motion.
* Friction: LuGre, ``dz/dt = v - sigma0 |v| z / g(v)``,
  ``g(v) = F_C + (F_S - F_C) exp(-|v / v_s|^alpha)``,
  ``F_f = sigma0 z + sigma1 dz/dt + b_v v``.
* End stops at ``x_min``, ``x_max``: a one-sided stiff spring-damper (``stops.k``, ``stops.c``)
  that only pushes.
* Chambers (paper Eq. 5, 6, 8), gas at ``T0``:
  ``dp_a/dt = n R T0 mdot_a / V_a - n p_a A_a v / V_a``,
  ``dp_b/dt = n R T0 mdot_b / V_b + n p_b A_b v / V_b``,
  ``V_a = V0a + A_a (x - x_min)``, ``V_b = V0b + A_b (x_max - x)``; ``mdot`` is the net mass flow
  into the chamber (inlet from the supply, outlet to ambient, plus the leaks).
* Valve flow (paper Eq. 7, ISO 6358): ``mdot = y C rho0 p_u sqrt(T_ref / T_u) phi(p_d / p_u)``
  with ``phi = 1`` for ``r <= b``, ``sqrt(1 - ((r - b) / (1 - b))^2)`` above, ``rho0`` = 1.185
  kg/m^3, ``T_ref`` = 293.15 K, ``T_u = T0``; ``y`` in [0, 1] is the valve's opening. Flow
  reverses when the downstream pressure is the higher one.
* Leaks (optional, default off): chamber A <-> B (``C_ab``), A -> ambient (``C_a0``), B ->
  ambient (``C_b0``), the same ISO law with the critical ratio ``leak.b``.
* PWM at ``pwm_hz``: a period starts at every ``k / pwm_hz``; the coil is on from the period start
  for ``d / pwm_hz``. ``immediate``: the coil is on while the time since the period start is
  below ``d_now / pwm_hz`` (a duty written mid-period acts at once, and may switch the coil on or
  off mid-period). ``latched``: the duty in force at the period start holds the whole period.
  ``d = 1`` is permanently on, ``d = 0`` permanently off.
* Valve mechanics: a coil on-edge starts the opening ``delay_on`` later, an off-edge starts the
  closing ``delay_off`` later; the opening moves linearly over ``ramp`` seconds. A coil pulse
  (on or off) shorter than ``min_pulse`` does not move the armature: a short on-pulse does not
  open the valve, a short off-gap does not close it. (If ``min_pulse`` exceeds a delay, the
  movement starts ``min_pulse`` after the edge, to stay causal.)
* Integration: fixed-step classic RK4, ``substeps`` per control period ``Ts`` (default 40: 0.1
  ms), the valve openings evaluated exactly (piecewise linear) at every RK4 stage time.
* Sampling: every ``Ts`` (the plant's control period) by default. ``--sample-period S``, which
  must divide ``Ts`` into whole samples, samples and ticks (``A``) every S instead, with
  ``ceil(substeps S / Ts)`` RK4 steps per sample, so the step is never longer than without it
  (0.5 ms: 5 steps of 0.1 ms); the hello's ``Ts`` is then S and its rig block keeps the
  plant's ``Ts``. The valves' PWM carrier does not depend on the sample period.
* Sensors (``R``): ``x`` + N(0, x_noise), ``p_a``, ``p_b``, ``p_s`` + N(0, p_noise), one draw
  per sample (a repeated ``R`` in one sample returns the same values), seeded by ``--seed``; each
  channel's sample time is the sample's ``t``. ``p_s`` is constant.
* A multiplexed ADC (``--channel-skew FX FA FB FS``, default all 0): channel i is sampled
  ``F_i`` sample periods before the sample's ``t`` (each ``F_i`` in [0, 1) and a whole number of
  RK4 steps), its reading is the state at that instant and its sample time says so. The first
  sample, before any step, reads the initial state at ``t`` = 0.
* Initial state: at rest, both chambers at ``p0``, ``z = 0``, at mid-stroke, except
  ``square-0.5hz`` at x = 6 mm where its reference starts (``--x0`` overrides). An experiment's
  name (``identification``, ``commissioning``: what ``record`` puts in ``{scenario}``) is the
  plain rig at mid-stroke.
* ``T`` (truth): ``v, a, F_friction, F_ext, mdot_a, mdot_b`` at the current sample.

Deliberate differences from a switch-model simulator
-----------------------------------------------------
1. LuGre friction (bristle state, pre-sliding displacement, ``sigma1`` micro-damping) instead of
   a stick/slip switch with a static-friction threshold.
2. Valves open and close along a linear ramp (default 0.5 ms) instead of an instantaneous step;
   a short off-gap is swallowed like a short on-pulse.
3. The ISO 6358 law is linearised for ``r > 0.999`` (a laminar region: the slope of
   ``phi`` is infinite at ``r = 1``, which an explicit integrator cannot resolve).
4. A stiff spring-damper end stop, not an inelastic clamp.
5. Fixed-step RK4 at 0.1 ms (or finer), not an event-driven or adaptive scheme.
6. Optional seal leaks.

The plant file (YAML; every key optional, unknown keys are an error, exit 2)
------------------------------------------------------------------------------
::

    mass: 1.05                    # moving mass [kg]
    friction: {F_C: 60.0, F_S: 90.0, v_s: 0.004, alpha: 2.0, b_v: 3500.0,
               sigma0: 1.0e6, sigma1: 500.0}       # N, N, m/s, -, N s/m, N/m, N s/m
    valves:                       # each of a_in, a_out, b_in, b_out; every key optional
      a_in: {C: 8.373e-9, b: 0.18561, delay_on: 2.0e-3, delay_off: 1.5e-3,
             min_pulse: 1.5e-3, ramp: 5.0e-4}      # m^3/(s Pa), -, s, s, s, s
    leak: {C_ab: 0.0, C_a0: 0.0, C_b0: 0.0, b: 0.5}  # m^3/(s Pa), -
    sensors: {x_noise: 5.0e-6, p_noise: 500.0}        # m, Pa (standard deviations)
    stops: {k: 2.0e7, c: 6000.0}                      # N/m, N s/m
    pwm_update: immediate         # or latched
    pwm_hz: 60.0
    Ts: 0.004                     # control period [s]; the sampling period without
                                  # --sample-period
    substeps: 40                  # RK4 steps per Ts

Scenarios: ``sine-0.5hz-heavy`` adds a 1.136 kg payload; ``disturbance-0.5hz`` applies
``F_ext`` = 30 N from 7.6 s, 80 N from 9.8 s, 0 from 11.9 s; any other name is the plain rig.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import struct
import sys
from typing import Any, BinaryIO

import numpy as np
import yaml

PROTOCOL = "pneutune.rig/1"
VALVE_NAMES: tuple[str, ...] = ("a_in", "a_out", "b_in", "b_out")

# The rig geometry and gas (paper Sec. 2 and 5); not part of the plant file.
A_A = 7.854e-3  # piston area, chamber A [m^2]
A_B = 7.54e-3  # annulus area, chamber B [m^2]
X_MIN = -0.0015  # stroke [m]
X_MAX = 0.0485
V0A = 5.036e-5  # dead volumes [m^3]
V0B = 2.916e-5
P0 = 101325.0  # ambient [Pa abs]
P_S = 6.0e5  # supply [Pa abs]
T0 = 283.15  # gas temperature [K]
N_POLY = 1.2  # polytropic exponent
R_GAS = 287.0  # [J/(kg K)]
RHO0 = 1.185  # ISO 6358 reference density [kg/m^3]
T_REF = 293.15  # ISO 6358 reference temperature [K]
R_LAMINAR = 0.999  # pressure ratio above which the ISO law is linearised

PAYLOAD_HEAVY = 1.136  # [kg], scenario sine-0.5hz-heavy
#: Where the piston rests at t = 0 when not at mid-stroke: the start of the scenario's reference
#: (deploy faults with ``start_position`` more than 1 mm away from x_r(0)).
START_X: dict[str, float] = {"square-0.5hz": 0.006}
#: (from t [s], F_ext [N]) of scenario disturbance-0.5hz.
DISTURBANCE: tuple[tuple[float, float], ...] = ((7.6, 30.0), (9.8, 80.0), (11.9, 0.0))

DEFAULTS: dict[str, Any] = {
    "mass": 1.05,
    "friction": {"F_C": 60.0, "F_S": 90.0, "v_s": 0.004, "alpha": 2.0, "b_v": 3500.0,
                 "sigma0": 1.0e6, "sigma1": 500.0},
    "valves": {name: {"C": 8.373e-9, "b": 0.18561, "delay_on": 2.0e-3, "delay_off": 1.5e-3,
                      "min_pulse": 1.5e-3, "ramp": 5.0e-4} for name in VALVE_NAMES},
    "leak": {"C_ab": 0.0, "C_a0": 0.0, "C_b0": 0.0, "b": 0.5},
    "sensors": {"x_noise": 5.0e-6, "p_noise": 500.0},
    "stops": {"k": 2.0e7, "c": 6000.0},
    "pwm_update": "immediate",
    "pwm_hz": 60.0,
    "Ts": 0.004,
    "substeps": 40,
}

_EPS_T = 1e-12  # time tolerance [s]
_DIVIDES_RTOL = 1e-9  # how closely a sample period must divide Ts


def divides(sample_period: float, Ts: float) -> bool:
    """Whether ``sample_period`` divides ``Ts`` into a whole number of samples.

    Parameters
    ----------
    sample_period : float
        The sample period [s].
    Ts : float
        The control period [s].

    Returns
    -------
    bool
        True when ``sample_period`` is positive, finite, at most ``Ts`` and ``Ts`` is a whole
        multiple of it (to a relative 1e-9).
    """
    if not (math.isfinite(sample_period) and 0.0 < sample_period <= Ts * (1.0 + _DIVIDES_RTOL)):
        return False
    k = round(Ts / sample_period)
    return k >= 1 and abs(k * sample_period - Ts) <= _DIVIDES_RTOL * Ts


def substeps_for(plant: dict[str, Any], sample_period: float | None) -> int:
    """RK4 steps per sample: the plant's ``substeps`` per ``Ts``, scaled to the sample period.

    Parameters
    ----------
    plant : dict
        A complete plant (`load_plant_dict`).
    sample_period : float or None
        The sample period [s]; None samples at the plant's ``Ts``.

    Returns
    -------
    int
        ``substeps`` without a sample period, else ``ceil(substeps sample_period / Ts)`` (at
        least 1), so that the step ``sample_period / n`` is never longer than ``Ts /
        substeps``.
    """
    n = int(plant["substeps"])
    if sample_period is None:
        return n
    ratio = n * float(sample_period) / float(plant["Ts"])
    return max(1, math.ceil(ratio - 1e-9))


def moving_mass(plant: dict[str, Any], scenario: str) -> float:
    """The mass the piston moves in a scenario: the plant's, with the heavy sine's payload.

    Parameters
    ----------
    plant : dict
        A complete plant (`load_plant_dict`).
    scenario : str
        The scenario name; ``sine-0.5hz-heavy`` adds ``PAYLOAD_HEAVY``.

    Returns
    -------
    float
        The moving mass [kg].
    """
    return float(plant["mass"]) + (PAYLOAD_HEAVY if scenario == "sine-0.5hz-heavy" else 0.0)


class PlantError(ValueError):
    """A plant file that cannot be used (unknown key, bad value)."""


def _merge(defaults: dict[str, Any], given: dict[str, Any], where: str) -> dict[str, Any]:
    out = copy.deepcopy(defaults)
    for key, value in given.items():
        if key not in defaults:
            raise PlantError(f"unknown key {where}{key!r} (known: {sorted(defaults)})")
        if isinstance(defaults[key], dict):
            if not isinstance(value, dict):
                raise PlantError(f"{where}{key} must be a mapping")
            out[key] = _merge(defaults[key], value, f"{where}{key}.")
        elif isinstance(defaults[key], str):
            if not isinstance(value, str):
                raise PlantError(f"{where}{key} must be a string")
            out[key] = value
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise PlantError(f"{where}{key} must be a number")
            if not math.isfinite(float(value)):
                raise PlantError(f"{where}{key} must be finite")
            out[key] = type(defaults[key])(value)
    return out


def load_plant_dict(given: dict[str, Any] | None) -> dict[str, Any]:
    """Complete a plant mapping with the defaults and validate it.

    Parameters
    ----------
    given : dict or None
        The plant as read from the YAML file (any subset of the keys of ``DEFAULTS``).

    Returns
    -------
    dict
        Every key of ``DEFAULTS``, the given values overriding the defaults.

    Raises
    ------
    PlantError
        On an unknown key, a value of the wrong type, or a value out of range.
    """
    if given is None:
        given = {}
    if not isinstance(given, dict):
        raise PlantError("the plant file must be a mapping")
    plant = _merge(DEFAULTS, given, "")
    if plant["pwm_update"] not in ("immediate", "latched"):
        raise PlantError("pwm_update must be 'immediate' or 'latched'")
    positive = [("mass", plant["mass"]), ("pwm_hz", plant["pwm_hz"]), ("Ts", plant["Ts"]),
                ("substeps", plant["substeps"])]
    fr = plant["friction"]
    positive += [(f"friction.{k}", fr[k]) for k in ("F_S", "v_s", "alpha", "sigma0")]
    for name in VALVE_NAMES:
        positive.append((f"valves.{name}.C", plant["valves"][name]["C"]))
    for key, value in positive:
        if value <= 0:
            raise PlantError(f"{key} must be positive")
    if not 0 < fr["F_C"] <= fr["F_S"]:
        raise PlantError("friction: need 0 < F_C <= F_S")
    for key in ("b_v", "sigma1"):
        if fr[key] < 0:
            raise PlantError(f"friction.{key} must be >= 0")
    for name in VALVE_NAMES:
        v = plant["valves"][name]
        if not 0 <= v["b"] < R_LAMINAR:
            raise PlantError(f"valves.{name}.b must be in [0, {R_LAMINAR})")
        for key in ("delay_on", "delay_off", "min_pulse", "ramp"):
            if v[key] < 0:
                raise PlantError(f"valves.{name}.{key} must be >= 0")
    lk = plant["leak"]
    if min(lk["C_ab"], lk["C_a0"], lk["C_b0"]) < 0 or not 0 <= lk["b"] < R_LAMINAR:
        raise PlantError("leak: conductances must be >= 0 and b in [0, 0.999)")
    if min(plant["sensors"].values()) < 0 or min(plant["stops"].values()) < 0:
        raise PlantError("sensors and stops must be >= 0")
    return plant


def load_plant(path: str | None) -> dict[str, Any]:
    """Read and complete a plant YAML file.

    Parameters
    ----------
    path : str or None
        The file; None gives the defaults.

    Returns
    -------
    dict
        The complete plant (see `load_plant_dict`).
    """
    if path is None:
        return load_plant_dict({})
    with open(path, encoding="utf-8") as fh:
        return load_plant_dict(yaml.safe_load(fh))


def _iso_coeffs(b: float) -> tuple[float, float]:
    """The flow function's value at ``R_LAMINAR`` and the slope of its linear tail."""
    u = (R_LAMINAR - b) / (1.0 - b)
    phi_l = math.sqrt(1.0 - u * u)
    return phi_l, phi_l / (1.0 - R_LAMINAR)


def iso_flow(p_up: float, p_down: float, k: float, b: float, slope: float) -> float:
    """ISO 6358 mass flow from ``p_up`` to ``p_down`` (negative when it runs backwards).

    Parameters
    ----------
    p_up, p_down : float
        Absolute pressures [Pa] at the nominal upstream and downstream ports.
    k : float
        ``C rho0 sqrt(T_ref / T0)`` times the opening [kg/(s Pa)].
    b : float
        Critical pressure ratio.
    slope : float
        ``phi(R_LAMINAR) / (1 - R_LAMINAR)`` (the linear tail above ``R_LAMINAR``).

    Returns
    -------
    float
        Mass flow [kg/s].
    """
    if p_up >= p_down:
        sign, pu, pd = 1.0, p_up, p_down
    else:
        sign, pu, pd = -1.0, p_down, p_up
    if pu <= 0.0:
        return 0.0
    r = pd / pu
    if r <= b:
        phi = 1.0
    elif r < R_LAMINAR:
        u = (r - b) / (1.0 - b)
        phi = math.sqrt(1.0 - u * u)
    else:
        phi = slope * (1.0 - r)
    return sign * k * pu * phi


class Valve:
    """One on/off valve: its PWM coil signal and the armature (opening) it drives.

    Parameters
    ----------
    prm : dict
        The valve's plant entry (``C, b, delay_on, delay_off, min_pulse, ramp``).
    pwm_hz : float
        PWM frequency [Hz].
    latched : bool
        True for ``pwm_update: latched``.
    """

    def __init__(self, prm: dict[str, float], pwm_hz: float, latched: bool) -> None:
        self.period = 1.0 / pwm_hz
        self.hz = pwm_hz
        self.latched = latched
        self.lag_on = max(prm["delay_on"], prm["min_pulse"])
        self.lag_off = max(prm["delay_off"], prm["min_pulse"])
        self.min_pulse = prm["min_pulse"]
        self.ramp = prm["ramp"]
        self.duty = 0.0  # the duty written last
        self.latched_m = -1  # the period whose duty is latched
        self.latched_d = 0.0
        self.level = False  # coil on
        self.edges: list[tuple[float, bool]] = []  # coil edges (t, new level)
        self.pending: list[tuple[float, bool, float]] = []  # (t_move, target, t_edge)
        self.s = 0.0  # the armature: last switch time, opening then, target
        self.ys = 0.0
        self.target = False

    def _period_duty(self, m: int, t0: float) -> float:
        if not self.latched:
            return self.duty
        if m > self.latched_m and m * self.period >= t0 - 1e-9:
            self.latched_m, self.latched_d = m, self.duty
        return self.latched_d

    def _coil(self, t: float, t0: float) -> bool:
        m = math.floor(t * self.hz + 1e-9)
        d = self._period_duty(m, t0)
        if d >= 1.0:
            return True
        if d <= 0.0:
            return False
        return t - m * self.period < d * self.period - _EPS_T

    def opening(self, t: float) -> float:
        """The opening in [0, 1] at ``t`` (not before the last armature switch).

        Parameters
        ----------
        t : float
            Time [s].

        Returns
        -------
        float
            The valve opening.
        """
        if self.ramp <= 0.0:
            return 1.0 if self.target else 0.0
        if self.target:
            return min(1.0, self.ys + (t - self.s) / self.ramp)
        return max(0.0, self.ys - (t - self.s) / self.ramp)

    def openings(self, t0: float, hh: float, npts: int) -> list[float]:
        """Generate the coil edges of ``[t0, t0 + (npts - 1) hh)`` and the openings on the grid.

        Parameters
        ----------
        t0 : float
            Start of the sample interval [s].
        hh : float
            Grid spacing [s] (half an RK4 step).
        npts : int
            Number of grid points, ``t0`` and the interval end included.

        Returns
        -------
        list of float
            The opening at ``t0 + j hh``, ``j = 0 .. npts - 1``.
        """
        t1 = t0 + (npts - 1) * hh
        # 1. coil edges in [t0, t1)
        cands = [t0]
        m = math.floor(t0 * self.hz + 1e-9)
        while True:
            ts = m * self.period
            if ts >= t1 - 1e-9:
                break
            if ts > t0 + 1e-9:
                cands.append(ts)
            d = self._period_duty(m, t0)
            t_off = ts + d * self.period
            if 0.0 < d < 1.0 and t0 < t_off < t1:
                cands.append(t_off)
            m += 1
        cands.sort()
        for c in cands:
            lvl = self._coil(c, t0)
            if lvl != self.level:
                self.level = lvl
                self.edges.append((c, lvl))
                self.pending.append((c + (self.lag_on if lvl else self.lag_off), lvl, c))
        # 2. armature switches in [t0, t1): a move is valid when the coil held its level for
        # min_pulse after the edge (every edge up to t1 is known by now)
        switches: list[tuple[float, bool]] = []
        keep: list[tuple[float, bool, float]] = []
        for tm, tgt, te in self.pending:
            if tm >= t1 - _EPS_T:
                keep.append((tm, tgt, te))
                continue
            nxt = next((e for e, _ in self.edges if e > te + _EPS_T), None)
            if nxt is None or nxt >= te + self.min_pulse - _EPS_T:
                switches.append((tm, tgt))
        self.pending = keep
        horizon = t0 - 0.2
        if self.edges and self.edges[0][0] < horizon:
            self.edges = [e for e in self.edges if e[0] >= horizon] or self.edges[-1:]
        # 3. openings on the grid
        y0 = self.opening(t0)
        if not switches and y0 == (1.0 if self.target else 0.0):
            return [y0] * npts
        switches.sort()
        out: list[float] = []
        i = 0
        for j in range(npts):
            t = t0 + j * hh
            while i < len(switches) and switches[i][0] <= t:
                ts, tgt = switches[i]
                if tgt != self.target:
                    self.ys = self.opening(max(ts, self.s))
                    self.s = max(ts, self.s)
                    self.target = tgt
                i += 1
            out.append(self.opening(t))
        return out

    def close(self) -> None:
        """Fail-safe: the coil off (the duty 0 from now on)."""
        self.duty = 0.0


class CylinderSim:
    """The simulated rig: state, valves, sensors and the fixed-step integrator.

    Parameters
    ----------
    plant : dict
        A complete plant (`load_plant_dict`).
    scenario : str
        The scenario name (only ``sine-0.5hz-heavy`` and ``disturbance-0.5hz`` change the plant).
    seed : int
        Sensor-noise seed.
    x_start : float, optional
        Initial piston position [m]; default ``START_X`` of the scenario, else mid-stroke.
    sample_period : float, optional
        Sample (and tick) every this many seconds, dividing the plant's ``Ts``; default ``Ts``.
    channel_skew : sequence of 4 floats, optional
        How many sample periods before each sample's time channels x, p_a, p_b, p_s are
        sampled (a multiplexed ADC); each in [0, 1) and a whole number of RK4 steps.

    Raises
    ------
    PlantError
        When ``sample_period`` does not divide the plant's ``Ts``, or a skew is out of range
        or falls between RK4 steps.
    """

    def __init__(self, plant: dict[str, Any], scenario: str, seed: int,
                 x_start: float | None = None, sample_period: float | None = None,
                 channel_skew: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
                 ) -> None:
        self.plant = plant
        self.control_Ts = float(plant["Ts"])
        if sample_period is not None and not divides(float(sample_period), self.control_Ts):
            raise PlantError(f"--sample-period: the sample period {sample_period!r} s must "
                             f"divide the plant's Ts = {self.control_Ts!r} s into whole samples")
        self.Ts = self.control_Ts if sample_period is None else float(sample_period)
        self.nsub = substeps_for(plant, sample_period)
        self.mass = moving_mass(plant, scenario)
        self.disturbance = scenario == "disturbance-0.5hz"
        latched = plant["pwm_update"] == "latched"
        self.valves = [Valve(plant["valves"][n], plant["pwm_hz"], latched) for n in VALVE_NAMES]
        self.k = 0  # sample index
        x0 = START_X.get(scenario, 0.5 * (X_MIN + X_MAX)) if x_start is None else x_start
        self.state = [x0, 0.0, P0, P0, 0.0]  # x, v, p_a, p_b, z
        self.last_y = [0.0, 0.0, 0.0, 0.0]
        self.rng = np.random.default_rng(seed)
        self._noise_k = -1
        self._noise = (0.0, 0.0, 0.0, 0.0)
        self._rhs = self._make_rhs()
        # the RK4 step (counted back from the sample) at which each channel is sampled
        self.skew_steps = []
        for f in channel_skew:
            m = round(f * self.nsub)
            if not 0.0 <= f < 1.0 or abs(m - f * self.nsub) > 1e-9:
                raise PlantError(f"--channel-skew: a channel skew of {f!r} sample periods must "
                                 f"be in [0, 1) and a multiple of 1/{self.nsub} (one RK4 step)")
            self.skew_steps.append(m)
        self._sampled = [self.state[0], self.state[2], self.state[3]]
        self._sample_t = [0.0, 0.0, 0.0, 0.0]

    @property
    def t(self) -> float:
        """Time of the current sample [s]: ``k Ts`` (``Ts`` the sample period)."""
        return self.k * self.Ts

    def f_ext(self, t: float) -> float:
        """``F_ext`` [N] at time ``t`` [s]: the scenario's force steps, opposing positive
        motion."""
        if not self.disturbance:
            return 0.0
        f = 0.0
        for t_from, value in DISTURBANCE:
            if t >= t_from - 1e-9:
                f = value
        return f

    def _make_rhs(self) -> Any:
        """The right-hand side, its constants bound as locals for speed."""
        fr, lk = self.plant["friction"], self.plant["leak"]
        f_c, f_s, v_s, alpha = fr["F_C"], fr["F_S"], fr["v_s"], fr["alpha"]
        b_v, s0, s1 = fr["b_v"], fr["sigma0"], fr["sigma1"]
        inv_m = 1.0 / self.mass
        k_st, c_st = self.plant["stops"]["k"], self.plant["stops"]["c"]
        temp = math.sqrt(T_REF / T0)
        vk = [self.plant["valves"][n]["C"] * RHO0 * temp for n in VALVE_NAMES]
        vb = [self.plant["valves"][n]["b"] for n in VALVE_NAMES]
        vs = [_iso_coeffs(b)[1] for b in vb]
        k_ab, k_a0, k_b0 = (lk[n] * RHO0 * temp for n in ("C_ab", "C_a0", "C_b0"))
        b_l, s_l = lk["b"], _iso_coeffs(lk["b"])[1]
        nrt = N_POLY * R_GAS * T0
        d_f = f_s - f_c
        rod = P0 * (A_A - A_B)
        flow = iso_flow

        def rhs(x: float, v: float, pa: float, pb: float, z: float, y0: float, y1: float,
                y2: float, y3: float, fext: float) -> tuple[float, ...]:
            # mass flows into each chamber
            ma = 0.0
            mb = 0.0
            if y0 > 0.0:
                ma += flow(P_S, pa, y0 * vk[0], vb[0], vs[0])
            if y1 > 0.0:
                ma -= flow(pa, P0, y1 * vk[1], vb[1], vs[1])
            if y2 > 0.0:
                mb += flow(P_S, pb, y2 * vk[2], vb[2], vs[2])
            if y3 > 0.0:
                mb -= flow(pb, P0, y3 * vk[3], vb[3], vs[3])
            if k_ab > 0.0:
                m_ab = flow(pa, pb, k_ab, b_l, s_l)
                ma -= m_ab
                mb += m_ab
            if k_a0 > 0.0:
                ma -= flow(pa, P0, k_a0, b_l, s_l)
            if k_b0 > 0.0:
                mb -= flow(pb, P0, k_b0, b_l, s_l)
            # LuGre friction
            av = v if v >= 0.0 else -v
            g = f_c + d_f * math.exp(-((av / v_s) ** alpha))
            zd = v - s0 * av * z / g
            ff = s0 * z + s1 * zd + b_v * v
            # end stops
            fst = 0.0
            if x < X_MIN:
                fst = k_st * (X_MIN - x) - c_st * v
                if fst < 0.0:
                    fst = 0.0
            elif x > X_MAX:
                fst = -(k_st * (x - X_MAX) + c_st * v)
                if fst > 0.0:
                    fst = 0.0
            acc = (pa * A_A - pb * A_B - rod - ff - fext + fst) * inv_m
            va = V0A + A_A * (x - X_MIN)
            vbv = V0B + A_B * (X_MAX - x)
            pad = (nrt * ma - N_POLY * pa * A_A * v) / va
            pbd = (nrt * mb + N_POLY * pb * A_B * v) / vbv
            return v, acc, pad, pbd, zd, ff, ma, mb

        return rhs

    def write(self, duties: tuple[float, float, float, float]) -> None:
        """Command the duties from now on.

        Parameters
        ----------
        duties : tuple of 4 floats
            a_in, a_out, b_in, b_out in [0, 1] (checked by the caller).
        """
        for valve, d in zip(self.valves, duties, strict=True):
            valve.duty = float(d)

    def close(self) -> None:
        """Fail-safe: every valve's duty 0."""
        for valve in self.valves:
            valve.close()

    def advance(self) -> float:
        """Integrate one sample period.

        Returns
        -------
        float
            The new sample time [s].
        """
        n = self.nsub
        t0 = self.t
        h = self.Ts / n
        hh = 0.5 * h
        ys = [v.openings(t0, hh, 2 * n + 1) for v in self.valves]
        o0, o1, o2, o3 = ys
        rhs = self._rhs
        x, v, pa, pb, z = self.state
        fe = self.f_ext
        skew = self.skew_steps
        sampled = self._sampled
        for c, m in enumerate(skew[:3]):
            if m == n:
                sampled[c] = (x, pa, pb)[c]
        for i in range(n):
            j = 2 * i
            ta = t0 + i * h
            fa, fm, fb = fe(ta), fe(ta + hh), fe(ta + h)
            k1 = rhs(x, v, pa, pb, z, o0[j], o1[j], o2[j], o3[j], fa)
            j1 = j + 1
            k2 = rhs(x + hh * k1[0], v + hh * k1[1], pa + hh * k1[2], pb + hh * k1[3],
                     z + hh * k1[4], o0[j1], o1[j1], o2[j1], o3[j1], fm)
            k3 = rhs(x + hh * k2[0], v + hh * k2[1], pa + hh * k2[2], pb + hh * k2[3],
                     z + hh * k2[4], o0[j1], o1[j1], o2[j1], o3[j1], fm)
            j2 = j + 2
            k4 = rhs(x + h * k3[0], v + h * k3[1], pa + h * k3[2], pb + h * k3[3],
                     z + h * k3[4], o0[j2], o1[j2], o2[j2], o3[j2], fb)
            w = h / 6.0
            x += w * (k1[0] + 2.0 * (k2[0] + k3[0]) + k4[0])
            v += w * (k1[1] + 2.0 * (k2[1] + k3[1]) + k4[1])
            pa += w * (k1[2] + 2.0 * (k2[2] + k3[2]) + k4[2])
            pb += w * (k1[3] + 2.0 * (k2[3] + k3[3]) + k4[3])
            z += w * (k1[4] + 2.0 * (k2[4] + k3[4]) + k4[4])
            for c, m in enumerate(skew[:3]):
                if m == n - 1 - i:
                    sampled[c] = (x, pa, pb)[c]
        if not all(map(math.isfinite, (x, v, pa, pb, z))):
            raise FloatingPointError("the integration diverged")
        self.state = [x, v, pa, pb, z]
        self.last_y = [o0[-1], o1[-1], o2[-1], o3[-1]]
        self.k += 1
        self._sample_t = [self.t - m * h for m in skew]
        return self.t

    def read(self) -> tuple[float, ...]:
        """The ``R`` reply: t, x, p_a, p_b, p_s and the four channels' sample times.

        Returns
        -------
        tuple of 9 floats
        """
        if self._noise_k != self.k:
            sn = self.plant["sensors"]
            scale = np.array([sn["x_noise"], sn["p_noise"], sn["p_noise"], sn["p_noise"]])
            self._noise = tuple(float(e) for e in self.rng.standard_normal(4) * scale)
            self._noise_k = self.k
        t = self.t
        x, pa, pb = self._sampled
        nx, na, nb, ns = self._noise
        return (t, x + nx, pa + na, pb + nb, P_S + ns, *self._sample_t)

    def truth(self) -> tuple[float, ...]:
        """The ``T`` reply at the current sample: v, a, F_friction, F_ext, mdot_a, mdot_b.

        Returns
        -------
        tuple of 6 floats
        """
        fext = self.f_ext(self.t)
        x, v, pa, pb, z = self.state
        d = self._rhs(x, v, pa, pb, z, *self.last_y, fext)
        return (v, d[1], d[5], fext, d[6], d[7])

    def hello(self) -> dict[str, Any]:
        """The hello: protocol, the sample period ``Ts`` and the rig block (whose ``Ts`` is the
        plant's control period).

        Returns
        -------
        dict
        """
        rig = {"A_a": A_A, "A_b": A_B, "x_min": X_MIN, "x_max": X_MAX, "V0a": V0A, "V0b": V0B,
               "p0": P0, "p_s": P_S, "T0": T0, "n": N_POLY, "R": R_GAS, "Ts": self.control_Ts,
               "pwm_hz": float(self.plant["pwm_hz"]), "pwm_update": self.plant["pwm_update"]}
        return {"protocol": PROTOCOL, "Ts": self.Ts, "rig": rig}


def _read_exact(src: BinaryIO, n: int) -> bytes | None:
    data = src.read(n)
    if data is None or len(data) < n:
        return None
    return data


def serve(sim: CylinderSim, src: BinaryIO, dst: BinaryIO) -> int:
    """Answer ``pneutune.rig/1`` requests until the end of input, ``C`` or an error.

    Parameters
    ----------
    sim : CylinderSim
        The rig.
    src, dst : binary file objects
        Requests in, replies out.

    Returns
    -------
    int
        The exit status: 0 at the end of input and after ``C``, 1 after an ``E`` reply.
    """

    def ok(body: bytes = b"") -> None:
        dst.write(b"K" + body)
        dst.flush()

    def error(message: str) -> int:
        sim.close()
        raw = message.encode("utf-8")[:4096]
        dst.write(b"E" + struct.pack("<I", len(raw)) + raw)
        dst.flush()
        print(f"other_sim_driver: {message}", file=sys.stderr)
        return 1

    while True:
        op = src.read(1)
        if not op:
            sim.close()
            return 0
        if op == b"H":
            raw = json.dumps(sim.hello()).encode("utf-8")
            ok(struct.pack("<I", len(raw)) + raw)
        elif op == b"R":
            ok(struct.pack("<9d", *sim.read()))
        elif op == b"W":
            data = _read_exact(src, 32)
            if data is None:
                sim.close()
                return 0
            duties = struct.unpack("<4d", data)
            if not all(0.0 <= d <= 1.0 for d in duties):  # NaN fails too
                return error(f"duties must be in [0, 1], got {list(duties)}")
            sim.write(duties)
            ok()
        elif op == b"A":
            try:
                t = sim.advance()
            except FloatingPointError as exc:
                return error(str(exc))
            ok(struct.pack("<d", t))
        elif op == b"T":
            ok(struct.pack("<6d", *sim.truth()))
        elif op == b"C":
            sim.close()
            ok()
            return 0
        else:
            return error(f"unknown request {op!r}")


def main(argv: list[str] | None = None) -> int:
    """Command line; see the module docstring.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status.
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--plant", default=None, help="plant YAML (default: the built-in defaults)")
    ap.add_argument("--scenario", default="sine-0.5hz")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--x0", type=float, default=None,
                    help="initial piston position [m] (default: the scenario's, see START_X)")
    ap.add_argument("--sample-period", type=float, default=None, metavar="S",
                    help="sample and tick every S seconds, dividing the plant's Ts (default Ts); "
                         "the hello's Ts is S, its rig block keeps the plant's Ts")
    ap.add_argument("--channel-skew", type=float, nargs=4, default=(0.0, 0.0, 0.0, 0.0),
                    metavar=("FX", "FA", "FB", "FS"),
                    help="a multiplexed ADC: sample x, p_a, p_b, p_s this many sample periods "
                         "before each sample's time, and say so in the sample times")
    ap.add_argument("--print-plant", action="store_true",
                    help="print the complete plant and the scenario's moving mass as JSON "
                         "and exit, serving nothing")
    args = ap.parse_args(argv)
    if args.x0 is not None and not X_MIN <= args.x0 <= X_MAX:
        print(f"other_sim_driver: --x0 must be in [{X_MIN}, {X_MAX}]", file=sys.stderr)
        return 2
    try:
        plant = load_plant(args.plant)
    except (OSError, yaml.YAMLError, PlantError) as exc:
        print(f"other_sim_driver: bad plant {args.plant}: {exc}", file=sys.stderr)
        return 2
    if args.print_plant:
        print(json.dumps({"plant": plant, "moving_mass": moving_mass(plant, args.scenario)}))
        return 0
    try:
        sim = CylinderSim(plant, args.scenario, args.seed, args.x0, args.sample_period,
                          tuple(args.channel_skew))
    except PlantError as exc:
        print(f"other_sim_driver: {exc}", file=sys.stderr)
        return 2
    try:
        return serve(sim, sys.stdin.buffer, sys.stdout.buffer)
    except BrokenPipeError:
        sim.close()  # the client is gone
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
