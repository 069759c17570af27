"""A prior for the friction of a rig whose logs cannot support the friction fit.

:class:`~pneutune.identify.motion.FrictionIdentifier` needs the piston to slide: a protocol run
cut short before its constant-speed ramps (``identify`` of a partial run, :mod:`.coverage`) has
the piston on its end stops nearly throughout, and the fit cannot run. Rather than fail, the
model then takes the friction from what the rig's geometry says, with ranges wide enough for
pneumatic cylinder seals, and says so in its notes and bases; the cross-check
(:mod:`pneutune.identify.crosscheck`) narrows whatever end the log contradicts.

Scales: ``F_ref = A_a (p_s - p0)``, the cylinder's force at supply pressure (3.9 kN for the
paper's rig: 100 mm bore, 6 bar absolute supply).

* Coulomb level: :data:`COULOMB_FRACTION` of ``F_ref``, 20-390 N for the paper's rig. The
  paper's rig has 50 N (1.3 %); the plants of benchmarks/fleet.py 30-120 N (0.8-3 %).
* Viscous coefficient: :data:`VISCOUS_PER_FORCE` times ``F_ref``, 390-19600 N s/m for the
  paper's rig, whose b_v is 3500 N s/m (0.9 s/m times F_ref; the fleet's 1500-5000 N s/m,
  0.4-1.3 s/m).
* Constant force F_n: ``±`` :data:`F_N_FRACTION` of ``F_ref`` around 0.
* Stiction: up to ``STICTION_PRIOR_MAX`` times the Coulomb level (the pipeline's rule for logs
  without break-aways); the Stribeck velocity and exponent: the pipeline's priors.

Nominal values are the geometric means of the ranges (F_n: 0).
"""

from __future__ import annotations

import math

import numpy as np

from pneutune.control.contracts.plant import RigConfig

#: Coulomb level as a fraction of A_a (p_s - p0) [-].
COULOMB_FRACTION = (0.005, 0.1)
#: Viscous coefficient per unit of A_a (p_s - p0) [s/m].
VISCOUS_PER_FORCE = (0.1, 5.0)
#: Half-width of the constant force F_n as a fraction of A_a (p_s - p0) [-].
F_N_FRACTION = 0.05


def reference_force(rig: RigConfig) -> float:
    """``A_a (p_s - p0)``: the cylinder's force at supply pressure [N]."""
    return rig.A_a * (rig.p_s - rig.p0)


class PriorFriction:
    """Friction from the rig's geometry alone, in the attributes of a fitted
    :class:`~pneutune.identify.motion.FrictionIdentifier` (module docstring).

    Parameters
    ----------
    rig : RigConfig
        The rig.
    n : int
        Number of samples of the dataset it stands in for (``sliding_`` is all False).
    reason : str
        Why the fit could not run (for the notes).

    Attributes
    ----------
    F_C_range_, b_v_range_, F_n_range_ : (float, float)
        The prior ranges [N, N s/m, N].
    basis_ : str
        One sentence for model.yaml's ``basis``.
    """

    fitted_ = True
    stiction_resolved_ = False
    coulomb_from_fast_ = False

    def __init__(self, rig: RigConfig, n: int, reason: str) -> None:
        F_ref = reference_force(rig)
        self.reason = reason
        self.F_C_range_ = (COULOMB_FRACTION[0] * F_ref, COULOMB_FRACTION[1] * F_ref)
        self.b_v_range_ = (VISCOUS_PER_FORCE[0] * F_ref, VISCOUS_PER_FORCE[1] * F_ref)
        self.F_n_range_ = (-F_N_FRACTION * F_ref, F_N_FRACTION * F_ref)
        self.F_C_ = math.sqrt(self.F_C_range_[0] * self.F_C_range_[1])
        self.F_S_ = self.F_C_
        self.b_v_ = math.sqrt(self.b_v_range_[0] * self.b_v_range_[1])
        self.F_n_ = 0.0
        self.v_s_ = 5.0e-3
        self.alpha_ = 2.0
        self.std_ = {k: 0.0 for k in ("F_S", "F_C", "v_s", "alpha", "b_v", "F_n")}
        self.smooth_ = np.array([0.0, self.b_v_, self.F_C_])
        self.sliding_ = np.zeros(n, dtype=bool)
        self.y_ = np.zeros(0)
        # the fast-changing friction error: at most the Coulomb level itself
        self.residual_max_ = self.F_C_range_[1]
        self.residual_std_ = float("nan")
        self.basis_ = (f"prior from the rig: F_C {COULOMB_FRACTION[0]:.1%}-"
                       f"{COULOMB_FRACTION[1]:.0%} and b_v {VISCOUS_PER_FORCE[0]:g}-"
                       f"{VISCOUS_PER_FORCE[1]:g} s/m times the force at supply "
                       f"A_a (p_s - p0) = {F_ref:.4g} N, F_n within ±{F_N_FRACTION:.0%} of it "
                       f"(the logs cannot support the friction fit: {reason})")

    def smooth_bootstrap(self, n_boot: int, block: int, seed: int) -> np.ndarray:
        """No data, no replicates: ``n_boot`` copies of ``smooth_`` (the ranges are set from
        the prior instead)."""
        return np.tile(self.smooth_, (n_boot, 1))


__all__ = ["COULOMB_FRACTION", "F_N_FRACTION", "VISCOUS_PER_FORCE", "PriorFriction",
           "reference_force"]
