"""The tuning objective: closed-loop simulation of the scenarios on plants drawn from the model.

For a candidate controller and every scenario s (default: the four Table-1 scenarios, then
``disturbance-0.5hz``) and plant draw d (:func:`pneutune.tune.plants.draw_plants`; the same
draws for every trial -- common random numbers, so trials are compared on the same plants and
the same sensor noise), one closed-loop run gives the paper's indices and the run's health
(:func:`pneutune.control.sim.closed_loop.run_batch`: all draws of a scenario in one compiled
call, in parallel over the draws). Its cost, dimensionless::

    c(s, d) = ½ (E_p / E_p* + E_rms / E_rms*)            tracking, * = the paper's Table 1
            + ½ · max(0, switches/s - 20) / 20           valve chattering (mode switches)
            + pressure penalty                            outside [½ p0, limits.p_max]
            + end-stop penalty                            time within 0.2 mm of a stroke end
            + 1 if θ̂ ever left [θ_min, θ_max]             (cannot happen; projection, Eq. 12)

``E_p*, E_rms*`` are the Table-1 figures of the scenario (the disturbance scenario has none and
uses those of the 0.5 Hz sine it is built on), so a tracking term of 1 means "as good as the
paper's rig". Per scenario the draws are aggregated by the CVaR at level α (default 0.25: the
mean of the worst quarter of the draws -- the worst two of eight); the objective is the mean of
the scenarios' CVaRs.

Why CVaR and not the worst case: with a fixed, finite set of draws the maximum is set by a
single plant (usually a corner draw) and rewards tuning to that one plant; CVaR_α is a coherent
risk measure between the mean (α = 1) and the worst case (α → 0) that averages the tail. It
equals the worst case when α·draws <= 1 (set ``cvar_alpha`` small for a minimax objective).
The worst case per scenario is recorded beside it (``trial.user_attrs["scenarios"]``).

Failures and pruning: a run that goes unstable (non-finite plant state), is aborted because
|e1| exceeded ``abort_error`` (5 mm by default: the paper's errors are below 0.6 mm, the initial
transient of the paper's gains below 1.2 mm) or gives non-finite indices ends the trial as
*pruned* (reported value :data:`FAIL_VALUE` at that step, reason in ``user_attrs["failure"]``),
never as an exception.

Reports to the pruner, two ways (the value of a completed trial is the same either way):

* per scenario (``instance_reports=False``; the median pruner): after each scenario the running
  mean is reported (``trial.report(value, step=scenario index)``) and the pruner may stop the
  trial there. With the median pruner and the TPE sampler (:func:`pruning_oracle`), a
  scenario after which the trial may be pruned runs its two corner draws first, then two more
  (:meth:`TuneObjective.bound_stages`, one draw on each thread); the CVaR over all draws is at
  least the mean of the largest costs known over the tail count (costs are non-negative), so
  when that bound already puts the running mean above the pruner's median it is reported and
  the trial is pruned without the other draws. The pruner takes the same decision on every
  trial as with the whole scenario (it reads only complete trials, and prunes more as a value
  grows); what differs is a pruned trial's last reported value, lower, which TPE reads only
  while fewer trials have completed than its better group holds. A run that fails among the
  corners fails the trial at once (its ``failure`` names that run).
* per instance (``instance_reports=True``; Optuna's ``WilcoxonPruner``): an *instance* is one
  (scenario, draw) run, id ``scenario index * n_draws + draw index``. The instances are run in
  chunks of :data:`INSTANCE_CHUNK` draws of one scenario (a fixed partition of the draws, one
  compiled call per chunk), the chunks in an order shuffled per trial (seeded by the objective's
  seed and the trial number, so a study stays reproducible); each run's cost c(s, d) is
  reported at its instance id and the pruner may stop the trial after each chunk. A failed run
  reports :data:`FAIL_VALUE` at its instance id. A pruned trial also reports, at the step one
  past the last instance id (``n_scenarios * n_draws``), an estimate of its objective from its
  runs so far (:func:`estimate_from_best`; :data:`FAIL_VALUE` when a run failed): Optuna's
  samplers rank pruned trials by the value at their highest step, which would otherwise be a
  single run's cost. The pruner never reads a pruned trial's values (only the current and the
  best trial's).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
import optuna

from pneutune.control.contracts.controller import DEAD_ZONE_MODES, ControllerConfig
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.errors import PneutuneError, argument_error
from pneutune.control.law.layout import pack
from pneutune.control.sim.closed_loop import (
    ClosedLoopResult,
    Metrics,
    PreparedBatch,
    PreparedRun,
    prepare_batch,
    prepare_run,
    run_batch,
    run_prepared,
)
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS, Scenario, resolve_scenarios

from .plants import PlantDraw, draw_plants
from .space import VARIANTS, SearchSpace, controller_from_params, search_space

#: Default scenarios: every scenario, that is Table 1, then the disturbance run.
DEFAULT_SCENARIOS: tuple[str, ...] = GROUPS["all"]
#: Value reported for a trial stopped by an unstable or aborted run.
FAIL_VALUE: float = 1.0e3
#: Draws of one scenario run per compiled call between two pruning checks, with per-instance
#: reports (fixed, not ``jobs``: the pruning decisions, hence the study, must not depend on the
#: number of threads).
INSTANCE_CHUNK: int = 4


class TuneError(PneutuneError, ValueError):
    """Bad tuning settings (scenario names, draw count, levels)."""


@dataclass(frozen=True)
class ObjectiveSettings:
    """What the objective simulates and how it scores (stored with the study).

    Attributes
    ----------
    scenarios : tuple of str
        Scenario names, in evaluation (and pruning) order.
    n_draws : int
        Plants: the nominal, two corners, the rest a Latin hypercube.
    cvar_alpha : float
        CVaR level over the draws, in (0, 1].
    abort_error : float
        A run whose measured |e1| exceeds this stops and fails the trial [m].
    duration : float or None
        Override of every scenario's duration [s] (tests); None keeps the scenarios' own.
    switches_free : float
        Mode switches per second without penalty [1/s].
    switches_weight : float
        Penalty per ``switches_free`` above the free allowance [-].
    p_low_fraction : float
        Lowest chamber pressure without penalty, as a fraction of p0 [-].
    pressure_weight : float
        Penalty per bar outside [p_low, limits.p_max], plus the same once for any excursion
        [1/bar].
    end_stop_weight : float
        Penalty per second within 0.2 mm of a stroke end, plus the same once for any contact
        [1/s].
    variant : str
        What is tuned: ``modified_darc`` (default) or ``pid`` (:func:`pneutune.tune.space.
        search_space`).
    dead_zone : str
        The tuned controller's ``dead_zone``: ``up`` (default) or ``dither`` (contract 4;
        fixed for the study, not searched).
    box : tuple of (str, float, float)
        Narrower ranges of plant coordinates, ``(key, lo, hi)``
        (:func:`pneutune.tune.plants.uncertainty_box`); set by the feasibility check
        (:mod:`pneutune.tune.feasibility`), empty when the model's box is used as it is.
    amplitude_scale : float
        Every scenario's reference amplitude, and Table 1's figures it is scored against, as
        a fraction of the paper's (:meth:`~pneutune.control.sim.scenarios.Scenario.scaled`),
        in (0, 1]; below 1 only on an axis too short for the paper's 17.5 mm
        (:func:`~pneutune.control.sim.scenarios.stroke_scale`, set by ``tune``).
    """

    scenarios: tuple[str, ...] = DEFAULT_SCENARIOS
    n_draws: int = 8
    cvar_alpha: float = 0.25
    abort_error: float = 5.0e-3
    duration: float | None = None
    switches_free: float = 20.0
    switches_weight: float = 0.5
    p_low_fraction: float = 0.5
    pressure_weight: float = 1.0
    end_stop_weight: float = 2.0
    variant: str = "modified_darc"
    dead_zone: str = "up"
    box: tuple[tuple[str, float, float], ...] = ()
    amplitude_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in self.scenarios:
            if name not in SCENARIOS:
                resolve_scenarios(name)  # raises with the list of known names
        if not self.scenarios:
            raise TuneError("at least one scenario must be given")
        if self.n_draws < 1:
            raise TuneError(f"n_draws >= 1 must hold, got {self.n_draws}")
        if not 0.0 < self.cvar_alpha <= 1.0:
            raise TuneError(f"0 < cvar_alpha <= 1 must hold, got {self.cvar_alpha}")
        if not self.abort_error > 0.0:
            raise TuneError(f"abort_error > 0 must hold, got {self.abort_error}")
        if self.duration is not None and not self.duration > 0.0:
            raise TuneError(f"duration > 0 must hold, got {self.duration}")
        if self.variant not in VARIANTS:
            raise argument_error(TuneError, "variant", f"must be one of {', '.join(VARIANTS)}, "
                                 f"got {self.variant!r}")
        if self.dead_zone not in DEAD_ZONE_MODES:
            raise argument_error(TuneError, "dead_zone", "must be one of "
                                 f"{', '.join(DEAD_ZONE_MODES)}, got {self.dead_zone!r}")
        if not 0.0 < self.amplitude_scale <= 1.0:
            raise TuneError(f"0 < amplitude_scale <= 1 must hold, got {self.amplitude_scale}")
        for key, lo, hi in self.box:
            if not lo <= hi:
                raise TuneError(f"box {key}: lo <= hi must hold, got lo={lo}, hi={hi}")

    def box_dict(self) -> dict[str, tuple[float, float]]:
        """``box`` as key -> (lo, hi)."""
        return {key: (lo, hi) for key, lo, hi in self.box}

    def to_dict(self) -> dict[str, Any]:
        """Plain data (JSON-able); ``box`` only when set, ``variant``, ``dead_zone`` and
        ``amplitude_scale`` only when not the default (studies made before any of them existed
        compare equal)."""
        out = dataclasses.asdict(self)
        out["scenarios"] = list(self.scenarios)
        if self.variant == "modified_darc":
            del out["variant"]
        if self.dead_zone == "up":
            del out["dead_zone"]
        if self.amplitude_scale == 1.0:
            del out["amplitude_scale"]
        if self.box:
            out["box"] = [list(b) for b in self.box]
        else:
            del out["box"]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ObjectiveSettings:
        """Inverse of :meth:`to_dict`."""
        data = dict(data)
        data["scenarios"] = tuple(data["scenarios"])
        data["box"] = tuple((str(k), float(lo), float(hi)) for k, lo, hi in data.get("box", ()))
        return cls(**data)


def cvar(values: Sequence[float], alpha: float) -> float:
    """Conditional value at risk: the mean of the worst ``ceil(alpha n)`` values (at least one).

    Parameters
    ----------
    values : sequence of float
        Costs (higher is worse).
    alpha : float
        Tail fraction in (0, 1].

    Returns
    -------
    float
    """
    v = np.sort(np.asarray(values, dtype=float))[::-1]
    return float(np.mean(v[:_tail(v.size, alpha)]))


def _tail(n: int, alpha: float) -> int:
    """How many of ``n`` costs the CVaR at level ``alpha`` averages: ``ceil(alpha n)``, at
    least one."""
    return max(1, math.ceil(alpha * n - 1e-12))


def reference_figures(scenario: Scenario) -> tuple[float, float]:
    """The (E_p, E_rms) [mm] a scenario's tracking is normalised by: its Table 1 figures
    (scaled with a scaled scenario's amplitude), or those of ``sine-0.5hz`` for a scenario
    without (the disturbance run), scaled alike."""
    if scenario.paper is not None:
        return scenario.paper
    ep, erms = SCENARIOS["sine-0.5hz"].paper  # type: ignore[misc]
    return (ep, erms) if scenario.scale == 1.0 else (scenario.scale * ep, scenario.scale * erms)


@dataclass(frozen=True)
class RunCost:
    """The cost of one closed-loop run and its parts (module docstring).

    ``cost`` is None when the run failed (``failure`` says why).
    """

    scenario: str
    draw: int
    metrics: Metrics
    cost: float | None
    tracking: float = float("nan")
    chatter: float = 0.0
    pressure: float = 0.0
    end_stop: float = 0.0
    theta: float = 0.0
    failure: str | None = None


def run_cost(metrics: Metrics, scenario: Scenario, draw: int, p0: float, p_max: float,
             settings: ObjectiveSettings) -> RunCost:
    """Score one run (module docstring).

    Parameters
    ----------
    metrics : Metrics
        From :func:`simulate_scenario`.
    scenario : Scenario
    draw : int
        Draw index.
    p0, p_max : float
        Ambient pressure and the controller's pressure limit [Pa abs].
    settings : ObjectiveSettings

    Returns
    -------
    RunCost
    """
    m = metrics
    if m.status != "ok":
        return RunCost(scenario.name, draw, m, None, failure=m.status)
    numbers = (m.E_p_mm, m.E_rms_mm, m.switches_per_s, m.p_a_max_Pa, m.p_b_max_Pa, m.p_a_min_Pa,
               m.p_b_min_Pa, m.end_stop_s)
    if not all(math.isfinite(x) for x in numbers):
        return RunCost(scenario.name, draw, m, None, failure="non-finite metrics")
    ep, erms = reference_figures(scenario)
    tracking = 0.5 * (m.E_p_mm / ep + m.E_rms_mm / erms)
    chatter = settings.switches_weight * max(0.0, m.switches_per_s - settings.switches_free) \
        / settings.switches_free
    p_low = settings.p_low_fraction * p0
    excess = (max(0.0, max(m.p_a_max_Pa, m.p_b_max_Pa) - p_max)
              + max(0.0, p_low - min(m.p_a_min_Pa, m.p_b_min_Pa)))
    pressure = settings.pressure_weight * (excess / 1e5 + (1.0 if excess > 0.0 else 0.0))
    end_stop = settings.end_stop_weight * (m.end_stop_s + (1.0 if m.end_stop_s > 0.0 else 0.0))
    theta = 0.0 if m.theta_in_bounds else 1.0
    total = tracking + chatter + pressure + end_stop + theta
    return RunCost(scenario.name, draw, m, total, tracking, chatter, pressure, end_stop, theta)


@dataclass
class Evaluation:
    """A controller scored on the scenarios x draws.

    Attributes
    ----------
    value : float or None
        The objective (mean over scenarios of the CVaR over draws); None if a run failed or the
        evaluation was stopped early.
    running : list of float
        The running mean after each scenario (what is reported to the pruner).
    scenario_cvar, scenario_worst : dict
        Per scenario: CVaR and maximum of the draws' costs.
    runs : dict
        ``(scenario, draw) -> RunCost``.
    failure : str or None
        Why the evaluation failed.
    stopped : bool
        The ``report`` callback asked to stop.
    reported : list of (int, float)
        Per-instance evaluation (:meth:`TuneObjective.evaluate_instances`): the (instance id,
        cost) pairs in the order they were run.
    failed_instance : int or None
        Per-instance evaluation: the instance id of the failed run.
    bound_draws : int or None
        Stopped on a lower bound (:meth:`TuneObjective.evaluate` with ``would_prune``): how
        many of the last scenario's draws had run; the last value in ``running`` is then that
        bound, not the scenario's CVaR.
    """

    value: float | None = None
    running: list[float] = field(default_factory=list)
    scenario_cvar: dict[str, float] = field(default_factory=dict)
    scenario_worst: dict[str, float] = field(default_factory=dict)
    runs: dict[tuple[str, int], RunCost] = field(default_factory=dict)
    failure: str | None = None
    stopped: bool = False
    reported: list[tuple[int, float]] = field(default_factory=list)
    failed_instance: int | None = None
    bound_draws: int | None = None

    def draw_totals(self) -> dict[int, float]:
        """Per draw, the mean cost over the scenarios evaluated (None-cost runs excluded)."""
        acc: dict[int, list[float]] = {}
        for (_, d), rc in self.runs.items():
            if rc.cost is not None:
                acc.setdefault(d, []).append(rc.cost)
        return {d: float(np.mean(v)) for d, v in sorted(acc.items())}

    def nominal_metrics(self) -> dict[str, dict[str, Any]]:
        """The metrics on draw 0 (the nominal plant), per scenario."""
        return {s: rc.metrics.as_dict() for (s, d), rc in self.runs.items() if d == 0}


def estimate_from_best(reported: Sequence[tuple[int, float]], study: optuna.Study) -> float:
    """What a pruned trial's objective would be, judged on the runs it did: the best trial's
    value times the geometric mean of the ratios of the trial's costs to the best trial's on the
    same instances (the mean of the costs when there is no best trial to compare with).

    It removes the difficulty of the instances a trial happened to run (a square wave costs
    more than a sine), so that pruned trials rank among themselves as their runs compare with
    the best trial's.

    Parameters
    ----------
    reported : sequence of (int, float)
        (instance id, cost) pairs of the pruned trial.
    study : optuna.Study

    Returns
    -------
    float
    """
    costs = dict(reported)
    try:
        best = study.best_trial
    except ValueError:
        best = None
    if best is not None and best.value is not None:
        pairs = [(c, best.intermediate_values[i]) for i, c in costs.items()
                 if i in best.intermediate_values]
        pairs = [(c, b) for c, b in pairs if c > 0.0 and b > 0.0]
        if pairs:
            ratio = float(np.exp(np.mean([math.log(c / b) for c, b in pairs])))
            return float(best.value) * ratio
    return float(np.mean(list(costs.values())))


def pruning_oracle(trial: optuna.Trial) -> Callable[[int, float], bool] | None:
    """``would_prune(step, value)`` for :meth:`TuneObjective.evaluate`: whether the study's
    pruner would stop ``trial`` if ``value`` were reported at ``step``, asked on a copy of the
    trial without reporting anything.

    Only where stopping a scenario early on a lower bound changes nothing but a pruned trial's
    last value: a median or percentile pruner (which reads the complete trials alone, and
    prunes more as the value grows) and a TPE sampler (which ranks pruned trials by their last
    value only when fewer trials have completed than its better group holds, which a study
    with the median pruner's start-up does not reach before a tenth of its trials complete).
    None otherwise (CMA-ES reads pruned trials' values; other pruners are not monotone).

    Returns
    -------
    callable or None
    """
    study = getattr(trial, "study", None)  # an optuna.trial.FixedTrial has none
    if study is None:
        return None
    pruner = study.pruner
    if not isinstance(pruner, optuna.pruners.PercentilePruner) \
            or not isinstance(study.sampler, optuna.samplers.TPESampler):
        return None
    number = trial.number

    def would_prune(step: int, value: float) -> bool:
        frozen = next(t for t in study.get_trials(deepcopy=False) if t.number == number)
        probe = optuna.trial.FrozenTrial(
            number=frozen.number, state=frozen.state, value=None,
            datetime_start=frozen.datetime_start, datetime_complete=None,
            params=frozen.params, distributions=frozen.distributions,
            user_attrs=frozen.user_attrs, system_attrs=frozen.system_attrs,
            intermediate_values={**frozen.intermediate_values, step: float(value)},
            trial_id=frozen._trial_id)
        return bool(pruner.prune(study, probe))

    return would_prune


class TuneObjective:
    """The objective for one model, seed and settings (module docstring).

    Building it draws the plants and merges each scenario's changes into each plant once;
    calling it on an Optuna trial suggests the parameters, builds the controller and scores it.

    Parameters
    ----------
    model : ModelConfig
        The identified model.
    seed : int
        Seed of the plant draws and the sensor noise (>= 0).
    settings : ObjectiveSettings, optional
    jobs : int
        Threads that run the draws of a scenario in parallel (numba's threads, one compiled call
        per scenario: :func:`~pneutune.control.sim.closed_loop.run_batch`). Every run is
        computed as if alone, so the values do not depend on ``jobs``; a trial's wall time
        drops by up to ``min(jobs, draws)``.
    instance_reports : bool
        Report each (scenario, draw) run's cost at its instance id, in a per-trial order, for
        Optuna's ``WilcoxonPruner`` (module docstring); False (default) reports the running
        mean after each scenario. A completed trial's value is the same either way.
    """

    def __init__(self, model: ModelConfig, seed: int,
                 settings: ObjectiveSettings | None = None, jobs: int = 1,
                 instance_reports: bool = False) -> None:
        if jobs < 1:
            raise TuneError(f"jobs >= 1 must hold, got {jobs}")
        self.jobs = int(jobs)
        self.instance_reports = bool(instance_reports)
        self.model = model
        self.seed = int(seed)
        self.settings = settings if settings is not None else ObjectiveSettings()
        self.space: SearchSpace = search_space(model, self.settings.variant)
        self.draws: tuple[PlantDraw, ...] = draw_plants(model, self.settings.n_draws, self.seed,
                                                        self.settings.box_dict())
        scen = [SCENARIOS[n].scaled(self.settings.amplitude_scale)
                for n in self.settings.scenarios]
        if self.settings.duration is not None:
            scen = [dataclasses.replace(s, duration=self.settings.duration) for s in scen]
        self.scenarios: tuple[Scenario, ...] = tuple(scen)
        # Everything that does not depend on the controller (each scenario's plant changes
        # merged into each draw, the reference, the sensor noise of the draw's seed, the
        # initial state) is prepared once; every trial runs on the same prepared runs.
        self._runs: dict[str, tuple[PreparedRun, ...]] = {
            s.name: tuple(prepare_run(s, d.plant) for d in self.draws) for s in self.scenarios}
        # per-instance evaluation: the draws in fixed chunks (draws i, i + k, i + 2k, ...),
        # their batches stacked on first use
        n_chunks = math.ceil(len(self.draws) / INSTANCE_CHUNK)
        self.draw_chunks: tuple[tuple[int, ...], ...] = tuple(
            tuple(range(i, len(self.draws), n_chunks)) for i in range(n_chunks))
        # batches of a scenario's draws by (scenario, draws): every draw (prepared now), and the
        # parts run apart (the chunks; bound_stages and the rest), stacked on first use
        every = tuple(range(len(self.draws)))
        self._draw_batches: dict[tuple[str, tuple[int, ...]], PreparedBatch] = {
            (name, every): prepare_batch(runs) for name, runs in self._runs.items()}

    def instance_id(self, scenario: int, draw: int) -> int:
        """The id of run (scenario index, draw index) as reported to the pruner."""
        return scenario * len(self.draws) + draw

    def instance_order(self, trial_number: int) -> list[tuple[int, int]]:
        """The (scenario index, chunk index) pairs in the order trial ``trial_number`` runs
        them with per-instance reports: a permutation seeded by the objective's seed and the
        trial number (the same in every process and on resume).

        Returns
        -------
        list of (int, int)
        """
        pairs = [(s, c) for s in range(len(self.scenarios)) for c in range(len(self.draw_chunks))]
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, int(trial_number)]))
        return [pairs[i] for i in rng.permutation(len(pairs))]

    def run_chunk(self, controller: ControllerConfig, scenario: int, chunk: int,
                  cfg_vec: np.ndarray | None = None) -> list[ClosedLoopResult]:
        """The draws ``draw_chunks[chunk]`` of scenario index ``scenario``, in one compiled
        call on :attr:`jobs` threads (each run bit-identical to :meth:`run_scenario`'s).

        Returns
        -------
        list of ClosedLoopResult
            In the order of ``draw_chunks[chunk]``.
        """
        return self.run_draws(controller, self.scenarios[scenario], self.draw_chunks[chunk],
                              cfg_vec)

    def _threads(self) -> int:
        """Threads to run a scenario's draws on."""
        return max(1, min(self.jobs, len(self.draws), numba.config.NUMBA_NUM_THREADS))

    def run_scenario(self, controller: ControllerConfig, scenario: Scenario,
                     cfg_vec: np.ndarray | None = None,
                     abort: bool = True) -> list[ClosedLoopResult]:
        """All draws of a scenario, in one compiled call on :attr:`jobs` threads.

        Returns
        -------
        list of ClosedLoopResult
            In draw order.
        """
        return self.run_draws(controller, scenario, range(len(self.draws)), cfg_vec, abort)

    def simulate(self, controller: ControllerConfig, scenario: Scenario, draw: PlantDraw,
                 cfg_vec: np.ndarray | None = None, abort: bool = True) -> ClosedLoopResult:
        """One run of ``controller`` on a scenario and draw (the plant's own noise seed).

        Returns
        -------
        ClosedLoopResult
        """
        run = self._runs[scenario.name][draw.index]
        return run_prepared(run, controller,
                            abort_error=self.settings.abort_error if abort else np.inf,
                            cfg_vec=cfg_vec)

    def evaluate(self, controller: ControllerConfig,
                 report: Callable[[int, float], bool] | None = None,
                 stop_on_failure: bool = True,
                 would_prune: Callable[[int, float], bool] | None = None) -> Evaluation:
        """Score ``controller`` on every scenario and draw.

        Parameters
        ----------
        controller : ControllerConfig
        report : callable, optional
            ``report(step, running_value) -> stop`` after each scenario but the last.
        stop_on_failure : bool
            Stop at the first failed run (tuning); False runs everything (reports).
        would_prune : callable, optional
            ``would_prune(step, value) -> bool``: whether the pruner would stop the trial if
            ``value`` were reported at ``step``, asked without reporting it, and whose answer
            cannot turn from yes to no as the value grows (a median or percentile pruner).
            With it (and ``report``), a scenario the trial may be pruned after is run in parts,
            the :meth:`bound_stages` first; when their costs already put the running
            value above what the pruner stops, that lower bound is reported
            (:meth:`scenario_bound`) and, if the pruner stops the trial, the other draws are
            never run. Every decision of the pruner is the one the whole scenario would have
            given; only a pruned trial's last reported value may be lower.

        Returns
        -------
        Evaluation
        """
        st = self.settings
        ev = Evaluation()
        vec = pack(controller)
        p0 = controller.rig.p0
        p_max = controller.limits.p_max
        stages = self.bound_stages()
        for step, sc in enumerate(self.scenarios):
            last = step == len(self.scenarios) - 1
            reported = False
            results: list[ClosedLoopResult | None]
            if (report is not None and would_prune is not None and not last and stages
                    and would_prune(step, math.inf)):
                part: dict[int, ClosedLoopResult] = {}
                failed = False
                for stage in stages:
                    part.update(zip(stage, self.run_draws(controller, sc, stage, vec),
                                    strict=True))
                    bound = self.scenario_bound([run_cost(r.metrics, sc, d, p0, p_max, st).cost
                                                 for d, r in part.items()])
                    if bound is None:  # a run failed: the trial fails, whatever the others do
                        failed = True
                        break
                    n_done = len(ev.scenario_cvar)
                    # the running value can only be higher; a hair lower covers rounding
                    low = (sum(ev.scenario_cvar.values()) + bound) / (n_done + 1) \
                        * (1.0 - 1.0e-12)
                    if would_prune(step, low):
                        ev.running.append(low)
                        reported = True
                        if report(step, low):
                            ev.stopped = True
                            ev.bound_draws = len(part)
                            return ev
                        break  # kept after all (another worker's trial completed meanwhile)
                if not failed:
                    rest = tuple(d.index for d in self.draws if d.index not in part)
                    part.update(zip(rest, self.run_draws(controller, sc, rest, vec),
                                    strict=True))
                results = [part.get(d.index) for d in self.draws]
            else:
                results = list(self.run_scenario(controller, sc, vec))
            costs = []
            for d in self.draws:
                res = results[d.index]
                if res is None:  # not run: a run of the first part failed
                    continue
                rc = run_cost(res.metrics, sc, d.index, p0, p_max, st)
                ev.runs[(sc.name, d.index)] = rc
                if rc.cost is None:
                    if ev.failure is None:
                        ev.failure = f"{rc.failure} in {sc.name} on draw {d.index} ({d.label})"
                    if stop_on_failure:
                        return ev
                    continue
                costs.append(rc.cost)
            if len(costs) == len(self.draws):
                ev.scenario_cvar[sc.name] = cvar(costs, st.cvar_alpha)
                ev.scenario_worst[sc.name] = float(max(costs))
            if ev.failure is None:
                if reported:  # the pruner kept the trial on the bound, already reported
                    ev.running[-1] = float(np.mean(list(ev.scenario_cvar.values())))
                    continue
                ev.running.append(float(np.mean(list(ev.scenario_cvar.values()))))
                if report is not None and not last and report(step, ev.running[-1]):
                    ev.stopped = True
                    return ev
        if ev.failure is None:
            ev.value = ev.running[-1]
        return ev

    def tail_count(self) -> int:
        """How many of the draws' costs the CVaR averages: ``ceil(alpha n)``, at least one
        (:func:`cvar`)."""
        return _tail(len(self.draws), self.settings.cvar_alpha)

    def bound_stages(self) -> tuple[tuple[int, ...], ...]:
        """The draws a scenario the trial may be pruned after runs first, in stages, each
        followed by a check of the bound (:meth:`evaluate`): the two corners of the box (draws 1
        and 2), whose costs are most often among the highest, then the next two draws of the
        Latin hypercube; each stage as many draws as the CVaR averages and at least as many as
        there are threads, and at least one draw left for the rest (the nominal plant, draw 0,
        runs last). None with fewer than three draws.

        Returns
        -------
        tuple of tuple of int
        """
        n = len(self.draws)
        if n < 3:
            return ()
        m = max(self.tail_count(), self._threads())
        order = [*range(1, n), 0]
        stages = []
        for start in (0, m):
            stage = tuple(order[start:min(start + m, n - 1)])
            if stage:
                stages.append(stage)
        return tuple(stages)

    def scenario_bound(self, costs: Sequence[float | None]) -> float | None:
        """A lower bound of a scenario's CVaR over all draws from the costs of some of them:
        the sum of the largest ``k`` of them (``k = ceil(alpha n)``, fewer if fewer are known)
        over ``k``; None when a run failed (``None`` cost).

        Costs are non-negative, so the mean of the ``k`` largest of all draws is at least
        that.

        Returns
        -------
        float or None
        """
        if any(c is None for c in costs):
            return None
        k = self.tail_count()
        top = sorted((float(c) for c in costs if c is not None), reverse=True)[:k]
        return sum(top) / k

    def run_draws(self, controller: ControllerConfig, scenario: Scenario,
                  draws: Sequence[int], cfg_vec: np.ndarray | None = None,
                  abort: bool = True) -> list[ClosedLoopResult]:
        """The draws ``draws`` of ``scenario`` in one compiled call on up to :attr:`jobs`
        threads; each run is computed as if alone, so the same whatever the draws beside it.

        Returns
        -------
        list of ClosedLoopResult
            In the order of ``draws``.
        """
        key = (scenario.name, tuple(draws))
        batch = self._draw_batches.get(key)
        if batch is None:
            runs = self._runs[scenario.name]
            batch = prepare_batch([runs[d] for d in key[1]])
            self._draw_batches[key] = batch
        threads = max(1, min(self.jobs, len(batch.runs), numba.config.NUMBA_NUM_THREADS))
        previous = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            with numba.parallel_chunksize(1):  # hand the runs out one at a time
                return run_batch(batch, controller,
                                 abort_error=self.settings.abort_error if abort else np.inf,
                                 cfg_vec=cfg_vec)
        finally:
            numba.set_num_threads(previous)

    def evaluate_instances(self, controller: ControllerConfig,
                           order: Sequence[tuple[int, int]],
                           report: Callable[[list[tuple[int, float]], bool], bool]
                           | None = None,
                           ) -> Evaluation:
        """Score ``controller`` chunk by chunk in ``order``, reporting each run's cost.

        Stops at the first failed run. When every run completed, the result (``value``,
        ``running``, ``scenario_cvar``, ``scenario_worst``) is that of :meth:`evaluate`: the
        same costs, aggregated in scenario and draw order.

        Parameters
        ----------
        controller : ControllerConfig
        order : sequence of (int, int)
            (scenario index, chunk index) pairs (:meth:`instance_order`), each once.
        report : callable, optional
            ``report([(instance id, cost), ...], last) -> stop`` after each chunk (``last``:
            the final one, whose answer is ignored); not called for a chunk with a failed run
            (the caller reports :data:`FAIL_VALUE`).

        Returns
        -------
        Evaluation
            With ``failure`` set, ``failed_instance`` holds the failed run's instance id.
        """
        st = self.settings
        ev = Evaluation()
        vec = pack(controller)
        p0 = controller.rig.p0
        p_max = controller.limits.p_max
        for k, (si, ci) in enumerate(order):
            sc = self.scenarios[si]
            results = self.run_chunk(controller, si, ci, vec)
            reported: list[tuple[int, float]] = []
            for d, res in zip(self.draw_chunks[ci], results, strict=True):
                rc = run_cost(res.metrics, sc, d, p0, p_max, st)
                ev.runs[(sc.name, d)] = rc
                if rc.cost is None:
                    ev.failure = (f"{rc.failure} in {sc.name} on draw {d} "
                                  f"({self.draws[d].label})")
                    ev.failed_instance = self.instance_id(si, d)
                    return ev
                reported.append((self.instance_id(si, d), rc.cost))
            last = k == len(order) - 1
            ev.reported.extend(reported)
            if report is not None and report(reported, last) and not last:
                ev.stopped = True
                return ev
        for sc in self.scenarios:  # scenario and draw order, as evaluate() aggregates
            costs = [ev.runs[(sc.name, d.index)].cost for d in self.draws]
            ev.scenario_cvar[sc.name] = cvar(costs, st.cvar_alpha)  # type: ignore[arg-type]
            ev.scenario_worst[sc.name] = float(max(costs))  # type: ignore[type-var]
            ev.running.append(float(np.mean(list(ev.scenario_cvar.values()))))
        ev.value = ev.running[-1]
        return ev

    def controller(self, params: dict[str, float]) -> ControllerConfig:
        """The controller of a parameter set on this model."""
        return controller_from_params(self.model, params, dead_zone=self.settings.dead_zone)

    def __call__(self, trial: optuna.Trial) -> float:
        """Score a trial (raises :class:`optuna.TrialPruned` when pruned or failed)."""
        params = self.space.suggest(trial)
        controller = self.controller(params)

        def report(step: int, value: float) -> bool:
            trial.report(value, step)
            return trial.should_prune()

        def report_instances(values: list[tuple[int, float]], last: bool) -> bool:
            for instance, cost in values:
                trial.report(cost, instance)
            return not last and trial.should_prune()

        if self.instance_reports:  # every run reported: the best trial must hold them all
            ev = self.evaluate_instances(controller, self.instance_order(trial.number),
                                         report=report_instances)
        else:
            ev = self.evaluate(controller, report=report, would_prune=pruning_oracle(trial))
        n_runs = len(self.scenarios) * len(self.draws)  # also the summary step
        if ev.failure is not None:
            trial.set_user_attr("failure", ev.failure)
            if self.instance_reports:
                if ev.failed_instance is not None:
                    trial.report(FAIL_VALUE, ev.failed_instance)
                trial.report(FAIL_VALUE, n_runs)
            else:
                trial.report(FAIL_VALUE, len(ev.scenario_cvar))
            raise optuna.TrialPruned(ev.failure)
        if ev.stopped:
            if self.instance_reports:  # the summary step (module docstring)
                trial.report(estimate_from_best(ev.reported, trial.study), n_runs)
                raise optuna.TrialPruned(f"pruned after {len(ev.reported)} of {n_runs} runs")
            if ev.bound_draws is not None:  # history.png marks its value as a lower bound
                trial.set_user_attr("pruned_on_bound", {
                    "scenario": self.scenarios[len(ev.running) - 1].name,
                    "draws_run": ev.bound_draws})
                raise optuna.TrialPruned(
                    f"pruned on a lower bound after {ev.bound_draws} of {len(self.draws)} "
                    f"draws of scenario {len(ev.running)}")
            raise optuna.TrialPruned(f"pruned after {len(ev.running)} scenario(s)")
        trial.set_user_attr("scenarios", {
            s: {"cvar": ev.scenario_cvar[s], "worst": ev.scenario_worst[s],
                "nominal_E_p_mm": ev.runs[(s, 0)].metrics.E_p_mm,
                "nominal_E_rms_mm": ev.runs[(s, 0)].metrics.E_rms_mm,
                "nominal_switches_per_s": ev.runs[(s, 0)].metrics.switches_per_s}
            for s in ev.scenario_cvar})
        totals = ev.draw_totals()
        trial.set_user_attr("worst_draw", max(totals, key=lambda d: totals[d]))
        if ev.value is None:  # pragma: no cover - evaluate() sets it whenever nothing failed
            raise RuntimeError(f"trial {trial.number}: evaluation ended without a value")
        return ev.value


__all__ = ["DEFAULT_SCENARIOS", "FAIL_VALUE", "INSTANCE_CHUNK", "Evaluation",
           "ObjectiveSettings", "RunCost", "TuneError", "TuneObjective", "cvar",
           "estimate_from_best", "pruning_oracle", "reference_figures", "run_cost"]
