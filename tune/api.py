"""``tune(model, settings)``: the whole of the ``tune`` command as a library call.

What the command does, a notebook does the same way, with the same validation::

    from pneutune.tune import TuneSettings, tune
    result = tune("reports/identify/model.yaml", TuneSettings(trials=200))
    result.controller          # the tuned ControllerConfig (contract 4)
    result.summary()           # what `tune --json` prints

Steps: validate the settings and the model; check that every plant draw can be tracked,
narrowing the ranges no controller tracks (:mod:`.feasibility`); run the study (:mod:`.study`)
to ``settings.trials`` finished trials and keep its best trial that passes the held-out guard
(:mod:`.guard`); with ``settings.restarts`` > 1 do so for each seed and keep the study whose
trial scores best on selection draws (:mod:`.restarts`); build the kept trial's controller
with its provenance;
score it against the paper's controller on every scenario and draw (:mod:`.report`); write
controller.yaml, report.md with its figures, and the nominal and worst plants (atomically) into
``settings.out``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import optuna
from optuna.trial import FrozenTrial

from pneutune.control.constants import VERSION
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import (
    PAPER_CONTROLLER,
    ControllerConfig,
    ProvenanceConfig,
    load_controller,
    save_controller,
)
from pneutune.control.contracts.model import ModelConfig, load_model
from pneutune.control.contracts.yamlio import validate_model, write_yaml
from pneutune.control.errors import ConfigError, ExperimentError, argument_error
from pneutune.control.sim.scenarios import AMPLITUDE, SCENARIOS, stroke_scale

from .feasibility import Feasibility, InfeasibleModelError, check_feasibility
from .guard import GuardResult, guarded_best
from .logcheck import check_logs, logged_controller
from .objective import ObjectiveSettings, TuneError, TuneObjective
from .pruners import check_pruner
from .report import Comparison, compare, write_report
from .restarts import Candidate, select, selection_objectives
from .samplers import DEFAULT_SAMPLER, check_sampler, describe
from .space import THETA_0_PARAM, controller_from_params, search_space
from .storage import DEFAULT_JOURNAL, is_url, out_lock, redact_url, storage_scheme
from .study import RunSummary, StudySpec, default_study_name, finished, run_study

#: Where ``tune`` writes by default.
DEFAULT_OUT = "reports/tune"


@dataclass(frozen=True)
class TuneSettings:
    """How to tune (the command's flags).

    Attributes
    ----------
    trials : int
        Finished (complete + pruned) trials the study should hold in total, >= 1.
    out : path-like or None
        Output folder for controller.yaml, report.md and the plants (the command's default
        is ``reports/tune``); None (the library's default): nothing is written
        (:meth:`TuneResult.save` writes them later).
    storage : str or None
        Journal file path or RDB URL; default ``out/study.journal``, or with no ``out`` a
        temporary journal that lives as long as the result (the study cannot be resumed).
    study : str or None
        Study name; default ``tune-<model sha256[:12]>-seed<S>``. With ``restarts`` > 1 the
        studies are ``<study>-seed<S>``, ``<study>-seed<S+1>``, ... (the default names already
        differ by seed).
    workers : int
        Worker processes on this host (1: reproducible).
    jobs : int or None
        Processes per worker for a trial's plant draws; default the available CPUs with one
        worker, else 1 (the values do not depend on it).
    seed : int
        Seed of the plant draws, sensor noise and samplers, >= 0.
    objective : ObjectiveSettings
        Scenarios, draws and the cost (docs/tuning.md).
    sampler : str
        ``tpe`` (default) or ``cmaes`` (TPE, then CMA-ES warm-started from it; needs the
        ``cmaes`` package); :mod:`pneutune.tune.samplers`.
    pruner : str or None
        ``staged``, ``wilcoxon``, ``median`` or ``none``
        (:func:`pneutune.tune.pruners.make_pruner`); None (default): a resumed study's own,
        ``staged`` for a new one.
    restarts : int
        Independent studies, seeds ``seed`` .. ``seed + restarts - 1``, each of ``trials``
        trials; the controller kept is the one that scores best on selection draws with new
        noise and new Latin-hypercube plants (:mod:`pneutune.tune.restarts`). 1 (default):
        one study.
    """

    trials: int
    out: str | os.PathLike[str] | None = None
    storage: str | None = None
    study: str | None = None
    workers: int = 1
    jobs: int | None = None
    seed: int = 1
    objective: ObjectiveSettings = field(default_factory=ObjectiveSettings)
    sampler: str = DEFAULT_SAMPLER
    pruner: str | None = None
    restarts: int = 1

    def __post_init__(self) -> None:
        if self.trials < 1:
            raise argument_error(TuneError, "trials", f"must be >= 1, got {self.trials}")
        if self.workers < 1:
            raise argument_error(TuneError, "workers", f"must be >= 1, got {self.workers}")
        if self.seed < 0:
            raise argument_error(TuneError, "seed", f"must be >= 0, got {self.seed}")
        if self.restarts < 1:
            raise argument_error(TuneError, "restarts", f"must be >= 1, got {self.restarts}")
        if self.jobs is not None and self.jobs < 1:
            raise argument_error(TuneError, "jobs", f"must be >= 1, got {self.jobs}")
        check_sampler(self.sampler)  # unknown, or its package missing: before any simulation
        check_pruner(self.pruner)


@dataclass(frozen=True, repr=False)
class TuneResult:
    """What :func:`tune` produced.

    ``controller`` is contract 4 (controller.yaml); :meth:`save` writes it with the report and
    the plants. ``repr`` shows the study, the kept trial and its score against the paper's.
    With restarts, ``study``, ``best``, ``feasibility``, ``run``, ``guard`` and ``info["seed"]``
    are the kept study's; ``info["restarts"]`` lists every study (None with one).

    Attributes
    ----------
    controller : ControllerConfig
        The chosen trial's controller, with its provenance.
    study : optuna.Study
    best : FrozenTrial
        The chosen trial: the study's best unless it failed the held-out guard
        (:mod:`pneutune.tune.guard`).
    comparison : Comparison
        The tuned and the paper's controllers on every scenario and draw.
    feasibility : Feasibility
        What the check before the study found and narrowed.
    run : RunSummary
        Trial counts before and after, wall time.
    paths : dict
        ``controller``, ``report``, ``plant_nominal``, ``plant_worst`` as written into
        ``settings.out``; empty when nothing was written.
    info : dict
        The model, its sha256, the storage (password redacted), seed, workers, jobs.
    """

    controller: ControllerConfig
    study: optuna.Study
    best: FrozenTrial
    comparison: Comparison
    feasibility: Feasibility
    run: RunSummary
    paths: dict[str, str]
    info: dict[str, Any]
    guard: GuardResult | None = None
    #: what :meth:`save` needs: the objective (its draws) and the report's facts
    _objective: TuneObjective | None = field(default=None, compare=False)
    _report: dict[str, Any] = field(default_factory=dict, compare=False)
    #: the temporary folder of a study kept in no file the caller named
    _scratch: Any = field(default=None, compare=False)

    def __repr__(self) -> str:
        comp = self.comparison
        paper = "n/a" if comp.paper.value is None else f"{comp.paper.value:.4g}"
        counts = self.run.counts_after
        return (f"TuneResult(study={self.info['study']!r}, trials={finished(counts)} "
                f"({counts['COMPLETE']} complete, {counts['PRUNED']} pruned), "
                f"best=#{self.best.number}, objective={comp.tuned.value:.4g} "
                f"(paper's gains {paper}), variant={self.controller.variant!r}, "
                f"written={sorted(self.paths) or 'nothing'})")

    def save(self, out: str | os.PathLike[str]) -> dict[str, str]:
        """Write controller.yaml, plant-nominal.yaml, plant-worst.yaml (atomically) and
        report.md with its figures into ``out``.

        Parameters
        ----------
        out : path-like
            Output folder (made if missing).

        Returns
        -------
        dict
            ``controller``, ``plant_nominal``, ``plant_worst``, ``report``: the paths written.
        """
        if self._objective is None:  # pragma: no cover - a record built by hand
            raise ValueError("this TuneResult does not hold what the report needs")
        return _save(Path(out), self, self._objective, self._report)

    def summary(self) -> dict[str, Any]:
        """The object ``tune --json`` prints."""
        counts = self.run.counts_after
        return {
            **self.paths, **self.info,
            "trials": {"wanted": self.info["n_trials"], "finished": finished(counts),
                       "complete": counts["COMPLETE"], "pruned": counts["PRUNED"],
                       "failed": counts["FAIL"], "running": counts["RUNNING"],
                       "this_run": finished(counts) - finished(self.run.counts_before),
                       "leftovers_failed": self.run.leftovers_failed},
            "wall_s": self.run.wall_s,
            "best": {"trial": self.best.number, "objective": self.best.value,
                     "params": self.best.params},
            "narrowed": [list(b) for b in self.feasibility.box],
            "feasibility": self.feasibility.notes(),
            "guard": None if self.guard is None else {
                "seed": self.guard.seed, "passed": self.guard.passed,
                "rejected": [{"trial": n, "failure": why} for n, why in self.guard.rejected]},
            **self.comparison.summary(),
        }


def version() -> str:
    """The installed pneutune version."""
    return VERSION


def available_cpus() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def provenance(model_sha256: str, study: str, trial: int, value: float, seed: int,
               notes: Sequence[str] = ()) -> dict[str, Any]:
    """The provenance block of a tuned controller.yaml.

    Parameters
    ----------
    model_sha256, study : str
    trial : int
    value : float
        The trial's objective.
    seed : int
    notes : sequence of str
        What tune had to assume or change (the feasibility check's notes).

    Returns
    -------
    dict
        ``seed`` and ``notes`` only if this pneutune's contract 4 has those keys.
    """
    prov: dict[str, Any] = {
        "model_sha256": model_sha256, "study": study, "trial": int(trial),
        "objective": float(value),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "version": version(),
    }
    if "seed" in ProvenanceConfig.model_fields:
        prov["seed"] = int(seed)
    if notes and "notes" in ProvenanceConfig.model_fields:
        prov["notes"] = list(notes)
    return prov


def paper_path() -> str:
    """How report.md names the paper's controller: ``data/controller-paper.yaml`` when run from
    a checkout (where that link points at the packaged file), else the packaged file's path
    (relative when it lies below the working directory, else absolute)."""
    link = Path("data") / "controller-paper.yaml"
    try:
        if link.resolve() == PAPER_CONTROLLER.resolve():
            return link.as_posix()
    except OSError:
        pass
    rel = os.path.relpath(PAPER_CONTROLLER)
    return str(PAPER_CONTROLLER.resolve()) if rel.startswith(os.pardir) else rel


def paper_on_rig(paper: ControllerConfig, tuned: ControllerConfig
                 ) -> tuple[ControllerConfig, bool]:
    """The paper's controller as a user compares it on the tuned controller's rig.

    The paper's file carries the paper's ``rig`` and ``limits`` blocks; on another rig the
    commissioning recipe (docs/commissioning.md) puts the rig's own blocks into a copy of it,
    and so does this: the paper's gains, adaptation, filters, valves and PWM curve, with
    ``tuned``'s ``rig`` and ``limits``.

    Parameters
    ----------
    paper : ControllerConfig
        ``data/controller-paper.yaml``.
    tuned : ControllerConfig
        The tuned controller (the model's rig and limits).

    Returns
    -------
    (ControllerConfig, bool)
        The baseline, and whether its blocks were replaced.
    """
    if paper.rig == tuned.rig and paper.limits == tuned.limits:
        return paper, False
    data = paper.to_dict()
    mine = tuned.to_dict()
    data["rig"], data["limits"] = mine["rig"], mine["limits"]
    return validate_model(ControllerConfig, data, "<the paper's controller on this rig>"), True


def failure_summary(study: optuna.Study) -> str:
    """Why the trials of a study failed, most frequent first (``user_attrs["failure"]``)."""
    reasons: dict[str, int] = {}
    for t in study.get_trials(deepcopy=False):
        why = t.user_attrs.get("failure")
        if why:
            reasons[why] = reasons.get(why, 0) + 1
    if not reasons:
        return "no failure recorded (every trial was pruned as worse than others)"
    top = sorted(reasons.items(), key=lambda kv: -kv[1])[:3]
    return "; ".join(f"{n}x {why}" for why, n in top)


def _load(model: Any) -> tuple[ModelConfig, str, str]:
    """The model, its sha256 and a name for messages. A model in memory is hashed over its
    canonical JSON (a file's hash is over its bytes: the same model read from a file and built
    in memory make different studies)."""
    if isinstance(getattr(model, "model", None), ModelConfig):  # identify's result
        model = model.model
    if isinstance(model, ModelConfig):
        text = json.dumps(model.to_dict(), sort_keys=True)
        return model, hashlib.sha256(text.encode()).hexdigest(), "<model>"
    if not isinstance(model, (str, os.PathLike)):
        raise argument_error(TuneError, "model", "must be a model.yaml path, a ModelConfig or "
                             f"identify's result, got {type(model).__name__}")
    path = Path(model)
    if not path.is_file():
        raise ConfigError(str(path), "", "no such model file; run identify first "
                          "(`identify LOG.mcap` writes reports/identify/model.yaml) or pass "
                          "--model M.yaml")
    return load_model(path), sha256_file(path), str(path)


def tune(model: Any, settings: TuneSettings | None = None,
         progress: Callable[[int, int], None] | None = None,
         notes: Callable[[str], None] | None = None) -> TuneResult:
    """Tune the modified DARC on an identified model; write controller.yaml and report.md
    when ``settings.out`` is given.

    Parameters
    ----------
    model : ModelConfig, path-like, or a result with a ``model`` attribute
        The identified model (contract 3), its file, or what
        :func:`pneutune.identify.identify` returned.
    settings : TuneSettings, optional
        Default ``TuneSettings(trials=200)``: the command's defaults, nothing written.
    progress : callable, optional
        ``progress(finished, total)`` now and then.
    notes : callable, optional
        Called with each line of prose (the feasibility check's steps).

    Returns
    -------
    TuneResult

    Raises
    ------
    ConfigError
        A missing or invalid model, one that cannot make a controller.yaml, one whose nominal
        plant nothing tracks, or a study with no complete trial (bad input: the model).
    TuneError, StorageError, StudyMismatchError, SamplerError
        Bad settings, an unusable storage, a stored study made for another model, seed or
        sampler, a sampler whose package is not installed.
    """
    settings = TuneSettings(trials=200) if settings is None else settings
    check_sampler(settings.sampler)
    model_cfg, model_sha, name = _load(model)
    try:  # a model whose θ box or valves cannot make a contract-4 controller: say so up front
        paper = controller_from_params(model_cfg, search_space(
            model_cfg, settings.objective.variant).paper_params(),
            dead_zone=settings.objective.dead_zone)
    except ConfigError as exc:
        raise ConfigError(name, exc.key, "cannot make a controller.yaml from this model: "
                          f"{exc.message}") from None
    settings, stroke_note = _fit_stroke(model_cfg, paper, settings, name)
    if stroke_note is not None and notes is not None:
        notes(stroke_note)
    scratch = None
    if settings.storage:
        storage = settings.storage
    elif settings.out is not None:
        storage = str(Path(settings.out) / DEFAULT_JOURNAL)
    else:  # nothing to be written: the study lives in a journal as long as the result
        scratch = tempfile.TemporaryDirectory(prefix="pneutune-tune-")
        storage = str(Path(scratch.name) / DEFAULT_JOURNAL)
    storage_scheme(storage)  # an unknown scheme is bad input before any simulation
    # folders that cannot be written are bad input before any simulation, not a traceback
    # after the study
    if settings.out is not None:
        _check_writable_folder(Path(settings.out), "out")
    if settings.storage and not is_url(settings.storage):
        _check_writable_folder(Path(settings.storage).parent, "storage")
        if Path(settings.storage).is_dir():
            raise argument_error(TuneError, "storage", f"{settings.storage} is a folder; give "
                                 "the journal file's path")
    # threads for a trial's draws: every CPU with one worker; the selection runs after the
    # workers have exited, so it may use every CPU whatever their number
    all_cpus = min(available_cpus(), settings.objective.n_draws)
    jobs = settings.jobs if settings.jobs is not None else (
        all_cpus if settings.workers == 1 else 1)
    dead_zone = settings.objective.dead_zone

    def make(params: dict[str, float]) -> ControllerConfig:
        return controller_from_params(model_cfg, params, dead_zone=dead_zone)

    arms: list[_Arm] = []
    for r in range(settings.restarts):
        arm_notes = notes if settings.restarts == 1 or notes is None else (
            lambda line, r=r: notes(f"[seed {settings.seed + r}] {line}"))
        # the bar runs over every study: those done count what they hold, those to come --trials
        before = sum(finished(a.run.counts_after) for a in arms)
        to_come = (settings.restarts - 1 - r) * settings.trials
        arm_progress = progress if progress is None else (
            lambda done, total, before=before, to_come=to_come:
            progress(before + done, before + total + to_come))
        arms.append(_run_arm(model_cfg, model_sha, name, storage, settings, settings.seed + r,
                             jobs, make, arm_progress, arm_notes))
    selection = None
    if settings.restarts > 1:
        if notes is not None:
            notes(f"scoring the {settings.restarts} restarts' controllers on selection draws")
        sel_jobs = settings.jobs if settings.jobs is not None else all_cpus
        selection = select([Candidate(a.seed, a.study_name, a.guard.trial,
                                      finished=finished(a.run.counts_after),
                                      this_run=finished(a.run.counts_after)
                                      - finished(a.run.counts_before)) for a in arms],
                           selection_objectives(model_cfg, settings.seed, settings.objective,
                                                sel_jobs), make)
        for line in selection.notes():
            if notes is not None:
                notes(line)
    arm = arms[0 if selection is None else selection.kept]
    feas, guard, run, study, study_name = arm.feas, arm.guard, arm.run, arm.run.study, \
        arm.study_name
    objective_settings, seed = arm.objective_settings, arm.seed
    counts = run.counts_after
    best = guard.trial
    prov = provenance(model_sha, study_name, best.number, float(best.value), seed,
                      [*([] if stroke_note is None else [stroke_note]), *feas.notes(),
                       *guard.notes(),
                       *([] if selection is None else selection.notes())])
    tuned = controller_from_params(model_cfg, best.params, prov, dead_zone=dead_zone)
    paper, moved = paper_on_rig(load_controller(PAPER_CONTROLLER), tuned)
    objective = TuneObjective(model_cfg, seed, objective_settings, jobs=jobs)
    comp = compare(objective, tuned, paper)
    behind = behind_paper(comp, best.number, settings)
    if behind is not None and notes is not None:
        notes(behind)
    log_check = check_logs(model_cfg, tuned, seed, name)
    for line in log_check.warnings():
        if notes is not None:
            notes(line)
    report_info = {
        "model": name, "model_sha256": model_sha, "storage": redact_url(storage),
        "n_trials": settings.trials, "counts": counts,
        "paper_path": paper_path(), "paper_moved": moved, "feasibility": feas.notes(),
        "stroke": stroke_note,
        "guard": guard.notes(), "guard_moved": guard.passed and bool(guard.rejected),
        "sampler": describe(settings.sampler),
        "behind_paper": behind, "log_check": log_check.lines(),
        "study": study_name, "seed": seed, "paper": paper,
        "restarts": None if selection is None else selection.rows(),
    }
    info = {"model": name, "model_sha256": model_sha, "seed": seed,
            "study": study_name, "storage": redact_url(storage), "workers": settings.workers,
            "jobs": jobs, "n_trials": settings.trials, "sampler": settings.sampler,
            "pruner": run.pruner,
            "restarts": None if selection is None else selection.rows(),
            **({} if selection is None else
               {"wall_s_restarts": sum(a.run.wall_s for a in arms)}),
            "behind_paper": behind, "log_check": log_check.as_dict(),
            "amplitude_scale": objective_settings.amplitude_scale}
    result = TuneResult(tuned, study, best, comp, feas, run, {}, info, guard,
                        objective, report_info, scratch)
    if settings.out is None:
        return result
    return dataclasses.replace(result, paths=result.save(settings.out))


@dataclass(frozen=True)
class _Arm:
    """One study of a tune (one restart): its seed, name, feasibility, run and guarded trial."""

    seed: int
    study_name: str
    feas: Feasibility
    objective_settings: ObjectiveSettings
    run: RunSummary
    guard: GuardResult


def _run_arm(model: ModelConfig, model_sha: str, name: str, storage: str,
             settings: TuneSettings, seed: int, jobs: int,
             make: Callable[[dict[str, float]], ControllerConfig],
             progress: Callable[[int, int], None] | None,
             notes: Callable[[str], None] | None) -> _Arm:
    """Check feasibility, run (or resume) the study of ``seed`` and apply the held-out guard."""
    try:
        feas = check_feasibility(model, seed, settings.objective, progress=notes, jobs=jobs)
    except InfeasibleModelError as exc:
        raise ConfigError(name, "", str(exc)) from None
    objective_settings = dataclasses.replace(settings.objective, box=feas.box)
    if settings.study and settings.restarts > 1:
        study_name = f"{settings.study}-seed{seed}"
    else:
        study_name = settings.study or default_study_name(
            model_sha, seed, settings.objective.variant, settings.sampler,
            settings.objective.dead_zone)
    first = [] if feas.paper_failure is None else [feas.reference_params]
    logged = _logged_trial(model, name, settings, first, notes)
    if logged is not None:
        first.append(logged)
    spec = StudySpec(storage, study_name, seed, settings.trials, settings.workers,
                     model_sha, objective_settings, jobs, extra_first=tuple(first),
                     sampler=settings.sampler, pruner=settings.pruner)
    run = run_study(spec, model, progress=progress)
    counts = run.counts_after
    if not any(t.state.name == "COMPLETE" for t in run.study.get_trials(deepcopy=False)):
        raise ConfigError(name, "", f"study {study_name!r}: no trial completed "
                          f"({counts['PRUNED']} pruned, {counts['FAIL']} failed): "
                          f"{failure_summary(run.study)}; check the model's ranges and fit")
    guard = guarded_best(run.study, model, seed, objective_settings, make, jobs=jobs)
    for line in guard.notes():
        if notes is not None:
            notes(line)
    return _Arm(seed, study_name, feas, objective_settings, run, guard)


def _same(a: dict[str, float], b: dict[str, float]) -> bool:
    """The same parameters, up to rounding (a Q rescaled by R / R')."""
    return a.keys() == b.keys() and all(math.isclose(a[k], b[k], rel_tol=1e-9) for k in a)


def _logged_trial(model: ModelConfig, model_path: str, settings: TuneSettings,
                  first: list[dict[str, float]],
                  notes: Callable[[str], None] | None) -> dict[str, float] | None:
    """The searched parameters of the controller that ran in the model's log, to enqueue as a
    trial (:func:`~pneutune.tune.logcheck.logged_controller`): a re-tune after a
    re-identification starts from the controller on the rig. None when the log names none, it
    is of another variant, or it is the paper's (trial 0) or the feasibility reference."""
    cfg, source = logged_controller(model, model_path, notes)
    if cfg is None:
        return None
    space = search_space(model, settings.objective.variant)
    params = space.params_of(cfg)
    if params is None:
        return None
    # trial 0 has the paper's gains with the model's θ̂3(0): the paper's controller file (3500
    # N s/m there) is the same candidate for the search, which covers θ̂3(0)
    gains = {k: v for k, v in params.items() if k != THETA_0_PARAM}
    if any(_same(gains, {k: v for k, v in other.items() if k != THETA_0_PARAM})
           for other in (space.paper_params(), *first)):
        return None
    if notes is not None:
        notes(f"the controller that ran in the log ({source}) is a trial of the study too")
    return params


def behind_paper(comp: Comparison, trial: int, settings: TuneSettings) -> str | None:
    """What to say when the kept trial scores worse than the paper's controller on the study's
    own plants and noise, or None when it does not.

    The study then has not found the region the paper's controller.yaml sits in (its θ box,
    valves and PWM curve are the paper rig's, not the model's). controller.yaml is still the
    kept trial, because it is made for this model; the line says what the user can do.
    """
    t, p = comp.tuned.value, comp.paper.value
    if p is None or not (t > p):
        return None
    return (f"warning: trial #{trial} scores {t:.4g} on the study's plants, worse than the "
            f"paper's controller ({p:.4g}): {settings.trials} trials did not find a better "
            f"region; resume with a larger --trials (the finished trials are kept), try "
            f"another --seed, or --restarts 3")


def _save(out: Path, result: TuneResult, objective: TuneObjective,
          report: dict[str, Any]) -> dict[str, str]:
    """controller.yaml and the nominal and worst plants (atomically), then report.md; their
    paths. An earlier report.md goes first: a run killed between the files leaves a new
    controller without a report (run the command again), never beside another trial's. Another
    ``tune`` writing to the same folder waits (:func:`~pneutune.tune.storage.out_lock`)."""
    with out_lock(out):
        (out / "report.md").unlink(missing_ok=True)
        paths = _write(out, report["model"], report["model_sha256"], report["study"],
                       result.best, result.controller, objective, result.comparison,
                       report["seed"])
        facts = {k: v for k, v in report.items() if k not in ("study", "seed", "paper")}
        paths["report"] = str(write_report(out, objective, result.study, result.best,
                                           result.controller, report["paper"],
                                           result.comparison, {**facts, **paths}))
    return paths


def _fit_stroke(model_cfg: ModelConfig, controller: ControllerConfig, settings: TuneSettings,
                name: str) -> tuple[TuneSettings, str | None]:
    """The settings with every scenario's reference, centred mid-stroke as ``simulate`` and
    ``deploy`` run it, within the limits of the controllers this model makes (its stroke).

    On a stroke too short for Table 1's 17.5 mm the scenarios are scaled to fit
    (:func:`~pneutune.control.sim.scenarios.stroke_scale`: the paper rig's clearance to the
    stroke ends in proportion), and Table 1's figures the objective normalises by with them;
    ``deploy`` and ``simulate`` scale them alike on that stroke. Otherwise a controller tuned
    on a stroke its scenarios overrun would score end-stop penalties.

    Returns
    -------
    settings : TuneSettings
        As given, or with ``objective.amplitude_scale`` lowered.
    note : str or None
        What was scaled (for the report and the controller's provenance); None when nothing.

    Raises
    ------
    ConfigError
        Naming the model's ``rig.x_max``: a stroke too short for any reference.
    """
    rig, lim, obj = model_cfg.rig, controller.limits, settings.objective
    scenarios = [SCENARIOS[n].scaled(obj.amplitude_scale) for n in obj.scenarios]
    try:
        factor = stroke_scale(scenarios, float(rig.Ts), 0.5 * (rig.x_min + rig.x_max),
                              lim.x_min, lim.x_max)
    except ExperimentError as exc:
        raise ConfigError(name, "rig.x_max", f"{exc} (check the rig block)") from None
    if factor == 1.0:
        return settings, None
    scale = obj.amplitude_scale * factor
    note = (f"The stroke [{rig.x_min * 1e3:.2f}, {rig.x_max * 1e3:.2f}] mm is too short for "
            f"Table 1's {AMPLITUDE * 1e3:.1f} mm about mid-stroke: every scenario's reference "
            f"is scaled by {scale:.3f} to {scale * AMPLITUDE * 1e3:.2f} mm, and Table 1's "
            "figures the objective is normalised by alike (deploy and simulate scale them the "
            "same on this stroke)")
    return dataclasses.replace(settings, objective=dataclasses.replace(
        obj, amplitude_scale=scale)), note


def _check_writable_folder(folder: Path, argument: str) -> None:
    """``folder`` exists (made if need be) and takes a new file.

    Raises
    ------
    TuneError
        Naming ``argument`` and why the folder cannot be written.
    """
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".pneutune-write-check-"):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise argument_error(TuneError, argument, f"names a folder that cannot be written, "
                             f"{folder} ({reason}): give one this user can write") from None


def _write(out: Path, name: str, model_sha: str, study_name: str, best: FrozenTrial,
           tuned: ControllerConfig, objective: TuneObjective, comp: Comparison,
           seed: int) -> dict[str, str]:
    """controller.yaml and the nominal and worst plants, atomically; their paths."""
    out.mkdir(parents=True, exist_ok=True)
    controller_path = out / "controller.yaml"
    nominal_path = out / "plant-nominal.yaml"
    worst_path = out / "plant-worst.yaml"
    header = (f"Tuned by `tune` (pneutune {version()}): study {study_name}, trial "
              f"{best.number}, objective {best.value:.6g}, seed {seed}.\n"
              f"Model {name} (sha256 {model_sha}).\n"
              f"Nominal runs: simulate --controller {controller_path} --plant "
              f"{nominal_path} --scenario all\n"
              "Contract 4 (pneutune.controller/1); docs/tuning.md.")
    save_controller(tuned, controller_path, header=header)
    # the file written loads back equal (contract 4 round trip)
    if load_controller(controller_path) != tuned:  # pragma: no cover - a bug in save/load
        raise RuntimeError(f"{controller_path} does not load back equal to the tuned config")
    write_yaml(nominal_path, objective.draws[0].plant.to_dict(),
               header=f"The nominal plant of {name} (draw 0), sensor-noise seed "
                      f"{objective.draws[0].noise_seed}. Contract 2.")
    wd = objective.draws[comp.worst_draw]
    write_yaml(worst_path, wd.plant.to_dict(),
               header=f"Draw {wd.index} ({wd.label}) of {name}, seed {seed}: where "
                      "the tuned controller does worst. Contract 2.")
    return {"controller": str(controller_path), "plant_nominal": str(nominal_path),
            "plant_worst": str(worst_path)}


__all__ = ["DEFAULT_OUT", "TuneResult", "TuneSettings", "available_cpus", "failure_summary",
           "provenance", "tune", "version"]
