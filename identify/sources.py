"""Which logs each fit of ``identify`` draws on, and how the bases and notes name them.

With several logs of one rig (docs/identification.md, "Several logs"):

* :func:`pool_members`: the logs the pooled fits use (those at the control instants);
* :func:`valve_pool`: the logs the valve fit uses (those that test the valves, and the others
  only where they hold the one record of a valve those do not test);
* :class:`Sources`: which of the pooled logs each fit drew on, appended to the bases
  (:func:`from_logs`);
* :func:`coverage_notes`: for each protocol run cut short (:mod:`.coverage`), what its missing
  segments leave each fit resting on.

With one log, the log itself is every fit's source and no basis names it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from pneutune.control.constants import VALVES

from .bounds import ThetaBounds
from .coverage import Coverage, lacks_mass_segments
from .dataset import Dataset, Pool, pool
from .friction_prior import PriorFriction
from .mass import LagMassIdentifier
from .motion import FrictionIdentifier, MassIdentifier
from .valves import FULL_OPEN_PIN_S, ValveIdentifier, longest_run


def pool_members(ctrl: Sequence[Dataset], names: Sequence[str], notes: list[str]) -> list[int]:
    """The logs the pooled fits use: those at the control instants (``rig.Ts``).

    If no log is at the control instants, those at the sampling period with the most data. A
    log left out is noted.

    Parameters
    ----------
    ctrl : sequence of Dataset
        Every log, cut to its control instants where it can be
        (:meth:`~pneutune.identify.dataset.Dataset.at_control_rate`).
    names : sequence of str
        The logs' short names.
    notes : list of str
        Appended to: one note per log left out.

    Returns
    -------
    list of int
        Indices into ``ctrl`` of the logs to pool, in order.
    """
    if len(ctrl) == 1:
        return [0]
    rig_Ts = ctrl[0].rig.Ts
    at = [j for j, d in enumerate(ctrl) if np.isclose(d.Ts, rig_Ts, rtol=1e-9)]
    if not at:
        totals: dict[float, float] = {}
        for d in ctrl:
            totals[d.Ts] = totals.get(d.Ts, 0.0) + d.duration
        best = max(totals, key=lambda h: totals[h])
        at = [j for j, d in enumerate(ctrl) if d.Ts == best]
    for j, d in enumerate(ctrl):
        if j not in at:
            notes.append(
                f"log {names[j]}: sampled every {d.Ts * 1e3:g} ms with duties that change "
                f"inside a {rig_Ts * 1e3:g} ms control period, so it cannot be cut to the "
                f"control instants of the others; the valve, friction and validation fits "
                f"leave it out (its samples still enter the mass, stiction and noise "
                f"estimates)")
    return at


def valve_pool(pl: Pool, fit: np.ndarray, notes: list[str]) -> Pool:
    """The logs the valve fit uses, pooled.

    The logs that test the valves, and the others only where they hold the one record of a
    valve those do not test. A valve is tested by a log that holds it at full duty for
    :data:`~pneutune.identify.valves.FULL_OPEN_PIN_S` at a stretch (a whole charge or vent):
    that pins its C and b (within 0.1 % and 1 % on data/run.mcap). Partial openings under a
    closed loop give C within 4 % at best (docs/identification.md), and pooled with the tests
    they only pull C and b off them: on data/run.mcap with a 12 s closed loop of the same
    plant, b of a_out moved from +0.63 % to +0.81 %. With one log, or no log that tests a
    valve, every log is used.

    Parameters
    ----------
    pl : Pool
        The pooled logs of the other fits.
    fit : ndarray of bool
        The pooled fit mask.
    notes : list of str
        Appended to: a note naming the logs left out, if any.

    Returns
    -------
    Pool
        ``pl`` itself, or the pool of the logs kept.
    """
    if len(pl.spans) == 1:
        return pl
    u = pl.data.u
    pins = []
    for a, b in pl.spans:
        f = fit[a:b]
        pins.append({i for i in range(4)
                     if longest_run(f & (u[a:b, i] >= 0.999)) * pl.data.Ts >= FULL_OPEN_PIN_S})
    tested = set().union(*pins)
    if not tested:
        return pl
    use = []
    for (a, b), pinned in zip(pl.spans, pins, strict=True):
        opens = {i for i in range(4) if np.any(fit[a:b] & (u[a:b, i] > 0.0))}
        use.append(bool(pinned) or bool(opens - tested))
    left = [n for n, keep in zip(pl.names, use, strict=True) if not keep]
    if left:
        by = ", ".join(n for n, keep in zip(pl.names, use, strict=True) if keep)
        notes.append(f"valves: C, b, the PWM curves, the valve timing and D_a, D_b from {by}, "
                     f"whose valve tests hold every valve the logs open fully open for "
                     f"{FULL_OPEN_PIN_S:g} s or more; the partial openings of "
                     f"{', '.join(left)} are left out of that fit")
        keep = [j for j, k in enumerate(use) if k]
        return pool([pl.parts[j] for j in keep], [pl.names[j] for j in keep])
    return pl


def from_logs(names: Sequence[str]) -> str:
    """The logs a basis rests on, as text to append to it.

    Parameters
    ----------
    names : sequence of str
        The logs' short names.

    Returns
    -------
    str
        `` (from a.mcap, b.mcap)``, or ``""`` when no log is named.
    """
    return f" (from {', '.join(names)})" if names else ""


class Sources:
    """Which of several pooled logs each fit drew on, for the bases (one log: not used).

    Parameters
    ----------
    pl : Pool
        The logs pooled for the friction fit.
    vpl : Pool
        The logs pooled for the valve fit (:func:`valve_pool`).
    vfit : ndarray of bool
        The fit mask of ``vpl``.
    valves : ValveIdentifier
        The fitted valves.
    friction : FrictionIdentifier or PriorFriction
        The friction fit (or its prior, which no log supports).

    Attributes
    ----------
    pool : Pool
        ``pl``.
    valve : list of tuple of str
        Per valve, the logs that open it in the fitted part.
    friction : str
        The logs with sliding samples, as :func:`from_logs` text ("" for the prior).
    chamber : list of str
        Per chamber, the logs behind D_a, D_b as :func:`from_logs` text: those with a stretch
        of the chamber's valves shut longer than a window, or every valve log when D came from
        the least squares.
    """

    def __init__(self, pl: Pool, vpl: Pool, vfit: np.ndarray, valves: ValveIdentifier,
                 friction: FrictionIdentifier | PriorFriction) -> None:
        self.pool = pl
        self.valve = [vpl.names_where(vfit & (vpl.data.u[:, i] > 0.0)) for i in range(4)]
        self.friction = ("" if isinstance(friction, PriorFriction)
                         else from_logs(pl.names_where(friction.sliding_)))
        self.chamber = []
        for ch in range(2):
            if valves.D_closed_[ch]:
                shut = vfit & np.all(vpl.data.u[:, 2 * ch:2 * ch + 2] <= 0.0, axis=1)
                used = tuple(n for n, (a, b) in zip(vpl.names, vpl.spans, strict=True)
                             if longest_run(shut[a:b]) > valves.window_)
            else:
                used = vpl.names_where(vfit)
            self.chamber.append(from_logs(used))

    def theta(self, theta: ThetaBounds) -> ThetaBounds:
        """θ's bases with the logs behind θ2..θ6 (θ1's, the mass basis, names its own).

        Parameters
        ----------
        theta : ThetaBounds
            θ's nominal, bounds and bases.

        Returns
        -------
        ThetaBounds
            A copy with the logs appended to the bases of θ2..θ6.
        """
        b = list(theta.basis)
        for i in (1, 2, 3):
            b[i] += self.friction
        b[4] += self.chamber[0]
        b[5] += self.chamber[1]
        return dataclasses.replace(theta, basis=tuple(b))


def coverage_notes(covs: Sequence[Coverage | None], pl: Pool,
                   valves: ValveIdentifier, friction: FrictionIdentifier | PriorFriction,
                   M_est: MassIdentifier | LagMassIdentifier | None, M_basis: str,
                   sources: Sources | None) -> list[str]:
    """For each protocol run cut short: what its missing segments leave each fit resting on.

    Parameters
    ----------
    covs : sequence of Coverage or None
        What each log's protocol run holds (None for a log without segment labels).
    pl : Pool
        The pooled logs of the friction fit.
    valves : ValveIdentifier
        The fitted valves.
    friction : FrictionIdentifier or PriorFriction
        The friction fit, or its prior.
    M_est : MassIdentifier, LagMassIdentifier or None
        The mass estimator (None for a given or prior mass).
    M_basis : str
        The mass range's basis.
    sources : Sources or None
        Which logs each fit drew on (None with one log).

    Returns
    -------
    list of str
        One note per missing kind of segment of each run cut short.
    """
    out: list[str] = []
    for cov in covs:
        if cov is None or not cov.partial:
            continue
        if cov.lacks("constant_speed"):
            if isinstance(friction, PriorFriction):
                rest = "friction is the prior"
            else:
                rest = "friction from " + (", ".join(pl.names_where(friction.sliding_))
                                           if len(pl.names) > 1 else
                                           "the other motion of the log")
            out.append(f"log {cov.name}: no constant-speed segments: {rest}")
        if lacks_mass_segments(cov):
            kinds = "acceleration" if cov.experiment == "identification" else "burst"
            if M_est is None or "prior" in M_basis:
                rest = ("the mass is the prior" if "given" not in M_basis
                        else "the mass is the one given (--mass)")
            elif isinstance(M_est, LagMassIdentifier):
                rest = "the mass from the other logs sampled fast enough"
            else:
                rest = (f"the mass from the integrated motion equation of the "
                        f"{pl.data.Ts * 1e3:g} ms samples")
            out.append(f"log {cov.name}: no {kinds} segments: {rest}")
        if cov.untested:
            for v in cov.untested:
                i = VALVES.index(v)
                if getattr(valves, "unopened_", np.zeros(4, bool))[i]:
                    rest = "its C and b are a prior"
                elif sources is not None and sources.valve[i]:
                    rest = f"its C and b from {', '.join(sources.valve[i])}"
                else:
                    rest = "its C and b from its other openings in the log"
                out.append(f"log {cov.name}: no valve tests of {v}: {rest}")
    return out
