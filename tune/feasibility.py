"""Before a study: every plant draw must be trackable, or the study ends with nothing.

A model's ranges can hold plants that no controller tracks -- a break-away force the log never
showed, a mass at the far end of a prior. A draw like that fails every trial, the pruner has no
complete trial to compare with, and the study ends with nothing. :func:`check_feasibility` runs
before the study and makes sure it cannot:

1. **Reference.** The study's first trial, the paper's gains (Sec. 5.1, clipped to the search
   ranges), is scored on every scenario and draw.
2. **Nominal.** If it fails on the nominal plant (draw 0), up to :data:`N_ALTERNATIVES`
   controllers sampled from the search space (seeded) are tried on the nominal plant; the first
   that tracks every scenario becomes the reference and is enqueued as a trial too. If none
   does, the model's nominal plant cannot be tracked: :class:`InfeasibleModelError`, which the
   command reports as bad input (exit 2).
3. **Narrowing.** While the reference fails on some draw, the coordinates that make that draw
   infeasible are found, in the scenario that failed: those that fail alone (each at the draw's
   value on the nominal plant); if none does, those whose return to nominal alone rescues the
   draw; if none does, every coordinate of the draw that is off nominal. Each culprit's range
   is narrowed on that side to halfway between the nominal value and the draw's value. The
   draws are made again from the narrowed box and checked again, at most :data:`MAX_ROUNDS`
   times; after that the culprits are held at nominal.

The narrowed box is part of the objective's settings (stored with the study, so a resumed run
checks it), and every step is written to report.md and to the controller's provenance. With a
model whose ranges the log supports, nothing is narrowed.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import PneutuneError
from pneutune.control.law.layout import pack
from pneutune.control.sim.closed_loop import (
    STATUS_ABORTED,
    STATUS_UNSTABLE,
    scenario_plant,
    simulate_scenario,
)
from pneutune.control.sim.model_box import Coordinate, plant_from_values, uncertainty_box
from pneutune.control.sim.scenarios import Scenario

from .objective import Evaluation, ObjectiveSettings, TuneObjective
from .plants import PlantDraw
from .space import search_space

#: Controllers tried on the nominal plant when the paper's gains fail it.
N_ALTERNATIVES = 24
#: Narrowing rounds before the culprits are held at their nominal values.
MAX_ROUNDS = 10
#: Units of the plant coordinates, for messages.
UNITS = {"mass": "kg", "friction.b_v": "N s/m", "friction.F_C": "N", "friction.F_S": "N",
         "friction.v_s": "m/s", "friction.alpha": "", "disturbance.F_n": "N",
         "disturbance.D_a": "Pa/s", "disturbance.D_b": "Pa/s"}


class InfeasibleModelError(PneutuneError, ValueError):
    """Even the model's nominal plant cannot be tracked: the model is wrong (bad input)."""


def _unit(key: str) -> str:
    if key.endswith(".C"):
        return "m^3/(s Pa)"
    return UNITS.get(key, "")


def describe(key: str, value: float) -> str:
    """``key = value unit`` for messages."""
    unit = _unit(key)
    return f"{key} = {value:.4g}{' ' + unit if unit else ''}"


def failure_text(status: str, abort_error: float) -> str:
    """What a failed run's status means."""
    if status == STATUS_ABORTED:
        return f"aborted: |e1| exceeded {abort_error * 1e3:g} mm"
    return "unstable: the plant state became non-finite"


@dataclass(frozen=True)
class Narrowing:
    """One narrowing step.

    Attributes
    ----------
    draw, label : int, str
        The draw the reference controller failed.
    scenario, failure : str
        Where and how it failed.
    culprits : tuple of (str, float, bool)
        ``(key, draw value, at a range end)`` of the coordinates that make the draw infeasible.
    alone : bool
        True when each culprit fails alone; False when none did (the culprits are then those
        whose return to nominal rescues the draw, or all of the draw's coordinates).
    ranges : tuple of (str, float, float)
        The culprits' ranges after this step, ``(key, lo, hi)``.
    """

    draw: int
    label: str
    scenario: str
    failure: str
    culprits: tuple[tuple[str, float, bool], ...]
    alone: bool
    ranges: tuple[tuple[str, float, float], ...]

    def sentence(self, reference: str) -> str:
        """One line for report.md and the provenance."""
        if self.alone or len(self.culprits) <= 3:
            vals = ", ".join(describe(k, v) + (" at its range end" if end else "")
                             for k, v, end in self.culprits)
        else:
            vals = (f"no parameter alone, but its {len(self.culprits)} parameters off nominal "
                    f"({', '.join(k for k, _, _ in self.culprits)})")
        how = "alone makes" if self.alone else (
            "with the rest of the draw makes" if len(self.culprits) == 1 else
            "together make")
        new = ", ".join(f"{k} to [{lo:.4g}, {hi:.4g}]" for k, lo, hi in self.ranges)
        return (f"draw {self.draw} ({self.label}): {vals} {how} {reference} fail "
                f"{self.scenario} ({self.failure}); narrowed {new}")


@dataclass(frozen=True)
class Feasibility:
    """What :func:`check_feasibility` found and did.

    Attributes
    ----------
    box : tuple of (str, float, float)
        The narrowed ranges (empty: the model's box is trackable as it is).
    steps : tuple of Narrowing
    reference : str
        ``"the paper's gains"`` or ``"alternative k"`` (a sampled controller).
    reference_params : dict
        The reference's parameters (enqueued as a trial when it is not the paper's).
    paper_failure : str or None
        How the paper's gains fail on the nominal plant, if they do.
    held : tuple of str
        Coordinates held at their nominal values after :data:`MAX_ROUNDS`.
    """

    box: tuple[tuple[str, float, float], ...]
    steps: tuple[Narrowing, ...]
    reference: str
    reference_params: dict[str, float]
    paper_failure: str | None = None
    held: tuple[str, ...] = ()

    @property
    def narrowed(self) -> bool:
        """Whether any range was narrowed."""
        return bool(self.box)

    def notes(self) -> list[str]:
        """Sentences for report.md, ``--json`` and the controller's provenance."""
        out = []
        if self.paper_failure is not None:
            out.append(f"the paper's gains fail on the nominal plant ({self.paper_failure}); "
                       f"{self.reference} tracks it and is the reference trial")
        out += [s.sentence(self.reference) for s in self.steps]
        if self.held:
            out.append(f"after {MAX_ROUNDS} rounds, held at nominal: "
                       f"{', '.join(dict.fromkeys(self.held))}")
        if self.box:
            out.append("the draws use the narrowed box: the tuned controller is robust to it, "
                       "not to the model's full ranges; a log that excites these parameters "
                       "would narrow them with evidence (identify)")
        return out


def _failures(ev: Evaluation, draw: int) -> list[tuple[str, str]]:
    """(scenario, status) of the failed runs of ``draw``."""
    return [(s, rc.failure or "failed") for (s, d), rc in ev.runs.items()
            if d == draw and rc.cost is None]


def _fails(ctl: ControllerConfig, objective: TuneObjective, scenario: Scenario,
           plant: PlantConfig, vec: np.ndarray) -> str | None:
    """How ``ctl`` fails ``scenario`` (changes already merged into ``plant``), or None."""
    res = simulate_scenario(ctl, dataclasses.replace(scenario, plant_updates={}), plant,
                            seed=None, abort_error=objective.settings.abort_error, cfg_vec=vec)
    if res.metrics.status == "ok":
        return None
    return failure_text(res.metrics.status, objective.settings.abort_error)


def _reference(model: ModelConfig, objective: TuneObjective, seed: int
               ) -> tuple[str, dict[str, float], str | None]:
    """The reference controller: the paper's gains, or the first sampled controller that
    tracks the nominal plant in every scenario."""
    space = search_space(model, objective.settings.variant)
    nominal = objective.draws[0]

    def tracks(params: dict[str, float]) -> str | None:
        ctl = objective.controller(params)
        vec = pack(ctl)
        for sc in objective.scenarios:
            res = objective.simulate(ctl, sc, nominal, vec)
            if res.metrics.status != "ok":
                return (f"{sc.name}: "
                        f"{failure_text(res.metrics.status, objective.settings.abort_error)}")
        return None

    paper = space.paper_params()
    why = tracks(paper)
    if why is None:
        name = "the paper's gains" if objective.settings.variant == "modified_darc" else \
            "the default PID gains"
        return name, paper, None
    rng = np.random.default_rng([int(seed), 11])
    for k in range(1, N_ALTERNATIVES + 1):
        params = {p.name: float(np.exp(rng.uniform(np.log(p.low), np.log(p.high)))) if p.log
                  else float(rng.uniform(p.low, p.high)) for p in space.params}
        if tracks(params) is None:
            return f"alternative {k}", params, why
    raise InfeasibleModelError(
        f"the nominal plant cannot be tracked: the paper's gains fail ({why}), and so do "
        f"{N_ALTERNATIVES} other controllers sampled from the search space. Either the rig "
        f"cannot do what the scenarios ask (rig.Ts {model.rig.Ts:g} s, the paper's 0.004; "
        f"supply rig.p_s {model.rig.p_s / 1e5:.3g} bar abs, the paper's 6; stroke "
        f"{(model.rig.x_max - model.rig.x_min) * 1e3:.1f} mm for a 35 mm travel: check the rig "
        f"block), or the model is wrong (see its fit NRMSE x {model.fit.nrmse_x:.3g}, p_a "
        f"{model.fit.nrmse_p_a:.3g}, p_b {model.fit.nrmse_p_b:.3g}, and its notes): identify "
        "from a log that moves the piston at several speeds and charges and vents each chamber "
        "(simulate --experiment identification shows one)")


def _culprits(model: ModelConfig, objective: TuneObjective, ctl: ControllerConfig,
              draw: PlantDraw, scenario: str, coords: tuple[Coordinate, ...]
              ) -> tuple[list[Coordinate], bool]:
    """The coordinates that make ``draw`` infeasible for ``ctl`` in ``scenario``.

    Those that fail alone (each on the nominal plant, True); else those whose return to nominal
    alone rescues the draw (False); else every coordinate off nominal (False).
    """
    nominal = {c.key: c.nominal for c in coords}
    sc = next(s for s in objective.scenarios if s.name == scenario)
    vec = pack(ctl)
    off = [c for c in coords
           if abs(draw.values[c.key] - c.nominal) > 1e-9 * max(1.0, abs(c.nominal))]

    def fails(values: dict[str, float], tag: str) -> bool:
        plant = scenario_plant(plant_from_values(model, values, draw.noise_seed,
                                                 f"{draw.label}:{tag}"), sc)
        return _fails(ctl, objective, sc, plant, vec) is not None

    alone = [c for c in off if fails({**nominal, c.key: draw.values[c.key]}, c.key)]
    if alone:
        return alone, True
    rescue = [c for c in off if not fails({**draw.values, c.key: c.nominal}, c.key)]
    return (rescue or off), False


def check_feasibility(model: ModelConfig, seed: int, settings: ObjectiveSettings,
                      progress: Callable[[str], None] | None = None,
                      jobs: int = 1) -> Feasibility:
    """Make every plant draw trackable by a reference controller (module docstring).

    Parameters
    ----------
    model : ModelConfig
    seed : int
        The study's seed (plant draws and noise).
    settings : ObjectiveSettings
        The objective's settings (its ``box`` is the starting box).
    progress : callable, optional
        Called with a line of prose after each step.
    jobs : int
        Threads for a scenario's draws (:class:`~pneutune.tune.objective.TuneObjective`; the
        results do not depend on it).

    Returns
    -------
    Feasibility

    Raises
    ------
    InfeasibleModelError
        Not even the nominal plant can be tracked.
    """
    box = settings.box_dict()
    objective = TuneObjective(model, seed, settings, jobs=jobs)
    label, ref_params, paper_failure = _reference(model, objective, seed)
    ctl = objective.controller(ref_params)
    steps: list[Narrowing] = []
    held: list[str] = []
    for rnd in itertools.count():
        st = dataclasses.replace(settings, box=tuple((k, lo, hi) for k, (lo, hi) in box.items()))
        objective = TuneObjective(model, seed, st, jobs=jobs)
        ev = objective.evaluate(ctl, stop_on_failure=False)
        bad = [(d, _failures(ev, d.index)) for d in objective.draws[1:]]
        bad = [(d, f) for d, f in bad if f]
        if not bad:
            break
        if rnd > MAX_ROUNDS + 1:
            d, fails = bad[0]
            raise InfeasibleModelError(
                f"draw {d.index} ({d.label}) fails {label} ({fails[0][0]}: {fails[0][1]}) even "
                "with every range held at its nominal value: the nominal plant is tracked only "
                "for some sensor-noise seeds; the model is likely wrong")
        coords = uncertainty_box(model, box)
        for d, fails in bad:
            scenario, status = fails[0]
            if rnd <= MAX_ROUNDS:
                culprits, alone = _culprits(model, objective, ctl, d, scenario, coords)
            else:  # last resort: the whole draw at nominal
                culprits = [c for c in coords if d.values[c.key] != c.nominal]
                alone = False
            ranges = []
            for c in culprits:
                lo, hi = c.low, c.high
                v = d.values[c.key]
                if rnd >= MAX_ROUNDS:
                    lo = hi = c.nominal
                    held.append(c.key)
                elif v > c.nominal:
                    hi = c.nominal + 0.5 * (v - c.nominal)
                else:
                    lo = c.nominal + 0.5 * (v - c.nominal)
                box[c.key] = (lo, hi)
                ranges.append((c.key, lo, hi))
            step = Narrowing(d.index, d.label, scenario,
                             failure_text(status, settings.abort_error)
                             if status in (STATUS_ABORTED, STATUS_UNSTABLE) else status,
                             tuple((c.key, d.values[c.key], d.values[c.key] in (c.low, c.high))
                                   for c in culprits),
                             alone, tuple(ranges))
            steps.append(step)
            if progress is not None:
                progress(step.sentence(label))
            coords = uncertainty_box(model, box)
    final = tuple((k, lo, hi) for k, (lo, hi) in box.items())
    return Feasibility(final, tuple(steps), label, ref_params, paper_failure, tuple(held))


__all__ = ["MAX_ROUNDS", "N_ALTERNATIVES", "Feasibility", "InfeasibleModelError", "Narrowing",
           "check_feasibility", "describe", "failure_text"]
