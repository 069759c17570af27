"""From a run log to model.yaml: the steps of ``identify`` in order.

1. :func:`~pneutune.identify.dataset.load_dataset`: data checks, aligned arrays.
2. :class:`~pneutune.identify.valves.ValveIdentifier`: C, b per valve, leak, D_a, D_b, the PWM
   curves (QP).
3. :class:`~pneutune.identify.motion.FrictionIdentifier`: Stribeck friction, F_n, the smooth
   model; :class:`~pneutune.identify.motion.MassIdentifier`: the mass and its interval.
4. :func:`~pneutune.identify.bounds.theta_bounds`: θ nominal and bounds.
5. :func:`~pneutune.identify.validation.validate`: the model simulated on the held-out part.
6. :func:`~pneutune.identify.crosscheck.cross_check`: every range end (and the corners) that
   ``tune`` would sample must reproduce the held-out part nearly as well as the best fit; the
   ends the log rules out are moved in.

Everything is fitted on the first ``1 - holdout`` of every 10 s of the log; the rest of each
10 s is for validation (:meth:`~pneutune.identify.dataset.Dataset.split`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from pneutune.control.constants import MODEL_SCHEMA, VALVES, WEAK_B_SPAN
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError, LogError
from pneutune.control.sim.scenarios import SCENARIOS

from .bounds import ThetaBounds, theta_bounds
from .crosscheck import CrossCheck, cross_check, narrowed_model
from .dataset import Dataset, load_dataset
from .mass import MIN_SAMPLES_PER_PWM, LagMassIdentifier, samples_per_pwm
from .mass_prior import mass_prior
from .motion import FrictionIdentifier, MassIdentifier
from .stiction import force_noise_std, position_noise_std, stiction_bounds
from .validation import Validation, validate
from .valves import ValveIdentifier

#: An interval wider than this ratio (hi / lo) means "not identifiable".
MASS_IDENTIFIABLE_RATIO = 1.5


#: Structural half-width added to the integrated mass estimate's bootstrap interval, as a
#: multiple of b_v Ts [kg]. The estimate runs high by 2-15 %, growing with b_v Ts / M, which the
#: bootstrap does not see. Calibrated on five simulated rigs (200 mm stroke, 50 mm bore, b_v
#: 200-800 N s/m, M 1-4 kg): bias +4 % to +15 %, and 0.15 b_v Ts covers each with room
#: (docs/identification.md).
MASS_BIAS_MARGIN = 0.15


def mass_sampling_limit(b_v: float, Ts: float) -> float:
    """Smallest mass whose mechanical pole b_v/M lies below the Nyquist frequency π/Ts [kg].

    Parameters
    ----------
    b_v : float
        Viscous coefficient [N s/m].
    Ts : float
        Sampling period [s].

    Returns
    -------
    float
        ``b_v Ts / π`` [kg].

    Below it the piston follows the force within one sample and the mass shows only as a lag
    M/b_v shorter than Ts/π. The integrated motion equation then carries a structural bias
    (the force path inside each sample is unknown) that its bootstrap does not see: on a
    noise-free identification run of the default plant (M = 1.05 kg) with 10 s of extra
    position steps it returned [1.84, 2.10] kg. Such an interval is not reported
    (docs/identifiability.md).
    """
    return b_v * Ts / np.pi


@dataclass
class IdentifyResult:
    """Everything ``identify`` learned, for model.yaml and the report."""

    data: Dataset
    valves: ValveIdentifier
    friction: FrictionIdentifier
    mass: float
    mass_range: tuple[float, float]
    mass_basis: str
    mass_estimate: MassIdentifier | LagMassIdentifier | None
    theta: ThetaBounds
    validation: Validation
    model: ModelConfig
    plant: PlantConfig
    notes: list[str] = field(default_factory=list)
    #: the log at its own sampling period (``data`` holds the control instants the fits use)
    log: Dataset | None = None
    #: the cross-check of the ranges against the held-out log (None when skipped)
    crosscheck: CrossCheck | None = None


def _lag_mass(log: Dataset, friction: FrictionIdentifier, fit: np.ndarray, seed: int,
              notes: list[str]) -> LagMassIdentifier | None:
    """The lag estimate of the mass when its interval is narrow enough, else None (noted)."""
    try:
        est = LagMassIdentifier(friction, seed=seed).fit(log, fit)
    except (LogError, ValueError, np.linalg.LinAlgError) as exc:
        notes.append(f"mass: the lag of the motion behind the pressure force gives no estimate "
                     f"({exc})")
        return None
    lo, hi = est.ci_
    if lo > 0.0 and hi / lo <= MASS_IDENTIFIABLE_RATIO:
        return est
    notes.append(f"mass: the lag of the motion behind the pressure force gives {est.M_:.3g} kg "
                 f"in [{lo:.3g}, {hi:.3g}] kg, wider than a factor {MASS_IDENTIFIABLE_RATIO:g} "
                 f"(on every other sample: {est.M_half_:.3g} kg)")
    return None


def _mass(data: Dataset, friction: FrictionIdentifier, fit: np.ndarray,
          mass: float | None, mass_tol: float, seed: int, notes: list[str],
          log: Dataset | None = None, log_fit: np.ndarray | None = None,
          ) -> tuple[float, tuple[float, float], str, MassIdentifier | LagMassIdentifier | None]:
    if mass is not None:
        rng = (mass * (1.0 - mass_tol), mass * (1.0 + mass_tol))
        return mass, rng, f"given by the user (±{mass_tol:.0%})", None
    if log is not None and samples_per_pwm(log) >= MIN_SAMPLES_PER_PWM:
        lag = _lag_mass(log, friction, log_fit, seed, notes)
        if lag is not None:
            return lag.M_, lag.ci_, (
                f"99 % bootstrap interval of tau b_v, tau the lag of the motion behind the "
                f"pressure force ({log.Ts * 1e3:g} ms samples), widened by "
                f"{lag.discretisation_:.3g} kg, the change on every other sample"), lag
    prior, prior_nominal, prior_basis = mass_prior(data.rig, data.mass_hint)
    try:
        est = MassIdentifier(friction, seed=seed).fit(data, fit)
    except (LogError, ValueError, np.linalg.LinAlgError) as exc:
        notes.append(f"mass: not estimated ({exc}); {prior_basis}: [{prior[0]:.3g}, "
                     f"{prior[1]:.3g}] kg, narrowed by the cross-check")
        return prior_nominal, prior, prior_basis, None
    margin = MASS_BIAS_MARGIN * friction.b_v_ * data.Ts
    lo, hi = max(est.ci_[0] - margin, 0.0), est.ci_[1] + margin
    limit = mass_sampling_limit(friction.b_v_, data.Ts)
    if lo > limit and hi / lo <= MASS_IDENTIFIABLE_RATIO:
        both = (max(lo, prior[0]), min(hi, prior[1]))
        basis = ("99 % bootstrap interval of the integrated motion equation, widened by "
                 f"{margin:.3g} kg for its bias (0.15 b_v Ts)")
        if both[0] < both[1]:
            if both != (lo, hi):
                basis += f", intersected with the {prior_basis}"
            return float(np.clip(est.M_, *both)), both, basis, est
        notes.append(f"mass: the estimate's interval [{lo:.3g}, {hi:.3g}] kg lies outside the "
                     f"{prior_basis} [{prior[0]:.3g}, {prior[1]:.3g}] kg; the data win")
        return est.M_, (lo, hi), basis, est
    if lo <= limit:
        why = (f"With a viscous coefficient of {friction.b_v_:.0f} N s/m the mechanical pole "
               f"b_v/M lies above the Nyquist frequency of the {data.Ts * 1e3:g} ms sampling "
               f"for any mass below {limit:.3g} kg, where this estimate is biased "
               f"(docs/identifiability.md); an identification run logged every 0.5 ms "
               f"resolves the mass (simulate --sample-period).")
    else:
        why = f"It is wider than a factor {MASS_IDENTIFIABLE_RATIO:g}."
    notes.append(
        f"mass: not identifiable from this log: the 99 % interval of the estimate is "
        f"[{lo:.3g}, {hi:.3g}] kg. {why} θ1 uses the {prior_basis}: [{prior[0]:.3g}, "
        f"{prior[1]:.3g}] kg (nominal {prior_nominal:.3g} kg), narrowed by the cross-check "
        f"where the log contradicts its ends; give --mass KG (datasheet plus weighed payload) "
        f"or a rig.mass hint in the log to narrow it")
    return prior_nominal, prior, prior_basis, est


def check_arguments(holdout: float, mass: float | None, mass_tol: float) -> None:
    """The rules for :func:`identify`'s arguments (the command's flags).

    Raises
    ------
    ExperimentError
        ``holdout`` outside [0.05, 0.5], ``mass`` outside (0, 1000] kg, ``mass_tol`` outside
        [0, 1).
    """
    if mass is not None and not 0.0 < mass <= 1000.0:
        raise ExperimentError(f"--mass must be in (0, 1000] kg, got {mass}")
    if not 0.0 <= mass_tol < 1.0:
        raise ExperimentError(f"--mass-tol must be in [0, 1), got {mass_tol}")
    if not 0.05 <= holdout <= 0.5:
        raise ExperimentError(f"--holdout must be in [0.05, 0.5], got {holdout}")


def _scenario_notes(data: Dataset) -> list[str]:
    """What the run record's scenario (``deploy --log``) puts in the log that the model lacks.

    A scenario with timed external force steps (``disturbance-0.5hz``: 30 N from 7.6 s, 80 N
    from 9.8 s, off at 11.9 s) pushes the piston with forces no term of the model stands for:
    the fits lend them to F_n and friction. Measured with the paper's controller on the paper's
    rig: F_C -17 %, b_v +5 % and F_n 14.9 N (the truth 50 N, 3500 N s/m, 0 N), the ranges wide
    enough to hold the truth; on another simulator F_C +10 %, b_v -4 %.
    """
    scenario = SCENARIOS.get(data.scenario)
    steps = scenario.plant_updates.get("disturbance", {}).get("force_steps") if scenario else None
    if not steps:
        return []
    listed = ", ".join(f"{f:g} N from {t:g} s" for t, f in steps)
    return [f"log: its run record names the scenario {scenario.name}, whose external force steps "
            f"({listed}) the model has no term for: F_n and the friction fit absorb them, and "
            f"their ranges widen; identify a run without them (e.g. `deploy --scenario "
            f"sine-0.5hz --log`) for the model tune should use"]


def identify(path: str | os.PathLike[str], holdout: float = 0.2, mass: float | None = None,
             mass_tol: float = 0.05, seed: int = 0, check: bool = True) -> IdentifyResult:
    """Identify the plant behind a run log.

    Parameters
    ----------
    path : path-like
        The MCAP run log (contract 1).
    holdout : float
        Fraction of every 10 s of the log kept for validation (its end), in [0.05, 0.5].
    mass : float, optional
        Known total moving mass [kg]; otherwise it is estimated (or the prior range is used).
    mass_tol : float
        Relative tolerance of a known mass, in [0, 1).
    seed : int
        Seed of the bootstraps.
    check : bool
        Cross-check every range end against the held-out log and move in those it rules out
        (:mod:`~pneutune.identify.crosscheck`).

    Raises
    ------
    LogError
        A bad log (typed, naming the file and what is wrong) or too little excitation.
    ExperimentError
        An argument out of range (:func:`check_arguments`).
    """
    check_arguments(holdout, mass, mass_tol)
    log = load_dataset(path)
    # valves, PWM curve, friction and validation work on the control instants; the mass on
    # every logged sample (an identification run logs 8 samples per control period)
    data = log.at_control_rate()
    fit, held = data.split(holdout)
    notes: list[str] = _scenario_notes(data)
    valves = ValveIdentifier().fit(data, fit)
    notes += valves.notes_
    friction = FrictionIdentifier(mass=mass if mass is not None else 1.0).fit(data, fit)
    M, M_range, M_basis, M_est = _mass(data, friction, fit, mass, mass_tol, seed, notes,
                                       log=log, log_fit=log.split(holdout)[0])
    if mass is None:  # redo the (small) inertial term with the mass used
        friction = FrictionIdentifier(mass=M).fit(data, fit)
    boot = friction.smooth_bootstrap(n_boot=300, block=50, seed=seed)
    theta = theta_bounds(M, M_range, M_basis, friction.smooth_, boot, friction.b_v_,
                         friction.F_C_, friction.F_S_, valves.D_, valves.D_std_,
                         _low_speed_margin(data, friction, notes),
                         stiction_resolved=friction.stiction_resolved_)
    if not friction.stiction_resolved_:
        notes.append("friction: the stiction peak is not resolved by the sliding samples "
                     f"(F_S {friction.F_S_:.3g} N, F_C {friction.F_C_:.3g} N, exponent "
                     f"{friction.alpha_:.3g}); the Stribeck velocity and exponent are weakly "
                     "identified from 4 ms samples, and θ4 allows a stiction excess of half "
                     "F_C")
    period = 1.0 / data.rig.pwm_hz
    plant_cfg = _plant(data, valves, friction, M)
    validation = validate(data, held, plant_cfg)
    model, ranges = _model(data, log, valves, friction, M, M_range, M_basis, theta,
                           validation, notes, period)
    cc = None
    if check:
        cc = cross_check(data, held, model, keys=ranges.unsupported)
        notes += cc.notes()
        model = narrowed_model(model, cc.box).model_copy(update={"notes": tuple(notes)})
        M_range = (model.theta.min[0], model.theta.max[0])
    return IdentifyResult(data, valves, friction, M, M_range, M_basis, M_est, theta,
                          validation, model, plant_cfg, notes, log, cc)


#: Slow sliding samples (2-20 mm/s) below which the Coulomb level is poorly separated from the
#: viscous term, and the Coulomb error then allowed for (relative to F_C).
LOW_SPEED_SAMPLES, LOW_SPEED_FC_ERROR = 500, 0.1


def _low_speed_margin(data: Dataset, friction: FrictionIdentifier,
                      notes: list[str]) -> tuple[float, float]:
    """Extra half-widths of θ3, θ4 when few sliding samples are slow (see theta_bounds)."""
    v = np.abs(data.v[friction.sliding_])
    slow = int(np.count_nonzero(v < 0.02))
    if slow >= LOW_SPEED_SAMPLES or v.size == 0:
        return 0.0, 0.0
    dF = LOW_SPEED_FC_ERROR * friction.F_C_
    v_rms = float(np.sqrt(np.mean(v**2)))
    notes.append(f"friction: only {slow} sliding samples below 20 mm/s, so the Coulomb level "
                 f"and the viscous coefficient trade off; θ3 and θ4 are widened by "
                 f"{dF / v_rms:.0f} N s/m and {dF:.0f} N ({LOW_SPEED_FC_ERROR:.0%} of F_C)")
    return dF / v_rms, dF


def _plant(data: Dataset, valves: ValveIdentifier, friction: FrictionIdentifier,
           mass: float) -> PlantConfig:
    """The identified model as a simulated rig."""
    period = 1.0 / data.rig.pwm_hz
    vdict = {}
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]),
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
    f = friction
    return PlantConfig.model_validate({
        "rig": data.rig.model_dump(), "mass": float(mass), "payload": 0.0,
        "friction": {"F_S": f.F_S_, "F_C": f.F_C_, "v_s": f.v_s_, "alpha": f.alpha_,
                     "b_v": f.b_v_},
        "valves": vdict, "leak": {"C": min(valves.leak_C_, 1e-7)},
        "disturbance": {"F_n": f.F_n_, "D_a": float(valves.D_[0]), "D_b": float(valves.D_[1])},
    })


#: Relative half-width of C for a valve never run at full duty whose C comes from the timing
#: stage (the exact opening per sample).
CLOSED_LOOP_C_ERROR = 0.12
#: Smallest half-width of b for a valve never run at full duty [-].
PARTIAL_B_ERROR = 0.12
#: A valve counts as fully open for its C and b only if the log holds it at duty 1 for this long
#: at a stretch [s]: a whole charge or vent (the identification run's last 1.5 s and more). A
#: closed-loop log has every valve at duty 1 in bursts of 0.01-0.28 s (benchmarks/fleet.py,
#: kind c), which left C and b ranges that missed the truth on 7 of 12 fleet plants.
FULL_OPEN_PIN_S = 0.5
#: Prior ranges of the Stribeck velocity [m/s] and exponent [-] of pneumatic cylinder seals,
#: joined with the fit's: both are weakly identified from samples that miss the stiction peak.
V_S_PRIOR, ALPHA_PRIOR = (1.0e-3, 1.0e-2), (0.5, 3.0)


def _hull(a: tuple[float, float], b: tuple[float, float]) -> list[float]:
    """The smallest interval holding both."""
    return [min(a[0], b[0]), max(a[1], b[1])]


def _range(value: float, sd: float, rel_floor: float, lo_floor: float = 0.0,
           hi_cap: float = np.inf) -> tuple[float, float]:
    half = max(3.29 * sd, rel_floor * abs(value))
    return max(lo_floor, value - half), min(hi_cap, value + half)


#: Stiction excess allowed for when the log shows no break-away: F_S <= this times F_C (a prior:
#: cylinder seals break away at 1.1-2 times their sliding friction).
STICTION_PRIOR_MAX = 2.0


@dataclass(frozen=True)
class Ranges:
    """The ranges of the model's plant coordinates and where each came from.

    Attributes
    ----------
    basis : dict
        Coordinate key path (as :func:`pneutune.control.sim.model_box.uncertainty_box` names it)
        -> one sentence: ``statistics: ...``, ``data bound: ...`` or ``prior: ...``.
    unsupported : frozenset of str
        The coordinates whose range is not a statistical fit (a prior, a structural margin, an
        unidentifiable parameter): those the cross-check tests against the log.
    """

    basis: dict[str, str]
    unsupported: frozenset[str]


def _stiction_range(log: Dataset, friction: FrictionIdentifier, F_C_range: tuple[float, float],
                    theta: ThetaBounds, notes: list[str]) -> tuple[float, tuple[float, float], str]:
    """F_S nominal, range and basis: stick and break-away events bound F_S from both sides
    (:mod:`.stiction`); where the log has none, a prior (F_C .. STICTION_PRIOR_MAX F_C)."""
    F_n = float(theta.nominal[1])
    F_n_half = 0.5 * float(theta.hi[1] - theta.lo[1])
    try:
        sb = stiction_bounds(log, F_n, F_n_half, b_v_max=float(theta.hi[2]),
                             m_max=float(theta.hi[0]))
    except (ValueError, np.linalg.LinAlgError) as exc:  # too little data for the events
        sb = None
        notes.append(f"friction: no stick or break-away events could be read ({exc})")
    lo = F_C_range[0]
    hi = STICTION_PRIOR_MAX * F_C_range[1]
    parts = []
    if sb is not None and sb.lo is not None and sb.lo > lo:
        lo = float(sb.lo)
        e = sb.lo_event
        parts.append(f"at rest under {abs(e.F):.4g} N at t = {e.t:.3f} s" if e else
                     f"at rest under {lo:.4g} N")
    if sb is not None and sb.hi is not None and np.isfinite(sb.hi):
        e = sb.hi_event
        parts.append(f"broke away at {abs(e.F):.4g} N at t = {e.t:.3f} s" if e else
                     f"broke away below {sb.hi:.4g} N")
        if sb.hi < hi:
            hi = float(sb.hi)
            kind = "data bound"
        else:
            kind = "prior"
            parts.append(f"the prior F_S <= {STICTION_PRIOR_MAX:g} F_C_max = {hi:.4g} N is "
                         f"tighter than the break-aways ({sb.hi:.4g} N)")
    else:
        kind = "prior"
        notes.append(f"friction: the log shows no break-away from rest away from the end "
                     f"stops, so nothing bounds the stiction force from above; F_S <= "
                     f"{STICTION_PRIOR_MAX:g} F_C_max = {hi:.4g} N is a prior (cylinder seals "
                     f"break away at 1.1-2 times their sliding friction)")
    if lo > hi:  # events inconsistent with each other or with F_C: trust the events' span
        notes.append(f"friction: the stick and break-away bounds of F_S ({lo:.4g} N, "
                     f"{hi:.4g} N) contradict each other or F_C; F_S is taken in between")
        lo, hi = min(lo, hi), max(lo, hi)
    nominal = float(np.clip(friction.F_S_, lo, hi))
    if not friction.stiction_resolved_:  # the sliding samples do not show the peak
        nominal = 0.5 * (lo + hi)
    detail = "; ".join(parts) if parts else "no rest or break-away events"
    basis = (f"{kind}: {detail}" + (f"; {sb.basis}" if sb is not None else "")
             + ("" if kind == "data bound" else f"; F_S <= {STICTION_PRIOR_MAX:g} F_C (prior)"))
    return nominal, (lo, hi), basis


def _model(data: Dataset, log: Dataset, valves: ValveIdentifier, friction: FrictionIdentifier,
           mass: float, mass_range: tuple[float, float], mass_basis: str, theta: ThetaBounds,
           validation: Validation, notes: list[str], period: float
           ) -> tuple[ModelConfig, Ranges]:
    vdict = {}
    basis: dict[str, str] = {}
    unsupported: set[str] = set()
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        c_lo, c_hi = _range(valves.C_[i], valves.C_std_[i], 0.03, 1e-12, 1e-6)
        c_basis = f"statistics: ±3.29 s.e. ({valves.C_std_[i]:.2g}), at least ±3 %"
        pinned = valves.full_open_s_[i] >= FULL_OPEN_PIN_S
        if not pinned and valves.timing_ is not None:
            # never held fully open, C from the exact opening per sample: C within 4 % on most
            # closed-loop logs of simulated rigs, 9 % where b traded off (benchmarks/fleet.py)
            c_lo, c_hi = _range(valves.C_[i], valves.C_std_[i], CLOSED_LOOP_C_ERROR, 1e-12,
                                1e-6)
            c_basis = (f"statistics and a structural margin: never held fully open for "
                       f"{FULL_OPEN_PIN_S:g} s, C from the exact opening per sample, "
                       f"±{CLOSED_LOOP_C_ERROR:.0%}")
            unsupported.add(f"valves.{name}.C")
        elif valves.max_duty_[i] < 0.999:
            # never fully open: only C r(u) over the duties seen is determined; with
            # r(u_max) <= r_true(u_max) <= 1 the conductance lies in [C r(u_max), C / r(u_max)]
            r_top = float(max(valves.ratio(valves.max_duty_[i], i), 0.05))
            c_lo = min(c_lo, valves.C_[i] * r_top)
            c_hi = min(max(c_hi, valves.C_[i] / r_top), 1e-6)
            c_basis = (f"structural: never fully open, C r(u) known to u = "
                       f"{valves.max_duty_[i]:.2f} only, [C r(u_max), C / r(u_max)]")
            unsupported.add(f"valves.{name}.C")
        b_lo, b_hi = _range(valves.b_[i], valves.b_std_[i], 0.05, 0.0, 0.95)
        b_basis = f"statistics: ±3.29 s.e. ({valves.b_std_[i]:.2g}), at least ±5 %"
        if not pinned:
            # never held fully open: b shows only through partial openings; on closed-loop logs of
            # the fleet it came out up to 0.1 off, several times its statistical error
            b_lo = max(0.0, min(b_lo, valves.b_[i] - PARTIAL_B_ERROR))
            b_hi = min(0.95, max(b_hi, valves.b_[i] + PARTIAL_B_ERROR))
            b_basis += (f", at least ±{PARTIAL_B_ERROR:g} (never held fully open for "
                        f"{FULL_OPEN_PIN_S:g} s)")
            unsupported.add(f"valves.{name}.b")
        if b_hi - b_lo > WEAK_B_SPAN:
            unsupported.add(f"valves.{name}.b")
            b_basis = "weakly identified: " + b_basis
        if b_hi - b_lo > 0.5:
            # b unidentifiable: the subsonic flow, hence C, is then only known to a factor
            c_lo, c_hi = min(c_lo, 0.5 * valves.C_[i]), min(max(c_hi, 2.0 * valves.C_[i]), 1e-6)
            c_basis = "structural: b not identifiable, so C to a factor 2"
            unsupported.add(f"valves.{name}.C")
        basis[f"valves.{name}.C"] = c_basis
        basis[f"valves.{name}.b"] = b_basis
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]), "C_min": c_lo,
                       "C_max": c_hi, "b_min": b_lo, "b_max": b_hi,
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
        v_duty, v_ratio = _curve_points(valves.knots_, valves.curves_[i])
        vdict[name]["pwm"] = {"duty": v_duty, "ratio": v_ratio}
    f = friction
    sd = f.std_
    F_C_range = _range(f.F_C_, sd["F_C"], 0.1)
    F_S, F_S_range, basis["friction.F_S"] = _stiction_range(log, f, F_C_range, theta, notes)
    unsupported |= {"friction.F_S", "friction.v_s", "friction.alpha"}
    basis["friction.F_C"] = f"statistics: ±3.29 s.e. ({sd['F_C']:.3g} N), at least ±10 %"
    basis["friction.b_v"] = f"statistics: ±3.29 s.e. ({sd['b_v']:.3g} N s/m), at least ±5 %"
    basis["friction.v_s"] = (f"prior {V_S_PRIOR[0] * 1e3:g}-{V_S_PRIOR[1] * 1e3:g} mm/s "
                             "joined with the fit's ±3.29 s.e. (at least ±50 %): weakly "
                             "identified")
    basis["friction.alpha"] = (f"prior {ALPHA_PRIOR[0]:g}-{ALPHA_PRIOR[1]:g} joined with the "
                               "fit's ±3.29 s.e. (at least ±50 %): weakly identified")
    basis["mass"] = mass_basis
    if "prior" in mass_basis:
        unsupported.add("mass")
    for key, i in (("disturbance.F_n", 1), ("disturbance.D_a", 4), ("disturbance.D_b", 5)):
        basis[key] = "statistics: " + theta.basis[i]
    for ch, key in enumerate(("disturbance.D_a", "disturbance.D_b")):
        if valves.D_closed_[ch] is False:
            unsupported.add(key)
            basis[key] = ("weakly identified: the chamber's valves are never all shut, "
                          "widened to cover zero")
    duty, ratio = _curve_points(valves.knots_, valves.curve_)
    data_dict = {
        "schema": MODEL_SCHEMA,
        "source": {"log": data.path, "sha256": data.sha256, "duration_s": data.duration},
        "rig": data.rig.model_dump(),
        "valves": vdict,
        "pwm": {"duty": duty, "ratio": ratio},
        "friction": {
            "F_S": max(F_S, f.F_C_), "F_C": f.F_C_, "v_s": f.v_s_, "alpha": f.alpha_,
            "b_v": f.b_v_, "A_f": float(theta.nominal[3]),
            "ranges": {
                "F_S": [min(F_S_range[0], f.F_C_), max(F_S_range[1], F_S, f.F_C_)],
                "F_C": list(F_C_range),
                "v_s": _hull(_range(f.v_s_, sd["v_s"], 0.5, 1e-4, 1.0), V_S_PRIOR),
                "alpha": _hull(_range(f.alpha_, sd["alpha"], 0.5, 0.3, 10.0), ALPHA_PRIOR),
                "b_v": list(_range(f.b_v_, sd["b_v"], 0.05)),
            },
        },
        "mass": float(mass),
        "mass_range": list(mass_range),
        "theta": {"nominal": theta.nominal.tolist(), "min": theta.lo.tolist(),
                  "max": theta.hi.tolist()},
        "uncertainty": {"F_max": f.residual_max_, "D_a_max": float(valves.D_max_[0]),
                        "D_b_max": float(valves.D_max_[1])},
        "fit": {"nrmse_x": validation.nrmse["x"], "nrmse_p_a": validation.nrmse["p_a"],
                "nrmse_p_b": validation.nrmse["p_b"]},
        "leak": {"C": min(valves.leak_C_, 1e-7)},
        "sensors": _noise_levels(log),
        "basis": basis,
        "notes": notes,
    }
    return ModelConfig.model_validate(data_dict), Ranges(basis, frozenset(unsupported))


def _curve_points(knots: np.ndarray, curve: np.ndarray) -> tuple[list[float], list[float]]:
    """The curve as contract-3 points, rounded, starting at (0, 0)."""
    duty = [round(float(k), 6) for k in knots]
    ratio = [round(float(r), 6) for r in np.maximum.accumulate(np.clip(curve, 0.0, 1.0))]
    ratio[0] = 0.0
    return duty, ratio


def _noise_levels(data: Dataset) -> dict[str, float]:
    """Sensor noise [m, Pa] from third differences where the signal is smooth at the sample
    scale (:func:`~pneutune.identify.stiction.position_noise_std`: the piston at rest;
    :func:`~pneutune.identify.stiction.force_noise_std`: the chambers with their valves shut, or the
    supply sensor). A smoothing residual would count the PWM ripple of a closed-loop log as
    noise (10 times the truth, measured)."""
    r = data.rig
    sigma_F, _ = force_noise_std(data)
    p_noise = sigma_F / float(np.hypot(r.A_a, r.A_b))
    return {"x_noise": float(min(position_noise_std(data.x), 1e-3)),
            "p_noise": float(min(p_noise, 1e5))}
