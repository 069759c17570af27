"""θ = [M, F_n, b_v, A_f, D_an, D_bn] nominal and bounds [θ_min, θ_max], with their basis.

Method (block bootstrap plus a model-mismatch margin; the choice is explained in
docs/identification.md):

* statistical part: a moving-block bootstrap of the smooth-model fit (θ2..θ4) and the
  Gauss-Newton standard errors of the valve fit (θ5, θ6), turned into ±``z`` standard errors
  (z = 3.29: 99.9 % two-sided under normality);
* structural part: the smooth model of Eqs. (3)-(4) is not the plant's Stribeck friction, so
  θ3 and θ4 also get the gap between the two friction models (b_v of the Stribeck fit vs θ3,
  and the Coulomb/stiction levels F_C, F_S vs θ4);
* the mass has its own interval (:class:`~pneutune.identify.motion.MassIdentifier`, or the
  user's ``--mass`` with its tolerance, or the prior range when it is not identifiable).

Coverage: a bound holds the true value whenever the estimation error is within z standard
errors and the structural gap; the tests check it on plants whose truth is known.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Standard errors either side (99.9 % two-sided for a normal estimate).
Z = 3.29
#: Stiction excess (F_S - F_C) / F_C allowed for when the log does not resolve it.
STICTION_PRIOR = 0.5
#: Smallest half-widths, so that a bound is never narrower than the sensors can resolve:
#: F_n [N], b_v [N s/m], A_f [N], D [Pa/s].
MIN_HALF = {"F_n": 2.0, "b_v": 50.0, "A_f": 5.0, "D": 200.0}


@dataclass(frozen=True)
class ThetaBounds:
    """θ nominal, min and max (6 each), and the half-widths' origin per parameter."""

    nominal: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    basis: tuple[str, ...]

    @property
    def widths(self) -> np.ndarray:
        """θ_max - θ_min."""
        return self.hi - self.lo


@dataclass(frozen=True)
class FrictionFit:
    """What the friction fit gives the bounds of θ2..θ4.

    Attributes
    ----------
    smooth : ndarray (3,)
        Smooth-model θ2 (F_n) [N], θ3 (b_v) [N s/m], θ4 (A_f) [N].
    smooth_boot : ndarray (B, 3)
        Bootstrap replicates of ``smooth``.
    stribeck_b_v, F_C, F_S : float
        The Stribeck fit's viscous coefficient [N s/m] and friction levels [N].
    low_speed_margin : (float, float)
        Extra half-widths of (b_v, A_f) when the log has few slow sliding samples: a
        Coulomb-level error ΔF is then absorbed by the viscous term as ΔF / v_rms.
    stiction_resolved : bool, optional
        Whether the friction fit measured the stiction peak
        (``FrictionIdentifier.stiction_resolved_``); default: F_S - F_C >= 2 % of F_C.
    """

    smooth: np.ndarray
    smooth_boot: np.ndarray
    stribeck_b_v: float
    F_C: float
    F_S: float
    low_speed_margin: tuple[float, float] = (0.0, 0.0)
    stiction_resolved: bool | None = None


def theta_bounds(*, mass: float, mass_range: tuple[float, float], mass_basis: str,
                 friction: FrictionFit, D: np.ndarray, D_std: np.ndarray) -> ThetaBounds:
    """Assemble θ and its bounds.

    Parameters
    ----------
    mass, mass_range, mass_basis : float, (float, float), str
        θ1 and its interval [kg], and how it was obtained.
    friction : FrictionFit
        The smooth model's θ2..θ4, their bootstrap, and the Stribeck fit they are compared
        with.
    D, D_std : ndarray (2,)
        θ5, θ6 (D_an, D_bn) [Pa/s] and their standard errors.

    Returns
    -------
    ThetaBounds
        θ nominal, min and max, and the basis of each half-width.
    """
    smooth, smooth_boot = friction.smooth, friction.smooth_boot
    stribeck_b_v, F_C, F_S = friction.stribeck_b_v, friction.F_C, friction.F_S
    low_speed_margin, stiction_resolved = friction.low_speed_margin, friction.stiction_resolved
    sd = np.std(smooth_boot, axis=0, ddof=1) if len(smooth_boot) > 1 else np.zeros(3)
    Fn, bv, Af = smooth
    half_Fn = max(Z * sd[0], MIN_HALF["F_n"])
    half_bv = max(Z * sd[1] + abs(bv - stribeck_b_v) + low_speed_margin[0], MIN_HALF["b_v"])
    # A_f S_f(v) stands for friction between the Coulomb level and the stiction peak. Where
    # the log does not resolve the peak (F_S = F_C), allow the stiction excess of typical
    # cylinder seals, F_S up to 1.5 F_C (a prior, stated in the basis).
    excess = max(abs(Af - F_C), abs(F_S - Af))
    unresolved = (F_S - F_C < 0.02 * max(F_C, 1e-9) if stiction_resolved is None
                  else not stiction_resolved)
    if unresolved:
        excess = max(excess, STICTION_PRIOR * F_C)
    half_Af = max(Z * sd[2] + excess + low_speed_margin[1], MIN_HALF["A_f"])
    half_D = np.maximum(Z * np.asarray(D_std), MIN_HALF["D"])
    # θ3 slightly below zero (within its uncertainty: pipeline.check_force_balance refuses
    # more) is a viscous term too small to see; its nominal sits at the bound, zero
    nominal = np.array([mass, Fn, max(bv, 0.0), Af, D[0], D[1]])
    lo = np.array([mass_range[0], Fn - half_Fn, bv - half_bv, Af - half_Af,
                   D[0] - half_D[0], D[1] - half_D[1]])
    hi = np.array([mass_range[1], Fn + half_Fn, bv + half_bv, Af + half_Af,
                   D[0] + half_D[0], D[1] + half_D[1]])
    lo[2] = max(lo[2], 0.0)
    basis = (mass_basis,
             f"±{Z:g}×bootstrap s.e. ({sd[0]:.3g} N)",
             f"±({Z:g}×bootstrap s.e. {sd[1]:.3g} + Stribeck/smooth gap "
             f"{abs(bv - stribeck_b_v):.3g})",
             f"±({Z:g}×bootstrap s.e. {sd[2]:.3g} + span to F_C/F_S"
             + (f", stiction unresolved: +{STICTION_PRIOR:.0%} of F_C)" if unresolved else ")"),
             f"±{Z:g}×Gauss-Newton s.e. ({D_std[0]:.3g} Pa/s)",
             f"±{Z:g}×Gauss-Newton s.e. ({D_std[1]:.3g} Pa/s)")
    return ThetaBounds(nominal=nominal, lo=lo, hi=hi, basis=basis)
