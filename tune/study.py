"""The Optuna study: storage, resume, several worker processes, several hosts.

Storage (``--storage``): :mod:`pneutune.tune.storage`.

Resume: re-running the same command opens the same study (default name
``tune-<model sha256[:12]>-seed<S>``) and runs only the remainder: ``--trials N`` is the number
of *finished* trials (complete or pruned) the study should hold in total. A worker starts a new
trial only while ``complete + pruned + running < N``; with K workers racing, the total can exceed
N by at most K - 1. Trials a killed run left RUNNING never count: on a local storage (journal or
SQLite file) a ``tune`` that finds no other ``tune`` on the same file (an ``flock`` on
``<storage>.tune-lock``) marks them FAIL at start; on a server they are failed by the heartbeat.
A study remembers the model's sha256, the seed, the objective settings and the search space
(study user attributes); resuming with different ones is an error.

Draw threads: ``--jobs J`` (default: the available CPUs with one worker, else 1) lets each
worker run the plant draws of a scenario on J threads (one compiled, multi-threaded call per
scenario). A run's result does not depend on which thread computes it, so this keeps a
one-worker study reproducible while using the cores.

Workers: ``--workers K`` starts K processes (``multiprocessing`` with the ``spawn`` start method)
on the one study; K = 1 runs in the calling process. Worker i samples with the study's sampler
(TPE by default; ``--sampler cmaes``: :mod:`pneutune.tune.samplers`) seeded by
``SeedSequence([seed, i, trials already in the study])``, so each worker is deterministic
given the study's history, and a resumed run does not repeat the random start-up points of the
first run. With one worker the whole study is reproducible (same seed, same trials, same best
trial); with several the interleaving of the workers is not. Each worker exits when its parent
dies, so ``kill -9`` of ``tune`` stops the whole run.

The first trial of a new study is the paper's Sec. 5.1 values (clipped to the ranges), so the
study always holds the baseline.

Pruning (``--pruner``): :mod:`pneutune.tune.pruners`.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import optuna
from optuna.trial import TrialState

from pneutune.control.contracts.model import ModelConfig
from pneutune.control.errors import PneutuneError, argument_error

from .objective import ObjectiveSettings, TuneObjective
from .pruners import LEGACY_PRUNER, check_pruner, make_pruner, study_pruner
from .samplers import DEFAULT_SAMPLER, check_sampler, make_sampler
from .space import search_space
from .storage import (
    StorageError,
    is_url,
    local_file,
    local_lock,
    open_storage,
    redact_url,
    repair_journal,
)

#: Study user attribute holding what the study was created with.
META_KEY = "pneutune"
STUDY_SCHEMA = "pneutune.tune-study/1"


class StudyMismatchError(PneutuneError, ValueError):
    """An existing study was created for another model, seed, objective or search space."""


class WorkerError(RuntimeError):
    """A worker process failed (its traceback is on stderr): an internal failure, exit 1."""


def default_study_name(model_sha256: str, seed: int, variant: str = "modified_darc",
                       sampler: str = DEFAULT_SAMPLER, dead_zone: str = "up") -> str:
    """``tune-<sha256[:12]>-seed<S>`` (``-pid`` appended for the pid variant, ``-cmaes`` for a
    sampler other than TPE, ``-dither`` for ``--dead-zone dither``): the same command resumes
    the same study."""
    suffix = "" if variant == "modified_darc" else f"-{variant}"
    if sampler != DEFAULT_SAMPLER:
        suffix += f"-{sampler}"
    if dead_zone != "up":
        suffix += f"-{dead_zone}"
    return f"tune-{model_sha256[:12]}-seed{seed}{suffix}"


def fail_leftover_trials(study: optuna.Study) -> int:
    """Mark every RUNNING trial FAIL (call only when no other worker can be running).

    Returns
    -------
    int
        How many.
    """
    n = 0
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        study.tell(t.number, state=TrialState.FAIL, skip_if_finished=True)
        n += 1
    return n


def trial_counts(study: optuna.Study) -> dict[str, int]:
    """Trials per state name (``COMPLETE``, ``PRUNED``, ``FAIL``, ``RUNNING``, ``WAITING``)."""
    counts = {s.name: 0 for s in TrialState}
    for t in study.get_trials(deepcopy=False):
        counts[t.state.name] += 1
    return counts


def finished(counts: dict[str, int]) -> int:
    """Finished trials in the sense of ``--trials``: complete + pruned."""
    return counts["COMPLETE"] + counts["PRUNED"]


@dataclass(frozen=True)
class StudySpec:
    """Everything a worker needs (plain data, so it crosses a ``spawn`` boundary).

    Attributes
    ----------
    storage : str
        Journal path or RDB URL.
    study_name : str
    seed : int
    n_trials : int
        Finished trials wanted in total.
    workers : int
    model_sha256 : str
    settings : ObjectiveSettings
    jobs : int
        Threads per worker running a trial's plant draws in parallel (the values do not
        depend on it; :class:`~pneutune.tune.objective.TuneObjective`).
    extra_first : tuple of dict
        Parameters enqueued after the paper's, in order, as the next trials of a new study: the
        reference controller of :mod:`pneutune.tune.feasibility` when the paper's gains do not
        track the nominal plant, and the controller that ran in the model's log.
    sampler : str
        ``tpe`` (default) or ``cmaes`` (:mod:`pneutune.tune.samplers`; ``gp`` for benchmarks).
        Stored with the study when not ``tpe``: a study is resumed only with its own sampler.
    pruner : str or None
        ``staged``, ``wilcoxon``, ``median`` or ``none``
        (:func:`~pneutune.tune.pruners.make_pruner`);
        None: the study's own (a new study: :data:`~pneutune.tune.pruners.DEFAULT_PRUNER`).
        Stored with the study when not ``median``: a study is resumed only with its own pruner.
    """

    storage: str
    study_name: str
    seed: int
    n_trials: int
    workers: int
    model_sha256: str
    settings: ObjectiveSettings = field(default_factory=ObjectiveSettings)
    jobs: int = 1
    extra_first: tuple[dict[str, float], ...] = ()
    sampler: str = DEFAULT_SAMPLER
    pruner: str | None = None

    def meta(self, model: ModelConfig) -> dict[str, Any]:
        """What the study is created with (stored, then checked on resume)."""
        meta = {"schema": STUDY_SCHEMA, "model_sha256": self.model_sha256, "seed": self.seed,
                "objective": self.settings.to_dict(),
                "space": search_space(model, self.settings.variant).signature()}
        if self.sampler != DEFAULT_SAMPLER:  # studies made before the option resume unchanged
            meta["sampler"] = self.sampler
        if self.pruner not in (None, LEGACY_PRUNER):  # likewise
            meta["pruner"] = self.pruner
        return meta

    def to_dict(self) -> dict[str, Any]:
        """Plain data."""
        return {"storage": self.storage, "study_name": self.study_name, "seed": self.seed,
                "n_trials": self.n_trials, "workers": self.workers,
                "model_sha256": self.model_sha256, "settings": self.settings.to_dict(),
                "jobs": self.jobs, "extra_first": [dict(p) for p in self.extra_first],
                "sampler": self.sampler, "pruner": self.pruner}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> StudySpec:
        """Inverse of :meth:`to_dict`."""
        d = dict(data)
        d["settings"] = ObjectiveSettings.from_dict(d["settings"])
        d["extra_first"] = tuple(dict(p) for p in d.get("extra_first") or ())
        return cls(**d)


def _normalise(obj: Any) -> Any:
    """JSON-like normal form (tuples as lists) for comparing stored and wanted metadata."""
    if isinstance(obj, dict):
        return {k: _normalise(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_normalise(v) for v in obj]
    return obj


def prepare_study(spec: StudySpec, model: ModelConfig) -> optuna.Study:
    """Create the study, or load it and check that it was made for this model, seed and settings.

    A new study gets its metadata and, as its first trial, the paper's parameters (then those
    of ``spec.extra_first``). ``spec.pruner`` None takes the study's own pruner (a new study:
    :data:`~pneutune.tune.pruners.DEFAULT_PRUNER`; :func:`study_pruner` tells which).

    Raises
    ------
    StudyMismatchError
        The existing study was created with another model, seed, objective or space.
    StorageError
        The storage cannot be opened.
    """
    storage = open_storage(spec.storage)
    study = optuna.create_study(storage=storage, study_name=spec.study_name,
                                direction="minimize", load_if_exists=True)
    have = study.user_attrs.get(META_KEY)
    spec = dataclasses.replace(spec, pruner=study_pruner(have, spec.pruner))
    want = _normalise(spec.meta(model))
    if have is None:
        study.set_user_attr(META_KEY, want)
        if not study.get_trials(deepcopy=False):
            study.enqueue_trial(search_space(model, spec.settings.variant).paper_params(),
                                skip_if_exists=True)
            for params in spec.extra_first:
                study.enqueue_trial(dict(params), skip_if_exists=True)
        return study
    have = _normalise(have)
    diffs = [k for k in want if have.get(k) != want[k]]
    defaults = {"sampler": DEFAULT_SAMPLER, "pruner": LEGACY_PRUNER}  # stored when not these
    for key, default in defaults.items():
        if key in have and key not in want:  # e.g. a CMA-ES study resumed with TPE
            want[key] = default
            diffs.append(key)
    if diffs:
        detail = "; ".join(f"{k}: study has "
                           f"{_short(have.get(k, defaults.get(k)))}, "
                           f"this run {_short(want[k])}"
                           for k in diffs)
        raise StudyMismatchError(
            f"study {spec.study_name!r} in {redact_url(spec.storage)} was created for another "
            f"{', '.join(diffs)} ({detail}); use another --study or --out")
    return study


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def sampler_seed(seed: int, worker: int, n_existing: int) -> int:
    """Seed of worker ``worker``'s sampler given the trials already in the study."""
    return int(np.random.SeedSequence([int(seed), int(worker), int(n_existing)])
               .generate_state(1)[0])


class _NoInterruptTraceback(logging.Filter):
    """Drop Optuna's report of a trial stopped by Ctrl-C (a traceback of the interrupted
    simulation, then "Trial N failed with value None."): the command says ``error:
    interrupted`` itself, and a resumed run redoes the trial."""

    def __init__(self) -> None:
        super().__init__()
        self._interrupted = False

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, KeyboardInterrupt):
            self._interrupted = True
            return False
        if self._interrupted and "failed with value None" in record.getMessage():
            self._interrupted = False
            return False
        return True


def _quiet_optuna() -> None:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    log = logging.getLogger("optuna.study._optimize")  # where Optuna reports a failed trial
    if not any(isinstance(f, _NoInterruptTraceback) for f in log.filters):
        log.addFilter(_NoInterruptTraceback())


def work(spec: StudySpec, model: ModelConfig, worker: int = 0,
         on_trial: Callable[[], None] | None = None, parent_pid: int | None = None,
         only_waiting: bool = False) -> int:
    """Run trials on the study until it holds ``spec.n_trials`` finished ones.

    Parameters
    ----------
    spec : StudySpec
    model : ModelConfig
    worker : int
        Worker index (sampler seed).
    on_trial : callable, optional
        Called after each trial this worker finishes (progress).
    parent_pid : int, optional
        Stop when the parent process is gone.
    only_waiting : bool
        Run only the enqueued (WAITING) trials, then return.

    Returns
    -------
    int
        Trials this worker ran.
    """
    _quiet_optuna()
    storage = open_storage(spec.storage)
    study_id = storage.get_study_id_from_name(spec.study_name)
    n_existing = len(storage.get_all_trials(study_id, deepcopy=False))
    sampler = make_sampler(spec.sampler, sampler_seed(spec.seed, worker, n_existing))
    pruner_name = study_pruner(storage.get_study_user_attrs(study_id).get(META_KEY),
                               spec.pruner)
    pruner = make_pruner(pruner_name)
    study = optuna.load_study(study_name=spec.study_name, storage=storage, sampler=sampler,
                              pruner=pruner)
    callbacks = [] if on_trial is None else [lambda _s, _t: on_trial()]
    ran = 0
    objective: TuneObjective | None = None
    while True:
        if parent_pid is not None and os.getppid() != parent_pid:
            break
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            optuna.storages.fail_stale_trials(study)
        counts = trial_counts(study)
        if finished(counts) + counts["RUNNING"] >= spec.n_trials:
            break
        if only_waiting and counts["WAITING"] == 0:
            break
        if objective is None:  # only now: a resumed, finished study prepares no runs
            objective = TuneObjective(model, spec.seed, spec.settings, jobs=spec.jobs,
                                      instance_reports=pruner_name == "wilcoxon")
        study.optimize(objective, n_trials=1, gc_after_trial=False, callbacks=callbacks)
        ran += 1
    return ran


def _worker_main(spec_data: dict[str, Any], model_data: dict[str, Any], worker: int,
                 parent_pid: int) -> None:
    """Entry point of a spawned worker (plain-data arguments)."""
    spec = StudySpec.from_dict(spec_data)
    model = ModelConfig.model_validate(model_data)
    work(spec, model, worker=worker, parent_pid=parent_pid)


@dataclass
class RunSummary:
    """What :func:`run_study` did.

    Attributes
    ----------
    study : optuna.Study
    counts_before, counts_after : dict
        Trials per state before and after.
    leftovers_failed : int
        RUNNING trials of a killed run marked FAIL at start.
    journal_repaired : bool
        A torn last journal line was dropped.
    wall_s : float
        Wall time of the optimisation [s].
    pruner : str
        The study's pruner (:func:`make_pruner`).
    """

    study: optuna.Study
    counts_before: dict[str, int]
    counts_after: dict[str, int]
    leftovers_failed: int
    journal_repaired: bool
    wall_s: float
    pruner: str = LEGACY_PRUNER


def run_study(spec: StudySpec, model: ModelConfig,
              progress: Callable[[int, int], None] | None = None,
              poll_s: float = 0.5) -> RunSummary:
    """Create or resume the study and run it to ``spec.n_trials`` finished trials.

    Parameters
    ----------
    spec : StudySpec
    model : ModelConfig
    progress : callable, optional
        ``progress(finished, total)`` now and then.
    poll_s : float
        Progress polling period with several workers [s].

    Returns
    -------
    RunSummary

    Raises
    ------
    WorkerError
        A worker process exited with an error.
    """
    _quiet_optuna()
    if spec.workers < 1:
        raise argument_error(StorageError, "workers", f"must be >= 1, got {spec.workers}")
    if spec.n_trials < 1:
        raise argument_error(StorageError, "trials", f"must be >= 1, got {spec.n_trials}")
    if spec.jobs < 1:
        raise argument_error(StorageError, "jobs", f"must be >= 1, got {spec.jobs}")
    check_sampler(spec.sampler)
    check_pruner(spec.pruner)
    t0 = time.perf_counter()
    with local_lock(spec.storage) as alone:
        repaired = False
        file = local_file(spec.storage)
        if alone and file is not None and not is_url(spec.storage):
            repaired = repair_journal(file)
        study = prepare_study(spec, model)
        spec = dataclasses.replace(spec, pruner=study_pruner(study.user_attrs.get(META_KEY),
                                                             spec.pruner))
        leftovers = fail_leftover_trials(study) if alone else 0
        before = trial_counts(study)
        if progress is not None:
            progress(finished(before), spec.n_trials)
        if spec.workers == 1:
            def tick() -> None:
                if progress is not None:
                    progress(finished(trial_counts(study)), spec.n_trials)

            work(spec, model, worker=0, on_trial=tick)
        else:
            _run_processes(spec, model, study, progress, poll_s)
        after = trial_counts(study)
        if progress is not None:
            progress(finished(after), spec.n_trials)
    return RunSummary(study, before, after, leftovers, repaired, time.perf_counter() - t0,
                      str(spec.pruner))


def _run_processes(spec: StudySpec, model: ModelConfig, study: optuna.Study,
                   progress: Callable[[int, int], None] | None, poll_s: float) -> None:
    # The enqueued trials (the paper's gains) run here first: workers popping the same waiting
    # trial race on SQLite ("Cannot tell a COMPLETE trial", optuna/optuna#4621).
    work(spec, model, worker=0, only_waiting=True)
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_worker_main, name=f"tune-worker-{i}",
                         args=(spec.to_dict(), model.to_dict(), i, os.getpid()))
             for i in range(spec.workers)]
    for p in procs:
        p.start()
    try:
        while any(p.is_alive() for p in procs):
            for p in procs:
                p.join(timeout=poll_s / len(procs))
            if progress is not None:
                progress(finished(trial_counts(study)), spec.n_trials)
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
            p.join()
    bad = [(p.name, p.exitcode) for p in procs if p.exitcode != 0]
    if bad:
        raise WorkerError(f"worker process(es) failed: {bad} (see the traceback above)")


__all__ = ["RunSummary", "StudyMismatchError", "StudySpec", "WorkerError", "default_study_name",
           "fail_leftover_trials", "finished", "prepare_study", "run_study", "sampler_seed",
           "trial_counts", "work"]
