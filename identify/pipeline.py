"""From a run log to model.yaml: the steps of ``identify`` in order.

1. :func:`~pneutune.identify.dataset.load_dataset`: data checks, aligned arrays.
2. :class:`~pneutune.identify.valves.ValveIdentifier`: C, b per valve, leak, D_a, D_b, the PWM
   curves (QP).
3. :class:`~pneutune.identify.motion.FrictionIdentifier`: Stribeck friction, F_n, the smooth
   model; :class:`~pneutune.identify.motion.MassIdentifier`: the mass and its interval.
4. :func:`~pneutune.identify.bounds.theta_bounds`: θ nominal and bounds.
5. :func:`~pneutune.identify.validation.validate`: the model simulated on the held-out part.

Everything is fitted on the first ``1 - holdout`` of every 10 s of the log; the rest of each
10 s is for validation (:meth:`~pneutune.identify.dataset.Dataset.split`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from pneutune.control.constants import MODEL_SCHEMA, VALVES
from pneutune.control.errors import LogError
from pneutune.control.model_config import ModelConfig
from pneutune.control.plant_config import PlantConfig

from .bounds import ThetaBounds, theta_bounds
from .dataset import Dataset, load_dataset
from .mass import MIN_SAMPLES_PER_PWM, LagMassIdentifier, samples_per_pwm
from .motion import FrictionIdentifier, MassIdentifier
from .validation import Validation, validate
from .valves import ValveIdentifier

#: Prior range of the moving mass when the log cannot pin it down [kg].
MASS_PRIOR: tuple[float, float] = (0.3, 10.0)
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
    try:
        est = MassIdentifier(friction, seed=seed).fit(data, fit)
    except Exception as exc:  # too few sliding windows: report, use the prior
        notes.append(f"mass: not estimated ({exc}); prior range {MASS_PRIOR} kg")
        nominal = float(np.sqrt(MASS_PRIOR[0] * MASS_PRIOR[1]))
        return nominal, MASS_PRIOR, "prior range (not identifiable)", None
    margin = MASS_BIAS_MARGIN * friction.b_v_ * data.Ts
    lo, hi = max(est.ci_[0] - margin, 0.0), est.ci_[1] + margin
    limit = mass_sampling_limit(friction.b_v_, data.Ts)
    if lo > limit and hi / lo <= MASS_IDENTIFIABLE_RATIO:
        return est.M_, (lo, hi), (
            "99 % bootstrap interval of the integrated motion equation, widened by "
            f"{margin:.3g} kg for its bias (0.15 b_v Ts)"), est
    nominal = float(np.sqrt(MASS_PRIOR[0] * MASS_PRIOR[1]))
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
        f"[{lo:.3g}, {hi:.3g}] kg. {why} θ1 uses the prior range "
        f"{MASS_PRIOR} kg (nominal {nominal:.3g} kg, the geometric mean); give "
        f"--mass KG (datasheet plus weighed payload) to narrow it")
    return nominal, MASS_PRIOR, "prior range (not identifiable)", est


def identify(path: str | os.PathLike[str], holdout: float = 0.2, mass: float | None = None,
             mass_tol: float = 0.05, seed: int = 0) -> IdentifyResult:
    """Identify the plant behind a run log.

    Parameters
    ----------
    path : path-like
        The MCAP run log (contract 1).
    holdout : float
        Fraction of every 10 s of the log kept for validation (its end).
    mass : float, optional
        Known total moving mass [kg]; otherwise it is estimated (or the prior range is used).
    mass_tol : float
        Relative tolerance of a known mass.
    seed : int
        Seed of the bootstraps.

    Raises
    ------
    LogError
        A bad log (typed, naming the file and what is wrong) or too little excitation.
    """
    log = load_dataset(path)
    # valves, PWM curve, friction and validation work on the control instants; the mass on
    # every logged sample (an identification run logs 8 samples per control period)
    data = log.at_control_rate()
    fit, held = data.split(holdout)
    notes: list[str] = []
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
    model = _model(data, valves, friction, M, M_range, theta, validation, notes, period)
    return IdentifyResult(data, valves, friction, M, M_range, M_basis, M_est, theta,
                          validation, model, plant_cfg, notes, log)


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


def _range(value: float, sd: float, rel_floor: float, lo_floor: float = 0.0,
           hi_cap: float = np.inf) -> tuple[float, float]:
    half = max(3.29 * sd, rel_floor * abs(value))
    return max(lo_floor, value - half), min(hi_cap, value + half)


def _model(data: Dataset, valves: ValveIdentifier, friction: FrictionIdentifier, mass: float,
           mass_range: tuple[float, float], theta: ThetaBounds, validation: Validation,
           notes: list[str], period: float) -> ModelConfig:
    vdict = {}
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        c_lo, c_hi = _range(valves.C_[i], valves.C_std_[i], 0.03, 1e-12, 1e-6)
        if valves.max_duty_[i] < 0.999:
            # never fully open: only C r(u) over the duties seen is determined; with
            # r(u_max) <= r_true(u_max) <= 1 the conductance lies in [C r(u_max), C / r(u_max)]
            r_top = float(max(valves.ratio(valves.max_duty_[i], i), 0.05))
            c_lo = min(c_lo, valves.C_[i] * r_top)
            c_hi = min(max(c_hi, valves.C_[i] / r_top), 1e-6)
        b_lo, b_hi = _range(valves.b_[i], valves.b_std_[i], 0.05, 0.0, 0.95)
        if b_hi - b_lo > 0.5:
            # b unidentifiable: the subsonic flow, hence C, is then only known to a factor
            c_lo, c_hi = min(c_lo, 0.5 * valves.C_[i]), min(max(c_hi, 2.0 * valves.C_[i]), 1e-6)
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]), "C_min": c_lo,
                       "C_max": c_hi, "b_min": b_lo, "b_max": b_hi,
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
    f = friction
    sd = f.std_
    duty, ratio = _curve_points(valves.knots_, valves.curve_)
    data_dict = {
        "schema": MODEL_SCHEMA,
        "source": {"log": data.path, "sha256": data.sha256, "duration_s": data.duration},
        "rig": data.rig.model_dump(),
        "valves": vdict,
        "pwm": {"duty": duty, "ratio": ratio},
        "friction": {
            "F_S": f.F_S_, "F_C": f.F_C_, "v_s": f.v_s_, "alpha": f.alpha_, "b_v": f.b_v_,
            "A_f": float(theta.nominal[3]),
            "ranges": {
                "F_S": list(_range(f.F_S_, sd["F_S"], 0.2)),
                "F_C": list(_range(f.F_C_, sd["F_C"], 0.1)),
                "v_s": list(_range(f.v_s_, sd["v_s"], 0.5, 1e-4, 1.0)),
                "alpha": list(_range(f.alpha_, sd["alpha"], 0.5, 0.3, 10.0)),
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
        "sensors": _noise_levels(data),
        "notes": notes,
    }
    return ModelConfig.model_validate(data_dict)


def _curve_points(knots: np.ndarray, curve: np.ndarray) -> tuple[list[float], list[float]]:
    """The curve as contract-3 points, rounded, starting at (0, 0)."""
    duty = [round(float(k), 6) for k in knots]
    ratio = [round(float(r), 6) for r in np.maximum.accumulate(np.clip(curve, 0.0, 1.0))]
    ratio[0] = 0.0
    return duty, ratio


def _noise_levels(data: Dataset) -> dict[str, float]:
    """Sensor noise: the spread of the residual of a short smoothing (x, p_a)."""
    from scipy.signal import savgol_filter

    rx = data.x - savgol_filter(data.x, 11, 3)
    rp = data.p_a - savgol_filter(data.p_a, 11, 3)
    # the residual of an order-3, 11-point smoother keeps about 60 % of white noise's variance
    k = 1.0 / np.sqrt(1.0 - 4.0 / 11.0)
    mad = 1.4826
    return {"x_noise": float(min(k * mad * np.median(np.abs(rx)), 1e-3)),
            "p_noise": float(min(k * mad * np.median(np.abs(rp)), 1e5))}
