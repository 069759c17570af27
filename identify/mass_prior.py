"""A prior range of the moving mass from the rig, for logs that cannot resolve the mass.

The mass shows in a log only as the lag M/b_v of the motion behind the pressure force (about
0.3 ms on the paper's rig, docs/identifiability.md): a log sampled at the 4 ms control rate
cannot resolve it. Its range then comes from what is known of the rig, narrowed later by the
cross-check (:mod:`pneutune.identify.crosscheck`: a mass whose simulation the log contradicts is
cut off):

* a ``rig.mass`` hint in the log's metadata (the engineer's datasheet plus payload figure):
  ``[hint / HINT_FACTOR, hint * HINT_FACTOR]``;
* otherwise the cylinder geometry: the piston, an aluminium disc of the bore with a thickness of
  0.3 bore diameters (seals, magnet, wear ring), plus the steel rod of the rod-side area over the
  stroke and 0.6 bore diameters (through the piston, the bearing and the thread). For the
  paper's rig (100 mm bore, 20 mm rod, 50 mm stroke) that is 0.91 kg against its 1.05 kg of
  moving parts. Attachments and payload are unknown, so the range is
  ``[GEOMETRY_RANGE[0], GEOMETRY_RANGE[1]]`` times that: 0.45-3.6 kg for the paper's rig.
"""

from __future__ import annotations

import math

from pneutune.control.contracts.plant import RigConfig

#: Densities of the piston (aluminium) and the rod (steel) [kg/m^3].
RHO_PISTON, RHO_ROD = 2700.0, 7850.0
#: Piston thickness and the rod's length beyond the stroke, in bore diameters [-].
PISTON_THICKNESS, ROD_EXTRA = 0.3, 0.6
#: Smallest rod diameter assumed when the rig gives no rod area (a through-rod cylinder) [-].
MIN_ROD_FRACTION = 0.2
#: Prior range around the geometric mass [-].
GEOMETRY_RANGE = (0.5, 4.0)
#: Prior range factor around a ``rig.mass`` hint [-].
HINT_FACTOR = 1.4


def geometric_mass(rig: RigConfig) -> float:
    """Piston plus rod mass of a cylinder of this geometry [kg] (module docstring).

    Parameters
    ----------
    rig : RigConfig

    Returns
    -------
    float
    """
    bore = math.sqrt(4.0 * rig.A_a / math.pi)
    rod_area = max(rig.A_a - rig.A_b, math.pi / 4.0 * (MIN_ROD_FRACTION * bore) ** 2)
    stroke = rig.x_max - rig.x_min
    piston = RHO_PISTON * rig.A_a * PISTON_THICKNESS * bore
    rod = RHO_ROD * rod_area * (stroke + ROD_EXTRA * bore)
    return piston + rod


def mass_prior(rig: RigConfig, hint: float | None = None
               ) -> tuple[tuple[float, float], float, str]:
    """The prior range of the moving mass, its nominal value and its basis.

    Parameters
    ----------
    rig : RigConfig
    hint : float, optional
        The log's ``rig.mass`` hint [kg].

    Returns
    -------
    ((float, float), float, str)
        ``(lo, hi)`` [kg], the nominal value (the hint, or the geometric mean of the range) and
        a sentence saying where it comes from.
    """
    if hint is not None:
        lo, hi = hint / HINT_FACTOR, hint * HINT_FACTOR
        return (lo, hi), float(hint), (
            f"prior from the log's rig.mass hint {hint:.3g} kg (÷/× {HINT_FACTOR:g})")
    m = geometric_mass(rig)
    lo, hi = GEOMETRY_RANGE[0] * m, GEOMETRY_RANGE[1] * m
    bore = math.sqrt(4.0 * rig.A_a / math.pi)
    return (lo, hi), math.sqrt(lo * hi), (
        f"prior from the cylinder geometry: piston and rod of a {bore * 1e3:.0f} mm bore, "
        f"{(rig.x_max - rig.x_min) * 1e3:.0f} mm stroke weigh about {m:.2g} kg; "
        f"{GEOMETRY_RANGE[0]:g}-{GEOMETRY_RANGE[1]:g} times that for attachments and payload")


__all__ = ["GEOMETRY_RANGE", "HINT_FACTOR", "geometric_mass", "mass_prior"]
