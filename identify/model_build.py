"""model.yaml from the fits: its document, the ranges and their bases, and the plant.

* :func:`build_plant`: the identified model as a simulated rig (the nominal values), which the
  validation simulates;
* :func:`build_model`: model.yaml's document (contract 3): each valve's C and b with their
  ranges and PWM curve, the friction and its ranges (F_S from the stick and break-away events
  of :mod:`.stiction`), the mass, θ, the sensors' noise, the loop delay, and a basis per
  range; and the :class:`Ranges` the cross-check tests (those that are not a statistical fit).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pneutune.control.constants import MODEL_SCHEMA, VALVES, WEAK_B_SPAN
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig

from .bounds import ThetaBounds, Z
from .dataset import Dataset, display_names
from .friction_choice import STICTION_PRIOR_MAX
from .friction_prior import PriorFriction
from .motion import FrictionIdentifier
from .sources import Sources, from_logs
from .stiction import StictionBounds, force_noise_std, position_noise_std, stiction_bounds
from .validation import Validation
from .valve_timing import LOOP_DELAY_TOLERANCE
from .valves import FULL_OPEN_PIN_S, ValveIdentifier

#: Relative half-width of C for a valve never run at full duty whose C comes from the timing
#: stage (the exact opening per sample).
CLOSED_LOOP_C_ERROR = 0.12
#: Smallest half-width of b for a valve never run at full duty [-].
PARTIAL_B_ERROR = 0.12
#: Prior ranges of the Stribeck velocity [m/s] and exponent [-] of pneumatic cylinder seals,
#: joined with the fit's: both are weakly identified from samples that miss the stiction peak.
V_S_PRIOR, ALPHA_PRIOR = (1.0e-3, 1.0e-2), (0.5, 3.0)

#: Range of a valve's conductance that no log opens, as a factor either side of the geometric
#: mean of the conductances the logs do identify (the valves of one rig are mostly of one
#: type): a prior.
UNOPENED_C_FACTOR = 4.0


def build_plant(data: Dataset, valves: ValveIdentifier, friction: FrictionIdentifier,
                mass: float) -> PlantConfig:
    """The identified model as a simulated rig: the nominal values, no ranges.

    Parameters
    ----------
    data : Dataset
        The pooled logs (their rig).
    valves : ValveIdentifier
        The fitted valves: C, b, switching, loop delay, leak, D_a, D_b.
    friction : FrictionIdentifier
        The friction fit (or its prior, which has the same attributes).
    mass : float
        The moving mass [kg].

    Returns
    -------
    PlantConfig
    """
    period = 1.0 / data.rig.pwm_hz
    vdict = {}
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]),
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
    f = friction
    return PlantConfig.model_validate({
        "io": {"delay": float(valves.loop_delay_ or 0.0)},
        "rig": data.rig.model_dump(), "mass": float(mass), "payload": 0.0,
        "friction": {"F_S": f.F_S_, "F_C": f.F_C_, "v_s": f.v_s_, "alpha": f.alpha_,
                     "b_v": f.b_v_},
        "valves": vdict, "leak": {"C": min(valves.leak_C_, 1e-7)},
        "disturbance": {"F_n": f.F_n_, "D_a": float(valves.D_[0]), "D_b": float(valves.D_[1])},
    })


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


def build_model(data: Dataset, logs: Dataset | Sequence[Dataset], valves: ValveIdentifier,
                friction: FrictionIdentifier | PriorFriction, mass: float,
                mass_range: tuple[float, float], mass_basis: str, theta: ThetaBounds,
                validation: Validation, notes: list[str], period: float,
                sources: Sources | None = None) -> tuple[ModelConfig, Ranges]:
    """model.yaml's document and the ranges' bases.

    Parameters
    ----------
    data : Dataset
        The pooled logs at the control instants (their rig).
    logs : Dataset or sequence of Dataset
        The log, or every log, at its own sampling period: the sources, the stiction events
        and the sensors' noise.
    valves : ValveIdentifier
        The fitted valves.
    friction : FrictionIdentifier or PriorFriction
        The friction fit, or its prior.
    mass : float
        The moving mass [kg].
    mass_range : (float, float)
        Its range [kg].
    mass_basis : str
        The basis of the mass range.
    theta : ThetaBounds
        θ's nominal, bounds and bases.
    validation : Validation
        The held-out fit (its NRMSE).
    notes : list of str
        The notes model.yaml holds; appended to (stiction and friction notes).
    period : float
        PWM period [s].
    sources : Sources, optional
        Which logs each fit drew on (several logs only).

    Returns
    -------
    (ModelConfig, Ranges)
        model.yaml's document (contract 3), and the ranges' bases with the coordinates the
        cross-check tests.
    """
    datasets = [logs] if isinstance(logs, Dataset) else list(logs)
    names = display_names([d.path for d in datasets])
    log = datasets[0]
    vdict = {}
    basis: dict[str, str] = {}
    unsupported: set[str] = set()
    unopened = getattr(valves, "unopened_", np.zeros(4, dtype=bool))
    opened_C = valves.C_[~unopened] if np.any(~unopened) else valves.C_
    C_ref = float(np.exp(np.mean(np.log(opened_C))))
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        if unopened[i]:
            # never commanded open in any log: C and b are a prior, checked against the logs
            c_lo, c_hi = C_ref / UNOPENED_C_FACTOR, min(C_ref * UNOPENED_C_FACTOR, 1e-6)
            basis[f"valves.{name}.C"] = (
                f"prior: never commanded open in the logs; within a factor "
                f"{UNOPENED_C_FACTOR:g} of the geometric mean {C_ref:.4g} m^3/(s Pa) of the "
                f"conductances the logs identify")
            basis[f"valves.{name}.b"] = "prior: never commanded open in the logs; 0-0.95"
            unsupported |= {f"valves.{name}.C", f"valves.{name}.b"}
            vdict[name] = {"C": C_ref, "b": float(np.clip(valves.b_[i], 0.0, 0.95)),
                           "C_min": c_lo, "C_max": c_hi, "b_min": 0.0, "b_max": 0.95,
                           "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                           "min_pulse": sw["min_pulse"]}
            v_duty, v_ratio = _curve_points(valves.knots_, valves.curves_[i])
            vdict[name]["pwm"] = {"duty": v_duty, "ratio": v_ratio}
            continue
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
        if sources is not None:
            c_basis += from_logs(sources.valve[i])
            b_basis += from_logs(sources.valve[i])
        basis[f"valves.{name}.C"] = c_basis
        basis[f"valves.{name}.b"] = b_basis
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]), "C_min": c_lo,
                       "C_max": c_hi, "b_min": b_lo, "b_max": b_hi,
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
        if valves.min_pulse_range_ is not None:  # set with the timing stage
            mp_lo, mp_hi = valves.min_pulse_range_[i]
            vdict[name]["min_pulse_min"], vdict[name]["min_pulse_max"] = mp_lo, mp_hi
            basis[f"valves.{name}.min_pulse"] = (
                f"data: the minimum pulses whose chamber fit is within 1 + {Z:g}^2/n of the "
                f"one found (n windows): {mp_lo * 1e3:.2f}-{mp_hi * 1e3:.2f} ms")
        v_duty, v_ratio = _curve_points(valves.knots_, valves.curves_[i])
        vdict[name]["pwm"] = {"duty": v_duty, "ratio": v_ratio}
    f = friction
    sd = f.std_
    prior = isinstance(f, PriorFriction)
    F_C_range = f.F_C_range_ if prior else _range(f.F_C_, sd["F_C"], 0.1)
    b_v_range = f.b_v_range_ if prior else _range(f.b_v_, sd["b_v"], 0.05)
    F_S, F_S_range, basis["friction.F_S"] = _stiction_range(
        log if len(datasets) == 1 else datasets, f, F_C_range, theta, notes, names)
    unsupported |= {"friction.F_S", "friction.v_s", "friction.alpha"}
    fsrc = sources.friction if sources is not None else ""
    if prior:
        basis["friction.F_C"] = basis["friction.b_v"] = f.basis_
        # b_v and F_n are replayed against the log; the Coulomb level is not: on a log whose
        # piston hardly moves the corners cannot tell it from the viscous term, and halving its
        # range toward the prior's geometric mean (88 N) cut off the truth (50 N) on
        # data/run.mcap cut before its ramps
        unsupported |= {"friction.b_v", "disturbance.F_n"}
    else:
        basis["friction.F_C"] = (f"statistics: ±3.29 s.e. ({sd['F_C']:.3g} N), at least ±10 %"
                                 + fsrc)
        basis["friction.b_v"] = (f"statistics: ±3.29 s.e. ({sd['b_v']:.3g} N s/m), at least "
                                 f"±5 %" + fsrc)
    basis["friction.v_s"] = (f"prior {V_S_PRIOR[0] * 1e3:g}-{V_S_PRIOR[1] * 1e3:g} mm/s "
                             "joined with the fit's ±3.29 s.e. (at least ±50 %): weakly "
                             "identified" + fsrc)
    basis["friction.alpha"] = (f"prior {ALPHA_PRIOR[0]:g}-{ALPHA_PRIOR[1]:g} joined with the "
                               "fit's ±3.29 s.e. (at least ±50 %): weakly identified" + fsrc)
    basis["mass"] = mass_basis
    if "prior" in mass_basis:
        unsupported.add("mass")
    for key, i in (("disturbance.F_n", 1), ("disturbance.D_a", 4), ("disturbance.D_b", 5)):
        basis[key] = ("" if prior and i == 1 else "statistics: ") + theta.basis[i]
    for ch, key in enumerate(("disturbance.D_a", "disturbance.D_b")):
        if valves.D_closed_[ch] is False:
            unsupported.add(key)
            basis[key] = ("weakly identified: the chamber's valves are never all shut, "
                          "widened to cover zero")
    duty, ratio = _curve_points(valves.knots_, valves.curve_)
    src = [{"log": d.path, "sha256": d.sha256, "duration_s": d.duration,
            **({"run": d.run_record} if d.run_record is not None else {})} for d in datasets]
    data_dict = {
        "schema": MODEL_SCHEMA,
        # one log: the mapping outside readers know; several: one mapping per log
        "source": src[0] if len(src) == 1 else src,
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
                "b_v": list(b_v_range),
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
        "sensors": _noise_levels(datasets),
        "basis": basis,
        "notes": notes,
    }
    data_dict.update(_loop_delay(valves, vdict, basis))
    return ModelConfig.model_validate(data_dict), Ranges(basis, frozenset(unsupported))



def _stiction_range(logs: Dataset | Sequence[Dataset], friction: FrictionIdentifier,
                    F_C_range: tuple[float, float], theta: ThetaBounds, notes: list[str],
                    names: Sequence[str] = ()) -> tuple[float, tuple[float, float], str]:
    """F_S nominal, range and basis: stick and break-away events bound F_S from both sides
    (:mod:`.stiction`); where the log has none, a prior (F_C .. STICTION_PRIOR_MAX F_C).

    With several logs (``names`` theirs) each is read at its own sampling period, and the
    highest lower bound and the lowest upper bound are kept, each naming its log.
    """
    many = not isinstance(logs, Dataset)
    datasets = list(logs) if many else [logs]
    F_n = float(theta.nominal[1])
    F_n_half = 0.5 * float(theta.hi[1] - theta.lo[1])
    found: list[tuple[str, StictionBounds]] = []
    for j, log in enumerate(datasets):
        where = f" in {names[j]}" if many else ""
        try:
            found.append((where, stiction_bounds(log, F_n, F_n_half,
                                                 b_v_max=float(theta.hi[2]),
                                                 m_max=float(theta.hi[0]))))
        except (ValueError, np.linalg.LinAlgError) as exc:  # too little data for the events
            notes.append(f"friction: no stick or break-away events could be read{where} "
                         f"({exc})")
    lows = [(w, b) for w, b in found if b.lo is not None]
    highs = [(w, b) for w, b in found if b.hi is not None and np.isfinite(b.hi)]
    lo_w, sb_lo = max(lows, key=lambda wb: wb[1].lo) if lows else ("", None)
    hi_w, sb_hi = min(highs, key=lambda wb: wb[1].hi) if highs else ("", None)
    sb = found[0][1] if found and not many else None
    lo = F_C_range[0]
    hi = STICTION_PRIOR_MAX * F_C_range[1]
    parts = []
    if sb_lo is not None and sb_lo.lo > lo:
        lo = float(sb_lo.lo)
        e = sb_lo.lo_event
        parts.append((f"at rest under {abs(e.F):.4g} N at t = {e.t:.3f} s" if e else
                      f"at rest under {lo:.4g} N") + lo_w)
    if sb_hi is not None:
        e = sb_hi.hi_event
        parts.append((f"broke away at {abs(e.F):.4g} N at t = {e.t:.3f} s" if e else
                      f"broke away below {sb_hi.hi:.4g} N") + hi_w)
        if sb_hi.hi < hi:
            hi = float(sb_hi.hi)
            kind = "data bound"
        else:
            kind = "prior"
            parts.append(f"the prior F_S <= {STICTION_PRIOR_MAX:g} F_C_max = {hi:.4g} N is "
                         f"tighter than the break-aways ({sb_hi.hi:.4g} N)")
    else:
        kind = "prior"
        notes.append(f"friction: the {'logs show' if many else 'log shows'} no break-away "
                     f"from rest away from the end "
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
    if many:  # each log's events and noise
        sb_text = "; ".join(f"{w.strip()}: {b.basis}" for w, b in found)
    else:
        sb_text = sb.basis if sb is not None else ""
    basis = (f"{kind}: {detail}" + (f"; {sb_text}" if sb_text else "")
             + ("" if kind == "data bound" else f"; F_S <= {STICTION_PRIOR_MAX:g} F_C (prior)"))
    return nominal, (lo, hi), basis



def _loop_delay(valves: ValveIdentifier, vdict: dict[str, dict[str, Any]],
                basis: dict[str, str]) -> dict[str, Any]:
    """model.yaml's ``effects.io.delay`` and ``loop_delay`` from the timing stage (none
    without it), with their bases added to ``basis``.

    ``io.delay`` is the part of the loop delay the valves' delays do not hold: a duty acting
    later than its sample, which the log separates only where it holds both steady duties
    (valve tests) and changing ones (a closed loop). ``loop_delay`` is the whole of it, from a
    written duty to the chamber flow's response: the valves' opening delays plus ``io.delay``.
    """
    if valves.loop_delay_ is None or valves.loop_delay_range_ is None:
        return {}
    d = float(valves.loop_delay_)
    lo, hi = (float(x) for x in valves.loop_delay_range_)
    grid, costs = valves.loop_delay_costs_
    best = (f"best {d * 1e3:g} ms, against which none leaves {costs[0] / costs.min():.3g} "
            f"times the residual" if d > 0.0 else "best none")
    basis["io.delay"] = (
        f"data: the chamber fit's residual over duties acting 0-{grid[-1] * 1e3:g} ms after "
        f"their samples, with the valves' delays as fitted: every delay within "
        f"{LOOP_DELAY_TOLERANCE:.0%} of the best ({best}); the valves' delays hold the rest "
        f"of the loop delay")
    ons = [float(v["delay_on"]) for v in vdict.values()]
    basis["loop_delay"] = (
        "data: the valves' opening delays (shortest to longest) plus io.delay's range: from a "
        "written duty to the chamber flow")
    return {"effects": {"io.delay": {"nominal": d, "range": [lo, hi]}},
            "loop_delay": {"nominal": float(np.mean(ons)) + d,
                           "range": [min(ons) + lo, max(ons) + hi]}}


def _curve_points(knots: np.ndarray, curve: np.ndarray) -> tuple[list[float], list[float]]:
    """The curve as contract-3 points, rounded, starting at (0, 0)."""
    duty = [round(float(k), 6) for k in knots]
    ratio = [round(float(r), 6) for r in np.maximum.accumulate(np.clip(curve, 0.0, 1.0))]
    ratio[0] = 0.0
    return duty, ratio


def _noise_levels(data: Dataset | Sequence[Dataset]) -> dict[str, float]:
    """Sensor noise [m, Pa] from third differences where the signal is smooth at the sample
    scale (:func:`~pneutune.identify.stiction.position_noise_std`: the piston at rest;
    :func:`~pneutune.identify.stiction.force_noise_std`: the chambers with their valves shut, or the
    supply sensor). A smoothing residual would count the PWM ripple of a closed-loop log as
    noise (10 times the truth, measured).

    With several logs, the smallest level any log shows: what a log's estimate fails to
    separate from the signal (ripple, motion) only adds to it."""
    datasets = [data] if isinstance(data, Dataset) else list(data)
    x_noise, p_noise = np.inf, np.inf
    for d in datasets:
        r = d.rig
        sigma_F, _ = force_noise_std(d)
        p_noise = min(p_noise, sigma_F / float(np.hypot(r.A_a, r.A_b)))
        x_noise = min(x_noise, position_noise_std(d.x))
    return {"x_noise": float(min(x_noise, 1e-3)),
            "p_noise": float(min(p_noise, 1e5))}


def _hull(a: tuple[float, float], b: tuple[float, float]) -> list[float]:
    """The smallest interval holding both."""
    return [min(a[0], b[0]), max(a[1], b[1])]


def _range(value: float, sd: float, rel_floor: float, lo_floor: float = 0.0,
           hi_cap: float = np.inf) -> tuple[float, float]:
    half = max(3.29 * sd, rel_floor * abs(value))
    return max(lo_floor, value - half), min(hi_cap, value + half)

