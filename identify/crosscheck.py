"""Cross-check of the ranges: every range end a tuner would use must reproduce the log.

A range is honest only if the log does not falsify its ends. The statistics behind a range (a
bootstrap, a Gauss-Newton standard error, a prior) do not know that: a prior mass of 10 kg, a
valve at half its conductance or a break-away force of kilonewtons can each be ruled out by a
single simulation of the log. So, on the held-out part of the log (the validation of
:mod:`.validation`: the model simulated from the measured state under the logged duties):

1. the nominal model gives the best fit, NRMSE_s for s in (x, p_a, p_b);
2. each coordinate of the box that ``tune`` samples (:func:`pneutune.control.sim.model_box.
   uncertainty_box`), alone at each of its range ends (the rest nominal), must give
   ``NRMSE_s <= FACTOR * best_s + FLOOR`` for every signal; a valve's C or b is replayed with
   the other at the best of :data:`PARTNER_POINTS` values over its range, since the two trade
   off on subsonic flow (on a closed-loop log a C 12 % off with b near 0 fitted as well as the
   truth);
3. so must the two corners ``tune`` uses (:func:`pneutune.control.sim.model_box.corner`), moving the
   checked coordinates only.

Only the coordinates whose range is not a statistical fit are checked (the caller names them:
a prior, a structural margin, an unidentifiable parameter): one-at-a-time replays cannot judge a
few per cent on a fitted value, whose neighbours compensate each other (a valve's C 8 % off
alone made a closed-loop replay 16 times worse while the truth, 1.4 % off, was 2-4 times worse).

An end that fails is moved toward the nominal value by bisection (halving the distance, at most
:data:`BISECTIONS` times) until it passes. A corner that fails halves the range of the coordinate
whose return to nominal helps it most, and is checked again (greedy, at most
:data:`CORNER_STEPS` halvings): the box is an axis-aligned stand-in for a region whose axes are
correlated, so its corners are the least supported points, and this cuts the fewest ranges.
Every change is reported (report.md) with the NRMSE that ruled the end out.

A corner is judged only where the replay is smooth in the parameters. Before halving anything,
a failing corner is replayed with every range shrunk to :data:`NEAR_FRACTION` of itself; the
ends passed one at a time, so a corner that close to the nominal model fits about as well as
the nominal one when the replay is a smooth function of the parameters. If it still fails, the
misfit is not the ranges' but the replay's (a piston that sticks or slips on a hair's difference
in the force, which an open-loop replay of a closed-loop log meets), and halving would shrink the
ranges to points that no statistic supports and that may miss the truth. Such a corner narrows
nothing, and the report says so. Nor does the greedy halving cut one range more than
:data:`MAX_HALVINGS` times for a corner: when its cuts run out before the corner passes (a misfit
that needs several coordinates back at once), the ranges return to where they were and all of
them are scaled alike, to the largest common fraction that passes (at least NEAR_FRACTION, which
passed). On a closed-loop log where the corners misfit by ten times the best fit, the unlimited
greedy cuts had left the mass, F_S and a valve's C as points that missed the truth.

Why a factor of the best fit and not an absolute level: a closed-loop log of 12 s and a 144 s
identification run fit to very different levels, and what matters is whether a range end explains
the log about as well as the best fit does. Why 5: the check moves one coordinate at a time and
holds the others at their fitted values, which compensate each other; on the fleet's logs
(benchmarks/fleet.py) a single coordinate moved from the fit to its *true* value made the
held-out NRMSE up to 4.4 times the best fit's, while the contradictions this check is for -- a
break-away force of kilonewtons, a valve at half or twice its conductance, a b of 0.95, a
constant pressure drift of 1e5 Pa/s -- gave 10 to 100 times. ``FLOOR`` (0.3 % of a signal's
range) keeps a near-perfect fit from making every end fail on sensor noise.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.contracts.model import ModelConfig
from pneutune.control.sim.model_box import Coordinate, corner, plant_from_values, uncertainty_box

from .dataset import Dataset
from .validation import validate

#: An end may fit the held-out log this many times worse than the best fit ...
FACTOR = 5.0
#: ... plus this much NRMSE (a fraction of each signal's range).
FLOOR = 3.0e-3
#: Halvings of an end's distance from nominal before it is left at the last one.
BISECTIONS = 5
#: Values of a valve's other parameter (b for C, C for b) tried when replaying an end.
PARTNER_POINTS = 5
#: Halvings at most to make a corner pass.
CORNER_STEPS = 24
#: A failing corner is halved only if the corner of every range shrunk to this fraction passes
#: (module docstring): 4 halvings of every coordinate at once.
NEAR_FRACTION = 1.0 / 16.0
#: Halvings at most of one range for one corner, so that no range ends below NEAR_FRACTION of
#: itself; when the greedy cuts run out, every range of the corner is scaled alike instead.
MAX_HALVINGS = 4
#: Bisections (geometric, between NEAR_FRACTION and 1) for that common scale.
UNIFORM_BISECTIONS = 4
SIGNALS = ("x", "p_a", "p_b")
#: Validation windows of the cross-check [s]: shorter than the validation's 2 s, so that an
#: open-loop replay of a closed-loop log does not let a small flow error drift for seconds.
WINDOW = 0.5


@dataclass(frozen=True)
class EndCheck:
    """One range end (or corner) checked against the log.

    Attributes
    ----------
    key : str
        Coordinate key path, or ``corner:slow`` / ``corner:fast``.
    end : str
        ``low`` or ``high`` (``corner`` for a corner).
    value : float
        The end checked (for a corner: 1.0, the whole box).
    nrmse : dict
        NRMSE per signal at that end.
    kept : float
        The end after the check (equal to ``value`` when it passed; for a corner 1.0 if it
        passed as it was, 0.0 if ranges were narrowed).
    """

    key: str
    end: str
    value: float
    nrmse: dict[str, float]
    kept: float

    @property
    def shrunk(self) -> bool:
        """Whether the log ruled the end out."""
        return self.kept != self.value

    def worst(self, best: Mapping[str, float]) -> str:
        """The signal that ruled the end out, as ``signal NRMSE a vs best b``."""
        s = max(SIGNALS, key=lambda k: self.nrmse[k] / max(best[k], 1e-12))
        return f"{s} NRMSE {self.nrmse[s]:.3g} vs {best[s]:.3g}"


@dataclass(frozen=True)
class CrossCheck:
    """The result of :func:`cross_check`.

    Attributes
    ----------
    best : dict
        NRMSE of the nominal model per signal.
    checks : tuple of EndCheck
        Every end and corner checked, in order.
    box : dict
        Key path -> (lo, hi) after the check (every coordinate).
    factor, floor : float
        The acceptance rule used.
    corner_keys : dict
        Per corner (``corner:slow``, ``corner:fast``), the coordinates halved to make it pass.
    rough : dict
        The corners that failed even at :data:`NEAR_FRACTION` of the ranges, with the NRMSE
        there; they narrowed nothing.
    scaled : dict
        The corners whose greedy cuts ran out, with the common scale every range of the corner
        was given instead.
    """

    best: dict[str, float]
    checks: tuple[EndCheck, ...]
    box: dict[str, tuple[float, float]]
    factor: float = FACTOR
    floor: float = FLOOR
    corner_keys: dict[str, tuple[str, ...]] = field(default_factory=dict)
    rough: dict[str, dict[str, float]] = field(default_factory=dict)
    scaled: dict[str, float] = field(default_factory=dict)

    def passes(self, nrmse: Mapping[str, float]) -> bool:
        """Whether ``nrmse`` reproduces the log well enough."""
        return all(nrmse[s] <= self.factor * self.best[s] + self.floor for s in SIGNALS)

    def notes(self) -> list[str]:
        """One sentence per end the log ruled out."""
        out = []
        for c in self.checks:
            if not c.shrunk:
                continue
            if c.end == "corner":
                keys = self.corner_keys.get(c.key, ())
                how = (f"every range of it scaled to {self.scaled[c.key]:.3g} of itself "
                       "about nominal" if c.key in self.scaled else "narrowed toward nominal")
                out.append(f"cross-check: the {c.key.split(':')[1]} corner of the ranges "
                           f"misfits the held-out log ({c.worst(self.best)}); {how}: "
                           f"{', '.join(keys)}")
            else:
                out.append(f"cross-check: {c.key} = {c.value:.4g} ({c.end} end) misfits the "
                           f"held-out log ({c.worst(self.best)}); that end moved to "
                           f"{c.kept:.4g}")
        for key, near in self.rough.items():
            s = max(SIGNALS, key=lambda k: near[k] / max(self.best[k], 1e-12))
            out.append(f"cross-check: the {key.split(':')[1]} corner misfits the held-out log "
                       f"even with every range at {NEAR_FRACTION:g} of itself ({s} NRMSE "
                       f"{near[s]:.3g} vs {self.best[s]:.3g}): the replay is not smooth in the "
                       "parameters there, so that corner narrows no range")
        return out


def _nrmse(data: Dataset, held: np.ndarray, model: ModelConfig, values: dict[str, float],
           label: str) -> dict[str, float]:
    plant = plant_from_values(model, values, 1, label)
    return dict(validate(data, held, plant, window=WINDOW).nrmse)


def cross_check(data: Dataset, held: np.ndarray, model: ModelConfig,
                keys: Collection[str] | None = None, factor: float = FACTOR,
                floor: float = FLOOR) -> CrossCheck:
    """Check the range ends and both corners of ``model`` against the held-out log.

    Parameters
    ----------
    data : Dataset
        The log (at the control instants, as the validation uses it).
    held : ndarray of bool
        The held-out samples.
    model : ModelConfig
        The identified model with its ranges.
    keys : collection of str, optional
        The coordinates to check (default: all); the corners move only these.
    factor, floor : float
        Acceptance rule (module docstring).

    Returns
    -------
    CrossCheck
    """
    coords = uncertainty_box(model)
    nominal = {c.key: c.nominal for c in coords}
    best = _nrmse(data, held, model, nominal, "nominal")
    checked = {c.key for c in coords} if keys is None else set(keys)
    rule = CrossCheck(best, (), {}, factor, floor)
    by_key = {c.key: c for c in coords}

    def replay(key: str, value: float, label: str) -> dict[str, float]:
        """NRMSE with ``key`` at ``value``, the rest nominal; for a valve's C or b, the best
        over its partner's range (C and b of one valve trade off on subsonic flow)."""
        values = {**nominal, key: value}
        partner = _partner(key)
        if partner not in by_key:
            return _nrmse(data, held, model, values, label)
        p = by_key[partner]
        best: dict[str, float] | None = None
        for q in np.linspace(p.low, p.high, PARTNER_POINTS):
            nr = _nrmse(data, held, model, {**values, partner: float(q)}, label)
            if best is None or _score(nr, rule) < _score(best, rule):
                best = nr
        return best if best is not None else {}

    checks: list[EndCheck] = []
    box: dict[str, tuple[float, float]] = {}
    shrunk_keys: dict[str, list[str]] = {}
    corner_keys: dict[str, tuple[str, ...]] = {}
    rough: dict[str, dict[str, float]] = {}
    scaled: dict[str, float] = {}
    for c in coords:
        ends = {"low": c.low, "high": c.high}
        for end, value in ends.items():
            if value == c.nominal or c.key not in checked:
                continue
            nr = replay(c.key, value, f"{c.key}:{end}")
            kept = value
            if not rule.passes(nr):
                kept = c.nominal
                frac = 1.0
                for _ in range(BISECTIONS):
                    frac *= 0.5
                    cand = c.nominal + frac * (value - c.nominal)
                    if rule.passes(replay(c.key, cand, f"{c.key}:{end}")):
                        kept = cand
                        break
                else:
                    kept = cand  # the smallest step: a range never collapses to a point
            ends[end] = kept
            checks.append(EndCheck(c.key, end, value, nr, kept))
        box[c.key] = (ends["low"], ends["high"])
    for slow in (True, False):
        label = f"corner:{'slow' if slow else 'fast'}"
        first = _nrmse(data, held, model, _corner_values(coords, box, slow, checked, nominal,
                                                         1.0), label)
        if not rule.passes(first):
            near = _nrmse(data, held, model, _corner_values(coords, box, slow, checked, nominal,
                                                            NEAR_FRACTION), label)
            if not rule.passes(near):
                rough[label] = near
                checks.append(EndCheck(label, "corner", 1.0, first, 1.0))
                continue
        nr = first
        before = dict(box)
        halved: dict[str, int] = {}
        for _ in range(CORNER_STEPS):
            if rule.passes(nr):
                break
            vals = _corner_values(coords, box, slow, checked, nominal, 1.0)
            # greedy: halve the range of the coordinate whose return to nominal helps most
            moved = [k for k in vals if vals[k] != nominal[k] and halved.get(k, 0) < MAX_HALVINGS]
            if not moved:
                break
            k = min(moved, key=lambda k: _score(
                _nrmse(data, held, model, {**vals, k: nominal[k]}, label), rule))
            lo, hi = box[k]
            box[k] = (nominal[k] + 0.5 * (lo - nominal[k]), nominal[k] + 0.5 * (hi - nominal[k]))
            shrunk_keys.setdefault(label, []).append(k)
            halved[k] = halved.get(k, 0) + 1
            nr = _nrmse(data, held, model, _corner_values(coords, box, slow, checked, nominal,
                                                          1.0), label)
        if not rule.passes(nr):  # the greedy cuts ran out: scale every range of it alike
            box.update(before)
            ok, bad = NEAR_FRACTION, 1.0
            for _ in range(UNIFORM_BISECTIONS):
                mid = math.sqrt(ok * bad)
                trial = _corner_values(coords, box, slow, checked, nominal, mid)
                if rule.passes(_nrmse(data, held, model, trial, label)):
                    ok = mid
                else:
                    bad = mid
            moved = [k for k in checked if k in box and box[k] != (nominal[k], nominal[k])]
            for k in moved:
                lo, hi = box[k]
                box[k] = (nominal[k] + ok * (lo - nominal[k]), nominal[k] + ok * (hi - nominal[k]))
            shrunk_keys[label] = sorted(moved)
            scaled[label] = ok
        checks.append(EndCheck(label, "corner", 1.0, first, 1.0 if label not in
                               shrunk_keys else 0.0))
        corner_keys[label] = tuple(dict.fromkeys(shrunk_keys.get(label, ())))
    return CrossCheck(best, tuple(checks), box, factor, floor, corner_keys, rough, scaled)


def _corner_values(coords: tuple[Coordinate, ...], box: Mapping[str, tuple[float, float]],
                   slow: bool, checked: Collection[str], nominal: Mapping[str, float],
                   fraction: float) -> dict[str, float]:
    """The slow or fast corner of ``box`` with every range scaled about its nominal value by
    ``fraction``, moving the ``checked`` coordinates only."""
    scaled = box if fraction == 1.0 else {
        k: (nominal[k] + fraction * (lo - nominal[k]), nominal[k] + fraction * (hi - nominal[k]))
        for k, (lo, hi) in box.items()}
    return {k: (v if k in checked else nominal[k])
            for k, v in corner(_shrunk_coords(coords, scaled), slow).items()}


def _partner(key: str) -> str:
    """The coordinate that trades off with ``key`` (a valve's b for its C and back), else ''."""
    if key.startswith("valves.") and key[-2:] in (".C", ".b"):
        return key[:-1] + ("b" if key.endswith("C") else "C")
    return ""


def _score(nrmse: Mapping[str, float], rule: CrossCheck) -> float:
    """How far a replay is from passing (the worst signal's NRMSE over its allowance)."""
    return max(nrmse[s] / (rule.factor * rule.best[s] + rule.floor) for s in SIGNALS)


def _shrunk_coords(coords: tuple[Coordinate, ...], box: Mapping[str, tuple[float, float]]
                   ) -> tuple[Coordinate, ...]:
    from dataclasses import replace

    return tuple(replace(c, low=box[c.key][0], high=box[c.key][1]) for c in coords)


def narrowed_model(model: ModelConfig, box: Mapping[str, tuple[float, float]]) -> ModelConfig:
    """``model`` with its ranges set to ``box`` where ``box`` is narrower.

    Each coordinate goes where :func:`~pneutune.control.sim.model_box.uncertainty_box` reads it:
    the mass into ``mass_range`` and θ1; F_n, D_a, D_b into θ2, θ5, θ6; the friction
    coordinates into ``friction.ranges``; the valves into their ``C_min`` ... ``b_max``. θ3 and
    θ4 (the smooth model's b_v and A_f) keep their boxes, which the controller's projection uses.

    Parameters
    ----------
    model : ModelConfig
    box : mapping
        Key path -> (lo, hi).

    Returns
    -------
    ModelConfig
    """
    data: dict[str, Any] = model.to_dict()
    th = data["theta"]
    theta_index = {"mass": 0, "disturbance.F_n": 1, "disturbance.D_a": 4, "disturbance.D_b": 5}

    def meet(old: list[float], new: tuple[float, float]) -> list[float]:
        return [max(old[0], new[0]), min(old[1], new[1])]

    for key, (lo, hi) in box.items():
        if key in theta_index:
            i = theta_index[key]
            th["min"][i], th["max"][i] = meet([th["min"][i], th["max"][i]], (lo, hi))
            if key == "mass" and data.get("mass_range") is not None:
                data["mass_range"] = meet(data["mass_range"], (lo, hi))
        elif key.startswith("friction."):
            name = key.split(".", 1)[1]
            ranges = data["friction"].get("ranges")
            if ranges is not None:
                ranges[name] = meet(ranges[name], (lo, hi))
        elif key.startswith("valves."):
            _, valve, name = key.split(".")
            v = data["valves"][valve]
            v[f"{name}_min"], v[f"{name}_max"] = meet([v[f"{name}_min"], v[f"{name}_max"]],
                                                      (lo, hi))
    return ModelConfig.model_validate(data)


__all__ = ["BISECTIONS", "FACTOR", "FLOOR", "CrossCheck", "EndCheck", "cross_check",
           "narrowed_model"]
