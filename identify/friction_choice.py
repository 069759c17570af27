"""The friction ``identify`` takes, and what it leaves θ's friction coordinates.

* :func:`fit_friction`: the Stribeck fit (:class:`~pneutune.identify.motion.FrictionIdentifier`),
  or, for a protocol run cut short on which it cannot run, the prior
  (:class:`~pneutune.identify.friction_prior.PriorFriction`);
* :func:`friction_disagreements`: notes where pooled logs' own friction fits disagree (the rig
  changed between them);
* :func:`low_speed_margin`: the widening of θ3, θ4 when few sliding samples are slow;
* :func:`prior_theta`: θ2..θ4 from the prior, when the fit could not run.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .bounds import MIN_HALF, ThetaBounds, Z
from .dataset import Dataset, IdentificationError, Pool
from .friction_prior import PriorFriction
from .motion import FrictionIdentifier

#: Stiction excess allowed for when the log shows no break-away: F_S <= this times F_C (a prior:
#: cylinder seals break away at 1.1-2 times their sliding friction).
STICTION_PRIOR_MAX = 2.0

#: Two logs disagree on a friction coefficient when their estimates lie this many combined
#: standard errors apart ...
DISAGREE_SIGMAS = 5.0
#: ... and differ by this fraction of the smaller one.
DISAGREE_FRACTION = 0.05

#: Slow sliding samples (2-20 mm/s) below which the Coulomb level is poorly separated from the
#: viscous term, and the Coulomb error then allowed for (relative to F_C).
LOW_SPEED_SAMPLES, LOW_SPEED_FC_ERROR = 500, 0.1


def fit_friction(data: Dataset, fit: np.ndarray, mass: float, partial: bool,
                 notes: list[str]) -> FrictionIdentifier | PriorFriction:
    """The friction fit, or for a protocol run cut short on which it cannot run, the prior.

    Parameters
    ----------
    data : Dataset
        The pooled logs at the control instants.
    fit : ndarray of bool
        The fit mask.
    mass : float
        The moving mass of the fit's inertial term [kg].
    partial : bool
        Some log is a protocol run cut short (:mod:`.coverage`): a fit that cannot run falls
        back to the prior (:mod:`.friction_prior`), noted.
    notes : list of str
        Appended to: a note when the prior is used.

    Returns
    -------
    FrictionIdentifier or PriorFriction

    Raises
    ------
    IdentificationError
        The fit cannot run on logs that are not a protocol run cut short (bad input).
    """
    try:
        return FrictionIdentifier(mass=mass).fit(data, fit)
    except IdentificationError as exc:
        if not partial:
            raise
        prior = PriorFriction(data.rig, data.n, exc.message)
        notes.append(f"friction: not identifiable from these logs ({exc.message}); F_C in "
                     f"[{prior.F_C_range_[0]:.3g}, {prior.F_C_range_[1]:.3g}] N, b_v in "
                     f"[{prior.b_v_range_[0]:.3g}, {prior.b_v_range_[1]:.3g}] N s/m and F_n in "
                     f"[{prior.F_n_range_[0]:.3g}, {prior.F_n_range_[1]:.3g}] N are a prior "
                     f"from the rig's geometry and supply; the cross-check narrows b_v and F_n "
                     f"where the log rules their ends out")
        return prior


def check_force_balance(name: str, friction: FrictionIdentifier,
                        smooth_boot: np.ndarray) -> None:
    """Refuse logs whose force balance runs backwards.

    The smooth model's viscous coefficient θ3 is the force per unit speed the pressures spend
    on friction; it cannot be negative. A value below zero by more than its uncertainty means
    the measured pneumatic force opposes the motion it drives: the chamber pressures swapped,
    a pressure reading stuck, or the areas of the rig metadata wrong. The bounds would then be
    built on a contradiction, so identification stops and says what to check.

    Parameters
    ----------
    name : str
        The log(s) as error messages give them.
    friction : FrictionIdentifier
        The friction fit.
    smooth_boot : ndarray (B, 3)
        Bootstrap replicates of its smooth θ2..θ4.

    Raises
    ------
    IdentificationError
        θ3 below ``-max(Z s.e., MIN_HALF["b_v"])``.
    """
    bv = float(friction.smooth_[1])
    sd = float(np.std(smooth_boot[:, 1], ddof=1)) if len(smooth_boot) > 1 else 0.0
    if bv < -max(Z * sd, MIN_HALF["b_v"]):
        raise IdentificationError(
            name, f"the force balance runs backwards: the friction fit gives a viscous "
            f"coefficient θ3 = {bv:.4g} N s/m (bootstrap s.e. {sd:.3g}), which cannot be "
            "negative: the pneumatic force A_a p_a - A_b p_b - A_r p0 pushes against the "
            "motion it drives; check that p_a is chamber A (rodless side) and p_b chamber B "
            "(rod side), that no pressure reading is stuck, and the rig metadata's A_a and A_b")


def friction_disagreements(pl: Pool, fit: np.ndarray, mass: float) -> list[str]:
    """Notes for pooled logs whose own friction fits disagree (the rig changed between them).

    Each pooled log that supports a friction fit of its own is fitted alone; two logs whose
    F_C or b_v lie more than :data:`DISAGREE_SIGMAS` combined standard errors and
    :data:`DISAGREE_FRACTION` apart show two states of the rig (a seal change, a new load),
    which the pooled fit blends.

    Parameters
    ----------
    pl : Pool
        The pooled logs.
    fit : ndarray of bool
        The pooled fit mask.
    mass : float
        The moving mass of the fits' inertial term [kg].

    Returns
    -------
    list of str
        One note per coefficient on which some pair disagrees (empty when they agree).
    """
    own: list[tuple[str, FrictionIdentifier]] = []
    for name, (a, b) in zip(pl.names, pl.spans, strict=True):
        mask = np.zeros_like(fit)
        mask[a:b] = fit[a:b]
        try:
            own.append((name, FrictionIdentifier(mass=mass).fit(pl.data, mask)))
        except IdentificationError:
            continue  # too little motion in this log for a fit of its own
    notes = []
    for key, unit, attr in (("F_C", "N", "F_C_"), ("b_v", "N s/m", "b_v_")):
        worst = None
        for i in range(len(own)):
            for j in range(i + 1, len(own)):
                (na, fa), (nb, fb) = own[i], own[j]
                va, vb = getattr(fa, attr), getattr(fb, attr)
                sd = math.hypot(fa.std_[key], fb.std_[key])
                gap = abs(va - vb)
                if gap > DISAGREE_SIGMAS * sd and gap > DISAGREE_FRACTION * min(abs(va), abs(vb)):
                    z = gap / sd if sd > 0 else math.inf
                    if worst is None or z > worst[0]:
                        worst = (z, na, va, nb, vb)
        if worst is not None:
            z, na, va, nb, vb = worst
            notes.append(f"friction: the logs disagree on {key}: {va:.4g} {unit} from {na}, "
                         f"{vb:.4g} {unit} from {nb} ({z:.0f} standard errors apart): the rig "
                         f"changed between them (a seal, a load, the supply?), and the model "
                         f"blends the two; identify the logs of the rig as it is now")
    return notes


def low_speed_margin(data: Dataset, friction: FrictionIdentifier,
                     notes: list[str]) -> tuple[float, float]:
    """Extra half-widths of θ3, θ4 when few sliding samples are slow.

    With fewer than :data:`LOW_SPEED_SAMPLES` sliding samples below 20 mm/s the Coulomb level
    and the viscous coefficient trade off: θ4 is widened by :data:`LOW_SPEED_FC_ERROR` F_C, and
    θ3 by that over the sliding samples' RMS speed
    (:class:`~pneutune.identify.bounds.FrictionFit`'s ``low_speed_margin``).

    Parameters
    ----------
    data : Dataset
        The data the friction was fitted on.
    friction : FrictionIdentifier
        The friction fit.
    notes : list of str
        Appended to: a note when θ3, θ4 are widened.

    Returns
    -------
    (float, float)
        The extra half-widths of θ3 [N s/m] and θ4 [N] (zeros when there are enough slow
        samples).
    """
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


def prior_theta(theta: ThetaBounds, prior: PriorFriction) -> ThetaBounds:
    """θ2..θ4 from the friction prior.

    Parameters
    ----------
    theta : ThetaBounds
        θ's nominal, bounds and bases.
    prior : PriorFriction
        The friction prior.

    Returns
    -------
    ThetaBounds
        A copy with θ2 (F_n) and θ3 (b_v) over the prior's ranges, θ4 (A_f) over the Coulomb
        range up to :data:`STICTION_PRIOR_MAX` times its top, and the prior's basis for all
        three.
    """
    lo, hi = theta.lo.copy(), theta.hi.copy()
    lo[1], hi[1] = prior.F_n_range_
    lo[2], hi[2] = prior.b_v_range_
    lo[3], hi[3] = prior.F_C_range_[0], STICTION_PRIOR_MAX * prior.F_C_range_[1]
    basis = list(theta.basis)
    basis[1] = basis[2] = basis[3] = prior.basis_
    return dataclasses.replace(theta, lo=lo, hi=hi, basis=tuple(basis))
