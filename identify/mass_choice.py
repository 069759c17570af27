"""The moving mass ``identify`` takes, its range and their basis.

:func:`choose_mass`, in order of preference:

1. a mass given by the user (``--mass``), with its tolerance;
2. the lag of the motion behind the pressure force
   (:class:`~pneutune.identify.mass.LagMassIdentifier`), on the logs sampled fast enough
   (:data:`~pneutune.identify.mass.MIN_SAMPLES_PER_PWM` samples per PWM period), when its
   interval is narrower than :data:`MASS_IDENTIFIABLE_RATIO`;
3. the integrated motion equation (:class:`~pneutune.identify.motion.MassIdentifier`) on the
   control instants, its interval widened by :data:`MASS_BIAS_MARGIN` b_v Ts, when it is
   narrow enough and above :func:`mass_sampling_limit`, intersected with the prior;
4. the prior (:func:`~pneutune.identify.mass_prior.mass_prior`): the rig's geometry, or the
   log's mass hint; the cross-check narrows it where the log rules its ends out.

Each choice that falls through says why in a note.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pneutune.control.errors import LogError

from .coverage import MASS_GROUPS, MASS_KINDS
from .dataset import Dataset, Pool
from .friction_prior import PriorFriction
from .mass import MIN_SAMPLES_PER_PWM, LagMassIdentifier, samples_per_pwm
from .mass_prior import mass_prior
from .motion import V_SLIDE, FrictionIdentifier, MassIdentifier
from .sources import from_logs

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


def _lag_mass(log: Dataset | Sequence[Dataset], friction: FrictionIdentifier,
              fit: np.ndarray | Sequence[np.ndarray], seed: int,
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


#: An estimate this many times the prior's upper end is more likely the sensors' lag than mass.
FAR_ABOVE_PRIOR = 5.0


def _far_above(lo: float, prior: tuple[float, float], b_v: float) -> str:
    """What a note adds when the data put the mass far above the prior: the likelier cause."""
    if not lo > FAR_ABOVE_PRIOR * prior[1]:
        return ""
    return (f". An estimate over {FAR_ABOVE_PRIOR:g} times the prior's upper end is more often "
            f"the sensors than a payload: pressure readings that lead the chambers' pressures "
            f"(transmitters at the valves' side of a line or fitting, which read its pressure "
            f"drop) or a position sensor lagging the transmitters add {b_v * 1e-3:.2g} kg per "
            f"ms of lag; tune then works on that effective mass, and on simulated rigs with such "
            f"lags controllers tuned on it tracked worse than ones tuned on the geometry prior. "
            f"If the axis carries no such payload, check where the transmitters are plumbed, or "
            f"give --mass KG")


def _above(M: float, lo: float, prior: tuple[float, float], b_v: float) -> str:
    """What a lag estimate's note adds when it lies above the prior's upper end (and not so
    far above that :func:`_far_above` speaks): how much sensor skew would explain it.

    The lag estimate is the mass plus b_v times how much the position sensor lags the
    pressure transmitters, and the log cannot tell the two apart (docs/identification.md,
    "Sensor lags move it"). The model keeps the estimate, since a payload the geometry does not
    know gives the same figure; the note gives the user what decides it.
    """
    if not M > prior[1] or lo > FAR_ABOVE_PRIOR * prior[1]:
        return ""
    return (f". It is above the prior's upper end ({prior[1]:.3g} kg, four times the piston "
            f"and rod): if the axis carries no payload that heavy, a position sensor lagging "
            f"the transmitters by {(M - prior[1]) / b_v * 1e3:.2g} ms or more explains it, and "
            f"on simulated rigs with such lags controllers tuned on the prior tracked better "
            f"than ones tuned on the skewed mass: give --mass KG where the mass is known")


def choose_mass(data: Dataset, friction: FrictionIdentifier | PriorFriction, fit: np.ndarray,
                mass: float | None, mass_tol: float, seed: int, notes: list[str],
                log: Dataset | Sequence[Dataset] | None = None,
                log_fit: np.ndarray | Sequence[np.ndarray] | None = None,
                names: Sequence[str] = (), pooled: Pool | None = None,
                unexcited: Sequence[str] = (), readings_lead: bool = False,
                ) -> tuple[float, tuple[float, float], str,
                           MassIdentifier | LagMassIdentifier | None]:
    """The mass, its range, their basis and the estimator (module docstring).

    Parameters
    ----------
    data : Dataset
        The pooled logs at the control instants (the integrated estimate's data).
    friction : FrictionIdentifier or PriorFriction
        The friction fit; with the prior, no estimate runs and the mass is the prior.
    fit : ndarray of bool
        The fit mask of ``data``.
    mass : float or None
        A mass given by the user [kg]; None to estimate it.
    mass_tol : float
        Relative tolerance of a given mass.
    seed : int
        Seed of the bootstraps.
    notes : list of str
        Appended to: why an estimate was taken or passed over.
    log : Dataset or sequence of Dataset, optional
        The log, or the logs, at their own sampling period that the lag estimate may use.
    log_fit : ndarray of bool or sequence of them, optional
        Their fit masks.
    names : sequence of str
        Their short names, for the basis of several logs.
    pooled : Pool, optional
        The pool behind ``data``, to name the logs of the integrated estimate.
    unexcited : sequence of str
        The experiments of logs sampled fast enough for the lag estimate that lack the
        segments exciting the mass (so not in ``log``): the advice is then those segments.
    readings_lead : bool
        The pressure readings lead the chambers' pressures
        (:func:`~pneutune.identify.transmitters.check_transmitters`): both estimates would take
        that lead for mass, so the mass is the prior.

    Returns
    -------
    (float, (float, float), str, MassIdentifier or LagMassIdentifier or None)
        The nominal mass [kg], its range [kg], their basis, and the estimator (None for a
        given or prior mass).
    """
    if mass is not None:
        rng = (mass * (1.0 - mass_tol), mass * (1.0 + mass_tol))
        return mass, rng, f"given by the user (±{mass_tol:.0%})", None
    prior, prior_nominal, prior_basis = mass_prior(data.rig, data.mass_hint)
    if readings_lead:
        notes.append(f"mass: not estimated (the pressure readings lead the chambers', see the "
                     f"transmitters note); {prior_basis}: [{prior[0]:.3g}, {prior[1]:.3g}] kg, "
                     f"narrowed by the cross-check")
        return prior_nominal, prior, prior_basis, None
    if isinstance(friction, PriorFriction):
        notes.append(f"mass: not estimated (the friction fit, which its estimates need, could "
                     f"not run); {prior_basis}: [{prior[0]:.3g}, {prior[1]:.3g}] kg, narrowed "
                     f"by the cross-check")
        return prior_nominal, prior, prior_basis, None
    logs = [] if log is None else [log] if isinstance(log, Dataset) else list(log)
    fits = ([] if log_fit is None else [log_fit] if isinstance(log, Dataset)
            else list(log_fit))
    fast = [j for j, d in enumerate(logs) if samples_per_pwm(d) >= MIN_SAMPLES_PER_PWM]
    if fast:
        one = len(logs) == 1
        lag = _lag_mass(logs[0] if one else [logs[j] for j in fast], friction,
                        fits[0] if one else [fits[j] for j in fast], seed, notes)
        if lag is not None:
            periods = "/".join(f"{h * 1e3:g}" for h in sorted({logs[j].Ts for j in fast}))
            where = (f"{periods} ms samples" if len(names) <= 1 else
                     f"{periods} ms samples of {', '.join(names[j] for j in fast)}")
            notes.append(
                f"mass: {lag.M_:.3g} kg from the lag of the measured position behind the "
                f"measured pressure force, which holds the sensors' lags too: each ms the "
                f"position sensor lags more than the pressure transmitters adds "
                f"{friction.b_v_ * 1e-3:.2g} kg (b_v times the lag), each ms less takes it "
                f"off; where the sensors' datasheets say they differ, give --mass KG"
                + _above(lag.M_, lag.ci_[0], prior, friction.b_v_)
                + _far_above(lag.ci_[0], prior, friction.b_v_))
            return lag.M_, lag.ci_, (
                f"99 % bootstrap interval of tau b_v, tau the lag of the motion behind the "
                f"pressure force ({where}), widened by "
                f"{lag.discretisation_:.3g} kg, the change on every other sample"), lag
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
        if pooled is not None and len(pooled.names) > 1:
            basis += from_logs(pooled.names_where(fit & (np.abs(data.v) > V_SLIDE)))
        if both[0] < both[1]:
            if both != (lo, hi):
                basis += f", intersected with the {prior_basis}"
            return float(np.clip(est.M_, *both)), both, basis, est
        notes.append(f"mass: the estimate's interval [{lo:.3g}, {hi:.3g}] kg lies outside the "
                     f"{prior_basis} [{prior[0]:.3g}, {prior[1]:.3g}] kg; the data win"
                     + _far_above(lo, prior, friction.b_v_))
        return est.M_, (lo, hi), basis, est
    if lo > limit and hi > lo and (lo > prior[1] or hi < prior[0]):
        # too wide to call identified, but it rules the whole prior out: the data win
        basis = ("99 % bootstrap interval of the integrated motion equation, widened by "
                 f"{margin:.3g} kg for its bias (0.15 b_v Ts), wider than a factor "
                 f"{MASS_IDENTIFIABLE_RATIO:g} but outside the {prior_basis}")
        notes.append(
            f"mass: the estimate's interval [{lo:.3g}, {hi:.3g}] kg is wider than a factor "
            f"{MASS_IDENTIFIABLE_RATIO:g}, but lies wholly {'above' if lo > prior[1] else 'below'}"
            f" the {prior_basis} [{prior[0]:.3g}, {prior[1]:.3g}] kg, which the log therefore "
            f"rules out: θ1 takes the interval (nominal {est.M_:.3g} kg); a payload the "
            f"geometry does not know would explain it; give --mass KG to narrow it"
            + _far_above(lo, prior, friction.b_v_))
        return float(np.clip(est.M_, lo, hi)), (lo, hi), basis, est
    if fast:
        # the log is sampled fast enough for the lag estimate, which failed (its note says why)
        why = ("At this sampling the mass comes from the lag of the motion behind the pressure "
               "force, which gave no usable estimate (see its note); the integrated motion "
               "equation cannot replace it.")
    elif unexcited:
        kinds = MASS_KINDS[unexcited[0]]
        why = (f"The log is sampled fast enough for the lag estimate but has none of the "
               f"segments that excite the mass ({', '.join(kinds)}): record them (record "
               f"--experiment {unexcited[0]} --segments {MASS_GROUPS[unexcited[0]]}) and "
               f"identify both logs together.")
    elif lo <= limit:
        why = (f"With a viscous coefficient of {friction.b_v_:.0f} N s/m the mechanical pole "
               f"b_v/M lies above the Nyquist frequency of the {data.Ts * 1e3:g} ms sampling "
               f"for any mass below {limit:.3g} kg, where this estimate is biased "
               f"(docs/identifiability.md); an identification run logged every 0.5 ms "
               f"resolves the mass (record --sample-period 0.0005).")
    else:
        why = f"It is wider than a factor {MASS_IDENTIFIABLE_RATIO:g}."
    interval = (f"is [{lo:.3g}, {hi:.3g}] kg" if hi > lo else
                f"lies below zero (its upper end is {hi:.3g} kg): the accelerations do not "
                f"follow the pressure force as the model has it (a lag between them, such as "
                f"a pressure transmitter's, or dynamics the model lacks)")
    notes.append(
        f"mass: not identifiable from this log: the 99 % interval of the estimate "
        f"{interval}. {why} θ1 uses the {prior_basis}: [{prior[0]:.3g}, "
        f"{prior[1]:.3g}] kg (nominal {prior_nominal:.3g} kg), narrowed by the cross-check "
        f"where the log contradicts its ends; give --mass KG (datasheet plus weighed payload) "
        f"or a rig.mass hint in the log to narrow it")
    return prior_nominal, prior, prior_basis, est

