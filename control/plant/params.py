"""The plant's frozen parameters as the flat float64 vector that the compiled code reads.

:func:`pack_plant` turns a validated :class:`~pneutune.control.contracts.plant.PlantConfig` into a
:class:`PlantParams` record. The index constants below are module-level ints, which numba treats
as compile-time constants. Per-valve quantities occupy four consecutive slots in the order
a_in, a_out, b_in, b_out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pneutune.control.constants import T_REF
from pneutune.control.contracts.plant import PlantConfig, load_plant
from pneutune.control.errors import ConfigError
from pneutune.control.physics.friction import (
    stribeck_flat_ratio,
    stribeck_peak,
    stribeck_stiffness,
)

P_AA, P_AB, P_XMIN, P_XMAX, P_V0A, P_V0B, P_P0, P_T0, P_N, P_R = range(10)
P_TS, P_TPWM, P_LATCHED, P_M, P_FS, P_FC, P_VS, P_ALPHA, P_BV = range(10, 19)
P_C = 19  # 4 slots: sonic conductance [m^3/(s Pa)]
P_B = 23  # 4 slots: critical pressure ratio
P_DON = 27  # 4 slots: opening delay [s]
P_DOFF = 31  # 4 slots: closing delay [s]
P_MINP = 35  # 4 slots: minimum pulse [s]
P_LEAKC, P_FN, P_DA, P_DB, P_DT, P_XNOISE, P_XSTEP, P_PNOISE = range(39, 47)
P_DTMIN = 47  # the step the steepest sliding friction needs, <= P_DT (set_step_limits) [s]
P_RPEAK = 48  # where the Stribeck slope peaks, |v|/v_s (physics.friction.stribeck_peak) [-]
P_UFREE = 49  # above this speed only b_v may shorten the step (set_step_limits) [m/s]
# Real-rig effects (contract 2's valves.*.tau_*, lines, heat, friction.sigma*, sensors lags,
# io, supply); each is off at 0 and then leaves the paper's model untouched.
P_TAUON = 50  # 4 slots: armature opening time constant [s]
P_TAUOFF = 54  # 4 slots: armature closing time constant [s]
P_VLAG = 58  # 1.0 when any valve has a time constant (the open fractions are lagged)
P_LINEC = 59  # 2 slots (A, B): line conductance [m^3/(s Pa)], 0 = no restriction
P_LINEB = 61  # 2 slots: line critical pressure ratio [-]
P_HEAT, P_HEATH, P_GAMMA, P_PERIM = range(63, 67)  # energy eq. on, h, gamma, bore perimeter
P_SIGMA0, P_SIGMA1, P_DTLUGRE = range(67, 70)  # LuGre; the step its bristles allow [s]
P_XLAG, P_PLAG, P_PSTEP, P_IODELAY = range(70, 74)
P_SUPC, P_SUPB, P_SUPVOL = range(74, 77)  # supply line (0 conductance: a stiff supply)
P_GENERAL = 77  # 1.0 when the flows need more than Eq. (7) per valve (lag, line, heat, supply)
P_EXTSTATE = 78  # 1.0 when states beyond the paper's are integrated (heat, LuGre, supply)
P_STEPK = 79  # the step rule's factor: h * stiffness / M at most this (STEP_STIFFNESS) [-]
P_RFLAT = 80  # from this |v|/v_s on Eq. (2)'s level is F_C (physics.friction.stribeck_flat_ratio)
P_KT = 81  # Eq. (7)'s temperature factor sqrt(T_ref / T0) of the chambers' gas [-]
P_PAT = 82  # 1.0: the chamber transmitters read the valves' junction (sensors.p_at: valves)
N_PARAMS = 83
#: RK4 keeps ``h * stiffness / M`` at most this while sliding (its stability limit on the real
#: axis is 2.79; at 2 the viscous mode's amplification per step is 0.33, no overshoot).
#: :func:`pack_plant` copies it into ``P_STEPK``, which the compiled step rule reads, so that
#: ``benchmarks/step_rule.py`` can compare factors in one process (docs/integration.md, "The
#: step rule's factor": 2 is as accurate as the earlier 1.4 against a 10 us step).
STEP_STIFFNESS: float = 2.0
#: The shortest step :func:`load_sim_plant` lets a plant file need [s]: ten million steps per
#: simulated second, a few seconds of computing each (a gram of moving mass on a steep Stribeck
#: law needs 0.5 us; a microgram against the paper's b_v, 0.6 ns).
MIN_SIM_STEP: float = 1.0e-7


@dataclass(frozen=True, slots=True)
class PlantParams:
    """Frozen numeric form of a plant.yaml, for the compiled simulator.

    Attributes
    ----------
    vec : numpy.ndarray
        float64 vector of length :data:`N_PARAMS` (read-only), indexed by the ``P_*`` constants.
    force_steps : numpy.ndarray
        float64 array of shape (K, 2): [[t_s, F_N], ...] with strictly increasing t (K may be 0).
    p_s : float
        Nominal supply pressure [Pa abs].
    seed : int
        Seed of the sensor noise.
    config : PlantConfig
        The validated configuration it came from.
    """

    vec: np.ndarray
    force_steps: np.ndarray
    p_s: float
    seed: int
    config: PlantConfig


def set_step_limits(v: np.ndarray) -> None:
    """Fill ``P_RPEAK``, ``P_DTMIN``, ``P_UFREE`` and ``P_RFLAT`` of a parameter vector from its
    friction, mass and ``P_DT`` (call again after changing any of them).

    ``P_DTMIN = min(P_DT, P_STEPK M / k_max)``, k_max the largest |dF_f/dv| at any speed
    (:func:`~pneutune.control.physics.friction.stribeck_stiffness` at u = 0): the shortest step
    the integrator may take while sliding. When it equals ``P_DT`` the friction never shortens
    a step. ``P_UFREE``: the speed above which the Stribeck branch needs no shorter step than
    ``min(P_DT, P_STEPK M / b_v)`` (0 when it never does), so that a fast step costs no
    evaluation of the slope. ``P_STEPK`` must be set (:func:`pack_plant` sets it).
    """
    v[P_RPEAK] = stribeck_peak(v[P_ALPHA])
    v[P_RFLAT] = stribeck_flat_ratio(v[P_FS], v[P_FC], v[P_ALPHA])

    def k(u: float) -> float:
        return stribeck_stiffness(u, v[P_FS], v[P_FC], v[P_VS], v[P_ALPHA], v[P_BV], v[P_RPEAK])

    # above P_UFREE the step needs no more than min(P_DT, P_STEPK M / b_v): the Stribeck branch
    # is no steeper there than what P_DT or the viscous mode allows anyway
    k_flat = max(v[P_STEPK] * v[P_M] / v[P_DT], v[P_BV])
    v[P_DTMIN] = min(v[P_DT], v[P_STEPK] * v[P_M] / k(0.0))
    if k(0.0) <= k_flat:
        v[P_UFREE] = 0.0
    else:  # k(u) falls with u above the peak: bisect for k(u) = k_flat
        lo = v[P_RPEAK] * v[P_VS]
        hi = 2.0 * lo + v[P_VS]
        while k(hi) > k_flat:
            hi *= 2.0
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if k(mid) > k_flat:
                lo = mid
            else:
                hi = mid
        v[P_UFREE] = hi


def gas_spring_step(cfg: PlantConfig, factor: float = STEP_STIFFNESS) -> float:
    """The longest RK4 step the chambers' gas spring allows the moving mass [s].

    The air in the chambers is a spring on the piston: moving it by dx changes p_i by
    ``n p_i A_i dx / V_i``, so its stiffness is at most ``n_eff p_s (A_a^2/V_a0 + A_b^2/V_b0)``
    (both chambers at supply, each at its dead volume, line volumes included; ``n_eff`` is
    ``heat.gamma`` with the energy equation, ``rig.n`` without). RK4 is stable on an undamped
    mode while ``h omega`` stays below 2.83; this keeps it at ``factor`` (the step rule's 2).
    For the paper's geometry the bound passes ``sim.dt`` only below about 0.09 kg, so it leaves
    every plant of cylinder-like mass as it was. Without it a plant of a few grams diverged.

    Parameters
    ----------
    cfg : PlantConfig
        The plant.
    factor : float
        ``h omega`` at most this [-].

    Returns
    -------
    float
        The step [s].
    """
    r = cfg.rig
    n_eff = cfg.heat.gamma if cfg.heat.h is not None else r.n
    v0a = r.V0a + cfg.lines.a.volume
    v0b = r.V0b + cfg.lines.b.volume
    stiffness = n_eff * r.p_s * (r.A_a**2 / v0a + r.A_b**2 / v0b)
    return float(factor * np.sqrt(cfg.total_mass / stiffness))


def _pack_effects(cfg: PlantConfig, v: np.ndarray) -> None:
    """Fill the real-rig effect slots; every one left at 0 keeps the paper's model exactly.

    The line's transport delay adds to the switching delays of its chamber's valves and its
    volume to the chamber's dead volume (a zero adds nothing, bit for bit).
    """
    for i, valve in enumerate(cfg.valves.ordered()):
        v[P_TAUON + i], v[P_TAUOFF + i] = valve.tau_open, valve.tau_close
        line = cfg.lines.a if i < 2 else cfg.lines.b
        v[P_DON + i] += line.delay
        v[P_DOFF + i] += line.delay
    v[P_VLAG] = 1.0 if np.any(v[P_TAUON:P_TAUON + 8] > 0.0) else 0.0
    v[P_V0A] += cfg.lines.a.volume
    v[P_V0B] += cfg.lines.b.volume
    for j, line in enumerate((cfg.lines.a, cfg.lines.b)):
        v[P_LINEC + j] = 0.0 if line.C is None else line.C
        v[P_LINEB + j] = line.b
    if cfg.heat.h is not None:
        v[P_HEAT], v[P_HEATH], v[P_GAMMA] = 1.0, cfg.heat.h, cfg.heat.gamma
    v[P_PERIM] = 2.0 * np.sqrt(np.pi * cfg.rig.A_a)  # pi times the bore
    f = cfg.friction
    v[P_SIGMA0], v[P_SIGMA1] = f.sigma0, f.sigma1
    if f.sigma0 > 0.0:
        # the bristles' spring-mass mode (omega h <= 0.5) and their damping with the viscous
        # term (h (sigma1 + b_v) / M <= P_STEPK) bound the step
        v[P_DTLUGRE] = min(v[P_DT], 0.5 * np.sqrt(v[P_M] / f.sigma0),
                           v[P_STEPK] * v[P_M] / max(f.sigma1 + f.b_v, 1.0e-12))
    s = cfg.sensors
    v[P_XLAG], v[P_PLAG], v[P_PSTEP] = s.x_lag, s.p_lag, s.p_step
    v[P_PAT] = 1.0 if s.p_at == "valves" else 0.0
    v[P_IODELAY] = cfg.io.delay
    if cfg.supply.C is not None:
        v[P_SUPC], v[P_SUPB], v[P_SUPVOL] = cfg.supply.C, cfg.supply.b, cfg.supply.volume
    general = v[P_VLAG] + v[P_LINEC] + v[P_LINEC + 1] + v[P_HEAT] + v[P_SUPC] > 0.0
    v[P_GENERAL] = 1.0 if general else 0.0
    v[P_EXTSTATE] = 1.0 if v[P_HEAT] + v[P_SIGMA0] + v[P_SUPC] > 0.0 else 0.0


def pack_plant(cfg: PlantConfig) -> PlantParams:
    """Pack a validated plant configuration into a :class:`PlantParams`.

    Parameters
    ----------
    cfg : PlantConfig
        The plant (already validated).

    Returns
    -------
    PlantParams
    """
    v = np.zeros(N_PARAMS)
    r = cfg.rig
    v[P_AA], v[P_AB], v[P_XMIN], v[P_XMAX] = r.A_a, r.A_b, r.x_min, r.x_max
    v[P_V0A], v[P_V0B], v[P_P0], v[P_T0], v[P_N], v[P_R] = r.V0a, r.V0b, r.p0, r.T0, r.n, r.R
    v[P_KT] = math.sqrt(T_REF / r.T0)  # the same bits as computing it at every flow
    v[P_TS], v[P_TPWM] = r.Ts, 1.0 / r.pwm_hz
    v[P_LATCHED] = 1.0 if r.pwm_update == "latched" else 0.0
    v[P_M] = cfg.total_mass
    f = cfg.friction
    v[P_FS], v[P_FC], v[P_VS], v[P_ALPHA], v[P_BV] = f.F_S, f.F_C, f.v_s, f.alpha, f.b_v
    for i, valve in enumerate(cfg.valves.ordered()):
        v[P_C + i], v[P_B + i] = valve.C, valve.b
        v[P_DON + i], v[P_DOFF + i] = valve.delay_on, valve.delay_off
        v[P_MINP + i] = valve.min_pulse
    v[P_LEAKC] = cfg.leak.C
    d = cfg.disturbance
    v[P_FN], v[P_DA], v[P_DB] = d.F_n, d.D_a, d.D_b
    v[P_STEPK] = STEP_STIFFNESS  # read now, not at import: a benchmark may compare factors
    # the longest step: sim.dt, or less on a plant so light that its gas spring needs it;
    # sliding friction may shorten it further (dynamics)
    v[P_DT] = min(cfg.sim.dt, gas_spring_step(cfg, v[P_STEPK]))
    set_step_limits(v)
    s = cfg.sensors
    v[P_XNOISE], v[P_XSTEP], v[P_PNOISE] = s.x_noise, s.x_step, s.p_noise
    _pack_effects(cfg, v)
    v.setflags(write=False)
    steps = np.array(d.force_steps, dtype=np.float64).reshape(-1, 2)
    steps.setflags(write=False)
    return PlantParams(vec=v, force_steps=steps, p_s=r.p_s, seed=cfg.sim.seed, config=cfg)


def step_limits(pp: PlantParams) -> dict[str, float]:
    """The longest step each of the plant's fast modes allows the integrator [s].

    Keys: ``sim.dt`` (the file's step, or the gas spring's when shorter: :func:`gas_spring_step`),
    ``friction`` (the steepest sliding friction, viscous or Stribeck, ``P_DTMIN`` and
    ``P_STEPK M / b_v``) and ``friction.sigma0`` (the LuGre bristles, when on).
    """
    v = pp.vec
    out = {"sim.dt": float(v[P_DT]), "friction": float(v[P_DTMIN])}
    if v[P_BV] > 0.0:
        out["friction"] = min(out["friction"], float(v[P_STEPK] * v[P_M] / v[P_BV]))
    if v[P_SIGMA0] > 0.0:
        out["friction.sigma0"] = float(v[P_DTLUGRE])
    return out


def load_sim_plant(path: str | None) -> PlantConfig:
    """Load a plant.yaml for the simulator, refusing one the integrator cannot run.

    A plant whose fastest mode (a moving mass of micrograms against the friction's slope,
    its gas spring or LuGre bristles) needs steps below :data:`MIN_SIM_STEP` would take
    minutes to hours per simulated second (and a compiled run does not see Ctrl-C): that is a
    unit mistake, not a cylinder.

    Parameters
    ----------
    path : str or None
        The plant.yaml; None gives the paper's rig.

    Returns
    -------
    PlantConfig

    Raises
    ------
    ConfigError
        Bad file (see :func:`~pneutune.control.contracts.plant.load_plant`), or a plant whose
        shortest step is below :data:`MIN_SIM_STEP`, naming the mass and the mode that needs it.
    """
    cfg = load_plant(path)
    limits = step_limits(pack_plant(cfg))
    key = min(limits, key=lambda k: limits[k])
    if limits[key] < MIN_SIM_STEP:
        what = {"sim.dt": "the gas spring of its chambers",
                "friction": f"its sliding friction (b_v {cfg.friction.b_v:g} N s/m and the "
                            "Stribeck slope)",
                "friction.sigma0": f"the LuGre bristles (sigma0 {cfg.friction.sigma0:g} N/m)"}[key]
        raise ConfigError(
            str(path) if path is not None else "<defaults>", "mass",
            f"a moving mass of {cfg.total_mass:g} kg against {what} needs integration steps "
            f"of {limits[key]:.2g} s ({1.0 / limits[key]:.1e} steps per simulated second; the "
            f"simulator runs plants down to {MIN_SIM_STEP:g} s); a cylinder's moving parts "
            "weigh grams to tonnes: check that mass and payload are in kg")
    return cfg


# ---------------------------------------------------------------------------------------------
# Plant state vector (float64). Continuous states, the stuck flag, the clock and, per valve, the
# PWM/valve switching state (see pneutune.control.plant.valves).
S_X, S_V, S_PA, S_PB, S_STUCK, S_T = range(6)
S_SIG = 6  # 4 slots: command signal of the PWM comparator (0/1)
S_OPEN = 10  # 4 slots: physical valve state (0 closed / 1 open)
S_RISE = 14  # 4 slots: time of the last rising edge of the command signal [s]
S_DUTY = 18  # 4 slots: duty the comparator uses now (latched mode: from the period start)
S_CMD = 22  # 4 slots: duty last commanded by the controller
S_NPEND = 26  # 4 slots: number of pending valve transitions
PEND_MAX = 16  # pending transitions per valve (sorted by time)
S_PEND_T = 30  # 4 * PEND_MAX slots: transition times [s]
S_PEND_V = S_PEND_T + 4 * PEND_MAX  # 4 * PEND_MAX slots: target state (0/1)
# Real-rig effects' states (untouched while the effect is off)
S_Y0 = S_PEND_V + 4 * PEND_MAX  # 4 slots: lagged open fraction at the last valve transition
S_TY = S_Y0 + 4  # 4 slots: time of that transition [s]
S_TA, S_TB = S_TY + 4, S_TY + 5  # chamber gas temperatures [K] (heat transfer)
S_Z = S_TY + 6  # LuGre bristle deflection [m]
S_PSUP = S_TY + 7  # supply manifold pressure [Pa abs] (0: not yet set, takes the supply)
S_XF, S_PAF, S_PBF, S_PSF = range(S_TY + 8, S_TY + 12)  # lagged sensor readings
S_PJ = S_TY + 12  # 2 slots: the lines' junction pressures last found (0: none yet) [Pa abs]
S_IO_N = S_TY + 14  # number of duty writes waiting for the IO delay
IO_MAX = 128  # writes that may wait: io.delay <= 10 ms over rig.Ts >= 0.1 ms, one per sample
S_IO = S_IO_N + 1  # IO_MAX x 5 slots: [time it acts, 4 duties]
N_STATE = S_IO + 5 * IO_MAX
