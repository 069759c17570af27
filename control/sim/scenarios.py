"""Reference trajectories and the closed-loop scenarios of the paper's Sec. 5 (Table 1, Fig. 17).

All trajectories are centred at mid-stroke (23.5 mm on the paper's rig) and are
returned as ``(N, 3)`` arrays of ``[x_r, v_r, a_r]`` in m, m/s, m/s^2.

The paper does not give the smooth square's edges: here each edge is a quintic
``s(τ) = 10τ³ - 15τ⁴ + 6τ⁵`` of 0.8 s (peak speed 1.875·2A/0.8 = 82 mm/s and peak acceleration
5.77·2A/0.8² = 0.32 m/s² for A = 17.5 mm, well within the valves' flow), holding each level for
the remaining 0.2 s of the half period. It starts at the low level, where the piston rests.

On an axis too short for Table 1's 17.5 mm (a stroke under about 35 mm), :func:`fit_to_limits`
scales every reference about mid-stroke so that it spans :data:`STROKE_SHARE` of the room, and
Table 1's figures with it (:meth:`Scenario.scaled`); where the references fit, they are the
paper's, unchanged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pneutune.control.errors import ExperimentError

AMPLITUDE = 0.0175  #: Table 1 amplitude [m]
EDGE = 0.8  #: smooth-square edge duration [s]
#: The paper's indices E_p and E_rms cover this many reference periods at the end of a run.
METRIC_PERIODS = 3
#: Share of the room between mid-stroke and the nearer limit that a reference scaled to a short
#: axis spans: that of Table 1's amplitude on the paper's rig (17.5 of the 25 mm from its
#: mid-stroke to either stroke end, plant.yaml's default -1.5 and 48.5 mm), so a short axis keeps
#: the paper's clearance to its stroke ends in proportion.
STROKE_SHARE = AMPLITUDE / 0.025
#: The smallest amplitude a reference is scaled to [m]: a shorter stroke is refused.
MIN_AMPLITUDE = 1.0e-3


def metric_window(period: float, Ts: float) -> int:
    """Samples of the indices' window: the last :data:`METRIC_PERIODS` reference periods.

    Parameters
    ----------
    period : float
        Period of the reference [s].
    Ts : float
        Sampling period [s].

    Returns
    -------
    int
    """
    return round(METRIC_PERIODS * period / Ts)


def sine(t: np.ndarray, center: float, amplitude: float, freq: float) -> np.ndarray:
    """``center + amplitude sin(2π f t)`` with its derivatives, shape (N, 3)."""
    w = 2.0 * np.pi * freq
    return np.column_stack([center + amplitude * np.sin(w * t), amplitude * w * np.cos(w * t),
                            -amplitude * w * w * np.sin(w * t)])


def quintic(t: np.ndarray, duration: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``s(τ) = 10τ³ - 15τ⁴ + 6τ⁵`` (τ = t / duration, clipped to [0, 1]) from 0 to 1 and its
    first two time derivatives, which are 0 from ``duration`` on [-, 1/s, 1/s²]."""
    z = np.clip(t / duration, 0.0, 1.0)
    s = z**3 * (10.0 - 15.0 * z + 6.0 * z * z)
    ds = np.where(t < duration, 30.0 * z**2 * (1.0 - z) ** 2 / duration, 0.0)
    dds = np.where(t < duration, 60.0 * z * (1.0 - z) * (1.0 - 2.0 * z) / duration**2, 0.0)
    return s, ds, dds


def smooth_square(t: np.ndarray, center: float, amplitude: float, freq: float,
                  edge: float = EDGE) -> np.ndarray:
    """Square wave with quintic edges of ``edge`` seconds, low level first, shape (N, 3)."""
    period = 1.0 / freq
    half = 0.5 * period
    if not 0.0 < edge <= half:
        raise ExperimentError(f"the edge must be in (0, half period = {half} s], got {edge}")
    tau = np.mod(t, period)
    rising = tau < half
    s, ds, dds = quintic(np.where(rising, tau, tau - half), edge)
    sign = np.where(rising, 1.0, -1.0)
    x = center + amplitude * sign * (2.0 * s - 1.0)
    return np.column_stack([x, 2.0 * amplitude * sign * ds, 2.0 * amplitude * sign * dds])


def move_and_hold(t: np.ndarray, x_from: float, x_to: float, move_s: float) -> np.ndarray:
    """A quintic move from ``x_from`` to ``x_to`` in ``move_s`` seconds, then a hold, (N, 3).

    The edge of :func:`smooth_square` (peak speed 1.875·|Δx|/``move_s``), starting at t = 0;
    deploy's homing move (``deploy --home``,
    :func:`pneutune.control.rig.homing.homing_move`).
    """
    if not move_s > 0.0:
        raise ExperimentError(f"the move must last > 0 s, got {move_s}")
    t = np.asarray(t, dtype=np.float64)
    s, ds, dds = quintic(t, move_s)
    dx = x_to - x_from
    return np.column_stack([np.where(t < move_s, x_from + dx * s, x_to), dx * ds, dx * dds])


@dataclass(frozen=True)
class Scenario:
    """A closed-loop test case.

    Attributes
    ----------
    name : str
        Command-line name.
    description : str
        One line for tables.
    duration : float
        [s].
    period : float
        Period of the reference [s]; the metrics cover the last three.
    reference : callable
        ``(t, center) -> (N, 3)`` array of ``[x_r, v_r, a_r]``.
    plant_updates : dict
        Changes to the plant (payload, force steps) deep-merged into plant.yaml.
    paper : (float, float) or None
        The paper's Table 1 (E_p, E_rms) in mm, measured on the rig; of a scaled scenario,
        those figures times its ``scale``.
    scale : float
        The reference's amplitude against the paper's (:meth:`scaled`); 1 for Table 1's.
    """

    name: str
    description: str
    duration: float
    period: float
    reference: Callable[[np.ndarray, float], np.ndarray]
    plant_updates: dict[str, Any] = field(default_factory=dict)
    paper: tuple[float, float] | None = None
    scale: float = 1.0

    def samples(self, Ts: float) -> int:
        """Number of samples at period ``Ts``."""
        return round(self.duration / Ts)

    def reference_array(self, Ts: float, center: float) -> np.ndarray:
        """The reference at every sample, (N, 3)."""
        return self.reference(np.arange(self.samples(Ts)) * Ts, center)

    def scaled(self, factor: float) -> Scenario:
        """The same scenario with its reference's excursion from the centre (and so its speed
        and acceleration) times ``factor``, and Table 1's figures times ``factor`` too.

        Tracking errors grow with the speed and acceleration they follow, so the figures are
        scaled with the amplitude (an assumption: the paper measured one amplitude). The plant
        changes (payload, force steps) stay. ``factor`` 1 returns the scenario itself.

        Raises
        ------
        ExperimentError
            ``factor`` not in (0, 1].
        """
        if not 0.0 < factor <= 1.0:
            raise ExperimentError(f"a scenario's scale must be in (0, 1], got {factor}")
        if factor == 1.0:
            return self
        base = self.reference

        def reference(t: np.ndarray, center: float) -> np.ndarray:
            r = base(t, center)
            return np.column_stack([center + factor * (r[:, 0] - center), factor * r[:, 1],
                                    factor * r[:, 2]])

        paper = None if self.paper is None else (factor * self.paper[0], factor * self.paper[1])
        scale = self.scale * factor
        return dataclasses.replace(
            self, reference=reference, paper=paper, scale=scale,
            description=f"{self.description} (amplitude x{scale:.3f})")

    def excursion(self, Ts: float) -> float:
        """The reference's largest distance from its centre [m]."""
        return float(np.max(np.abs(self.reference_array(Ts, 0.0)[:, 0])))


def _sine_ref(freq: float) -> Callable[[np.ndarray, float], np.ndarray]:
    return lambda t, c: sine(t, c, AMPLITUDE, freq)


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("sine-0.5hz", "17.5 sin(πt) mm, M = 1.05 kg", 12.0, 2.0, _sine_ref(0.5),
                 {}, (0.42, 0.19)),
        Scenario("sine-0.75hz", "17.5 sin(1.5πt) mm, M = 1.05 kg", 12.0, 1.0 / 0.75,
                 _sine_ref(0.75), {}, (0.53, 0.23)),
        Scenario("sine-0.5hz-heavy", "17.5 sin(πt) mm, +1.136 kg payload (M ≈ 2.18 kg)", 12.0,
                 2.0, _sine_ref(0.5), {"payload": 1.136}, (0.45, 0.20)),
        Scenario("square-0.5hz", "smooth square 0.5 Hz, 17.5 mm, 0.8 s quintic edges", 12.0,
                 2.0, lambda t, c: smooth_square(t, c, AMPLITUDE, 0.5), {}, (0.38, 0.16)),
        Scenario("disturbance-0.5hz", "17.5 sin(πt) mm; 30 N at 7.6 s, 80 N at 9.8 s, 0 at 11.9 s",
                 14.0, 2.0, _sine_ref(0.5),
                 {"disturbance": {"force_steps": [[7.6, 30.0], [9.8, 80.0], [11.9, 0.0]]}},
                 None),
    )
}
#: Scenario groups accepted by ``--scenario``.
GROUPS: dict[str, tuple[str, ...]] = {
    "table1": ("sine-0.5hz", "sine-0.75hz", "sine-0.5hz-heavy", "square-0.5hz"),
    "all": tuple(SCENARIOS),
}


def fits(scenario: Scenario, Ts: float, center: float, x_min: float, x_max: float) -> bool:
    """Whether the scenario's reference about ``center`` lies within [``x_min``, ``x_max``]."""
    x_r = scenario.reference_array(Ts, center)[:, 0]
    return bool(x_r.min() >= x_min and x_r.max() <= x_max)


def stroke_scale(scenarios: Sequence[Scenario], Ts: float, center: float, x_min: float,
                 x_max: float) -> float:
    """The factor :func:`fit_to_limits` scales the scenarios by: 1 when every reference about
    ``center`` lies within [``x_min``, ``x_max``], else the one that makes the widest span
    :data:`STROKE_SHARE` of the room between the centre and the nearer limit.

    Parameters
    ----------
    scenarios : sequence of Scenario
        The scenarios to run, all scaled by the one factor (so their figures stay comparable).
    Ts : float
        Sampling period [s].
    center, x_min, x_max : float
        Mid-stroke and the position limits [m].

    Returns
    -------
    float
        In (0, 1].

    Raises
    ------
    ExperimentError
        ``center`` not strictly inside the limits, or a stroke so short that the references
        would span less than :data:`MIN_AMPLITUDE`.
    """
    room = min(x_max - center, center - x_min)
    if not room > 0.0:
        raise ExperimentError(f"mid-stroke {center * 1e3:.2f} mm is not inside the limits "
                              f"[{x_min * 1e3:.2f}, {x_max * 1e3:.2f}] mm")
    if all(fits(sc, Ts, center, x_min, x_max) for sc in scenarios):
        return 1.0
    if STROKE_SHARE * room < MIN_AMPLITUDE:
        raise ExperimentError(
            f"{room * 1e3:.3g} mm either side of mid-stroke within [{x_min * 1e3:.2f}, "
            f"{x_max * 1e3:.2f}] mm is too short for any scenario: they need at least "
            f"{2.0 * MIN_AMPLITUDE / STROKE_SHARE * 1e3:.2f} mm of stroke (a "
            f"{MIN_AMPLITUDE * 1e3:.0f} mm reference)")
    widest = max(sc.excursion(Ts) for sc in scenarios)
    return min(1.0, STROKE_SHARE * room / widest)


def fit_to_limits(scenarios: Sequence[Scenario], Ts: float, center: float, x_min: float,
                  x_max: float) -> tuple[list[Scenario], float]:
    """The scenarios as they run between these limits: unchanged where every reference fits,
    else all scaled by :func:`stroke_scale` (:meth:`Scenario.scaled`).

    Returns
    -------
    scenarios : list of Scenario
    factor : float
        The scale applied, 1 when none.
    """
    factor = stroke_scale(scenarios, Ts, center, x_min, x_max)
    return [sc.scaled(factor) for sc in scenarios], factor


def resolve_scenarios(name: str) -> list[Scenario]:
    """Scenarios for a ``--scenario`` value: a name, ``table1``, ``all``, or a comma-separated
    list of these (in the order given, each scenario once).

    Raises
    ------
    ExperimentError
        Unknown name (the message lists the known ones).
    """
    out: list[Scenario] = []
    known = ", ".join([*SCENARIOS, *GROUPS])
    for part in (p.strip() for p in name.split(",")):
        if part in GROUPS:
            found = [SCENARIOS[n] for n in GROUPS[part]]
        elif part in SCENARIOS:
            found = [SCENARIOS[part]]
        else:
            raise ExperimentError(f"unknown scenario {part!r}; expected one of: {known}, or a "
                                  f"comma-separated list of them")
        out += [sc for sc in found if sc not in out]
    return out
