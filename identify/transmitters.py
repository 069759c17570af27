"""Whether the chamber pressure transmitters read the chamber, or the valves' side of a line.

A chamber charged through its inlet valve alone, with the piston still, cannot lose pressure,
and one vented through its exhaust alone cannot gain any. A transmitter plumbed at the valves
(the tee where a chamber's two valves meet the tube to the cylinder) reads the tube's pressure
drop too: while its inlet pulses, the reading steps down each time the valve closes, and while
its exhaust pulses it steps up. The steps come once per PWM period, at the same phase of the
carrier as long as the duty holds.

So, in every stretch of a fast log (several samples per PWM period) where one valve of a
chamber holds a duty strictly between 0 and 1, the other is shut and the piston is still, the
reading's increments are folded on the PWM period (:data:`MIN_PERIODS` periods at least): the
mean increment of each phase bin, divided by its standard error (the increments' scatter about
their bins' means), is a z-score. A chamber's pressure gives no bin below (charging) or above
(venting) what the noise allows: the most extreme of the bins has |z| of about 2. A reading at
the valves gives one far beyond, at the phase where the valve closes. The chamber's verdict is
the median over its stretches, for charging and for venting alike.

Measured on 0.5 ms identification runs (seed 1): transmitters at the chambers, the paper's rig
and six fleet plants with every other effect: medians of |z| 0.9-2.2; at the valves, behind a
0.3 m line (1.71e-8 m^3/(s Pa), 300 Pa noise) 21-40, and on data/plant-paper-rig.yaml (0.13 m,
2.9e-8, 1.7 kPa noise, a 0.54 ms transmitter lag) 12.7-14.2.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .dataset import Dataset, true_runs
from .mass import MIN_SAMPLES_PER_PWM, samples_per_pwm

#: A chamber's reading is taken for the valves' side of a line when the median |z| of its
#: charging and of its venting stretches both exceed this (a chamber's: about 2).
Z_LEAD = 6.0
#: Least PWM periods of a stretch.
MIN_PERIODS = 20
#: Least stretches per chamber and direction.
MIN_STRETCHES = 3
#: Largest piston speed for the volume to count as fixed [m/s].
STILL_SPEED = 1.0e-3


@dataclass(frozen=True)
class TransmitterCheck:
    """Per chamber (``a``, ``b``): the median z of its charging and venting stretches (charging
    negated, so both are positive for a reading at the valves) and how many stretches each."""

    charge: dict[str, float]
    vent: dict[str, float]
    stretches: dict[str, tuple[int, int]]

    @property
    def at_valves(self) -> tuple[str, ...]:
        """The chambers whose reading steps with their valves: both medians above
        :data:`Z_LEAD`."""
        return tuple(c for c in ("a", "b") if c in self.charge and c in self.vent
                     and self.charge[c] > Z_LEAD and self.vent[c] > Z_LEAD)

    def note(self) -> str | None:
        """The note identify prints when a chamber's reading steps, else None."""
        found = self.at_valves
        if not found:
            return None
        parts = ", ".join(f"chamber {c.upper()}'s (median z {self.charge[c]:.0f} charging and "
                          f"{self.vent[c]:.0f} venting, over {sum(self.stretches[c])} "
                          f"stretches)" for c in found)
        return (f"transmitters: the pressure reading steps when a valve closes, which a "
                f"chamber's pressure cannot: {parts}. The transmitter reads upstream of a "
                f"restriction (plumbed at the valves, before the tube or a fitting to the "
                f"cylinder), so the readings lead the chamber's pressure while air flows. The "
                f"mass estimates would take that lead for mass, so θ1 is the prior unless "
                f"--mass KG is given; the friction and valve fits see the readings as they "
                f"are, which is also what the controller will see. Plumbed at the cylinder's "
                f"ports, the transmitters read the chambers")


def _folded_z(t: np.ndarray, p: np.ndarray, period: float, bins: int) -> np.ndarray:
    """z-score of the mean increment of ``p`` in each phase bin of the PWM period."""
    dp = np.diff(p)
    k = np.floor(np.mod(t[:-1], period) / period * bins).astype(np.int64) % bins
    n = np.bincount(k, minlength=bins)
    mean = np.bincount(k, weights=dp, minlength=bins) / np.maximum(n, 1)
    resid = dp - mean[k]
    sd = np.sqrt(np.sum(resid * resid) / max(dp.size - bins, 1))
    se = np.maximum(sd, 1e-9) / np.sqrt(np.maximum(n, 1))
    return np.where(n > 0, mean / se, 0.0)


def check_transmitters(logs: Sequence[Dataset]) -> TransmitterCheck | None:
    """Fold every qualifying stretch of the fast logs (module docstring).

    Parameters
    ----------
    logs : sequence of Dataset
        The logs at their own sampling period; those with fewer than
        :data:`~pneutune.identify.mass.MIN_SAMPLES_PER_PWM` samples per PWM period are skipped.

    Returns
    -------
    TransmitterCheck or None
        None when no chamber has :data:`MIN_STRETCHES` stretches of each kind.
    """
    zs: dict[tuple[str, str], list[float]] = {}
    for d in logs:
        if samples_per_pwm(d) < MIN_SAMPLES_PER_PWM:
            continue
        period = 1.0 / d.rig.pwm_hz
        bins = max(round(period / d.sample_period), 2)
        still = np.abs(d.v) < STILL_SPEED
        for side, chamber in enumerate(("a", "b")):
            p = d.p_a if side == 0 else d.p_b
            for kind, act, shut, sign in (("charge", 2 * side, 2 * side + 1, -1.0),
                                          ("vent", 2 * side + 1, 2 * side, 1.0)):
                u = d.u[:, act]
                ok = (u > 0.0) & (u < 1.0) & (d.u[:, shut] == 0.0) & still
                for lo, hi in true_runs(ok):
                    # one duty at a time: its valve closes at one phase of the carrier
                    for lo2, hi2 in true_runs(np.r_[True, u[lo + 1:hi] == u[lo:hi - 1]]):
                        a, b = lo + lo2, lo + hi2
                        if (b - a) * d.sample_period < MIN_PERIODS * period:
                            continue
                        z = _folded_z(d.t[a:b], p[a:b], period, bins)
                        zs.setdefault((chamber, kind), []).append(float(np.max(sign * z)))
    charge, vent, stretches = {}, {}, {}
    for chamber in ("a", "b"):
        c, v = zs.get((chamber, "charge"), []), zs.get((chamber, "vent"), [])
        if len(c) >= MIN_STRETCHES and len(v) >= MIN_STRETCHES:
            charge[chamber] = float(np.median(c))
            vent[chamber] = float(np.median(v))
            stretches[chamber] = (len(c), len(v))
    if not charge:
        return None
    return TransmitterCheck(charge, vent, stretches)


__all__ = ["MIN_PERIODS", "MIN_STRETCHES", "STILL_SPEED", "Z_LEAD", "TransmitterCheck",
           "check_transmitters"]
