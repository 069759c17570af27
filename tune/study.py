"""The Optuna study: storage, resume, several worker processes, several hosts.

Storage (``--storage``):

* default: a journal file ``DIR/study.journal`` (Optuna's ``JournalStorage``; its records are
  written by :class:`TrialEndSyncBackend`). Every finished trial is an fsync'ed append, so
  ``kill -9`` loses at most the trials that were running; ``optuna-dashboard
  DIR/study.journal`` opens it.
* a path (any name not of the form ``scheme://``): a journal file at that path.
* ``sqlite:///path.db``, ``postgresql://user@host:port/db`` (or ``postgresql+psycopg2://``),
  ``mysql+pymysql://...``: Optuna's RDB storage, with a heartbeat every 10 s so that the trials
  of a killed worker are failed after 30 s (``optuna.storages.fail_stale_trials``).

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

Pruning (``--pruner``, :func:`make_pruner`): ``median`` (the default): ``MedianPruner`` on
the running mean after each scenario (also every study made before the option); ``wilcoxon``:
Optuna's ``WilcoxonPruner`` on per-run reports (each (scenario, draw) run's cost at its instance
id, :class:`~pneutune.tune.objective.TuneObjective` with ``instance_reports``), which stops a
trial once a signed-rank test over the runs done so far finds it worse than the best trial on
the same runs; ``none``. A study keeps its pruner (stored with it when not ``median``); without
``--pruner`` a resumed study uses its own.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import multiprocessing
import os
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import optuna
from optuna.trial import TrialState

from pneutune.control.contracts.model import ModelConfig
from pneutune.control.errors import PneutuneError, argument_error

from .objective import ObjectiveSettings, TuneError, TuneObjective
from .samplers import DEFAULT_SAMPLER, N_STARTUP_TRIALS, check_sampler, make_sampler
from .space import search_space

#: Study user attribute holding what the study was created with.
META_KEY = "pneutune"
STUDY_SCHEMA = "pneutune.tune-study/1"
#: Default journal file name in the output folder.
DEFAULT_JOURNAL = "study.journal"
#: A journal write lock unchanged for this long is a killed writer's and is taken over [s].
JOURNAL_LOCK_GRACE_S = 3
#: Heartbeat of RDB storages [s] and the silence after which a running trial is failed [s].
HEARTBEAT_INTERVAL = 10
GRACE_PERIOD = 30
#: MedianPruner start-up trials (TPE's are :data:`pneutune.tune.samplers.N_STARTUP_TRIALS`). (A
#: PercentilePruner keeping the best third was measured too: 30 % faster, but a worse best trial
#: on 3 of 3 studies.)
PRUNER_STARTUP_TRIALS = 10
#: Pruners of ``--pruner``.
PRUNERS: tuple[str, ...] = ("wilcoxon", "median", "none")
#: The pruner of a new study when none is asked for (``wilcoxon`` is about twice as fast but
#: found a worse best trial on some seeds: docs/tuning.md, "Pruning").
DEFAULT_PRUNER = "median"
#: The pruner of a study whose metadata names none (made before the option).
LEGACY_PRUNER = "median"
#: WilcoxonPruner: p-value below which a trial is stopped as worse than the best one, and the
#: paired runs needed before any test (one chunk of draws).
WILCOXON_P_THRESHOLD = 0.1
WILCOXON_STARTUP_STEPS = 4
_RDB_SCHEMES = ("sqlite", "postgresql", "postgres", "mysql", "mariadb", "oracle", "mssql")


class StorageError(PneutuneError, ValueError):
    """The storage URL or file cannot be used."""


class StudyMismatchError(PneutuneError, ValueError):
    """An existing study was created for another model, seed, objective or search space."""


class WorkerError(RuntimeError):
    """A worker process failed (its traceback is on stderr): an internal failure, exit 1."""


def check_pruner(name: str | None) -> None:
    """Raise :class:`~pneutune.tune.objective.TuneError` unless ``name`` is None or one of
    :data:`PRUNERS`."""
    if name is not None and name not in PRUNERS:
        raise argument_error(TuneError, "pruner",
                             f"must be one of {', '.join(PRUNERS)}, got {name!r}")


def make_pruner(name: str) -> optuna.pruners.BasePruner:
    """The Optuna pruner of ``--pruner`` (module docstring).

    Parameters
    ----------
    name : str
        One of :data:`PRUNERS`.

    Returns
    -------
    optuna.pruners.BasePruner
    """
    check_pruner(name)
    if name == "wilcoxon":
        with warnings.catch_warnings():  # experimental in Optuna 3.6-5.x
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.pruners.WilcoxonPruner(p_threshold=WILCOXON_P_THRESHOLD,
                                                 n_startup_steps=WILCOXON_STARTUP_STEPS)
    if name == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=PRUNER_STARTUP_TRIALS,
                                           n_warmup_steps=0, interval_steps=1)
    return optuna.pruners.NopPruner()


def study_pruner(meta: dict[str, Any] | None, asked: str | None) -> str:
    """The pruner a study runs with: ``asked``, else the one stored in its metadata ``meta``
    (:data:`LEGACY_PRUNER` when it names none), else, for a new study (``meta`` None),
    :data:`DEFAULT_PRUNER`."""
    if asked is not None:
        return asked
    if meta is None:
        return DEFAULT_PRUNER
    return str(meta.get("pruner", LEGACY_PRUNER))


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


def is_url(storage: str) -> bool:
    """Whether ``storage`` is a ``scheme://`` URL (otherwise it is a journal file path)."""
    return "://" in storage


def local_file(storage: str) -> Path | None:
    """The file a local storage lives in (journal path or ``sqlite:///`` file), else None."""
    if not is_url(storage):
        return Path(storage)
    if storage.startswith("sqlite:///") and len(storage) > len("sqlite:///"):
        name = storage[len("sqlite:///"):]
        return None if name.startswith(":memory:") else Path(name)
    return None


def storage_scheme(storage: str) -> str:
    """The scheme of an RDB URL (``sqlite``, ``postgresql``, ...), ``journal`` for a path.

    Raises
    ------
    StorageError
        An unknown scheme.
    """
    if not is_url(storage):
        return "journal"
    scheme = storage.split("://", 1)[0].split("+", 1)[0].lower()
    if scheme not in _RDB_SCHEMES:
        raise argument_error(StorageError, "storage", f"{storage!r}: unknown scheme {scheme!r}; "
                             "expected a journal file path, sqlite:///FILE or "
                             "postgresql://USER@HOST:PORT/DB")
    return scheme


#: Journal records that only add to a running trial, by their ``op_code`` in the journal file
#: format (Optuna's ``JournalOperation``: CREATE_TRIAL 4, SET_TRIAL_PARAM 5,
#: SET_TRIAL_INTERMEDIATE_VALUE 7, SET_TRIAL_USER_ATTR 8, SET_TRIAL_SYSTEM_ATTR 9): written at
#: once, but not fsync'ed (:class:`TrialEndSyncBackend`).
RUNNING_TRIAL_OPS = frozenset({4, 5, 7, 8, 9})


class TrialEndSyncBackend(optuna.storages.journal.BaseJournalBackend):
    """Optuna's journal file, fsync'ed when a trial ends instead of after every record.

    Reading is Optuna's :class:`~optuna.storages.journal.JournalFileBackend`; appending writes
    the same JSON lines under the same lock, and flushes them to the operating system at once
    (a killed process loses nothing written). Only a record that ends a trial (its state and
    value) or changes the study is also fsync'ed, which puts every earlier record of the file on
    the disk too: a machine that goes down loses at most the records of running trials, which a
    resume discards anyway. A trial writes about twenty records (each parameter, each
    intermediate value); fsyncing each took about 2 % of a ``tune --trials 200``.

    Parameters
    ----------
    path : Path
        The journal file.
    lock : optuna.storages.journal.JournalFileSymlinkLock
        The lock every writer of the file takes.
    """

    def __init__(self, path: Path, lock: Any) -> None:
        self._path = str(path)
        self._lock = lock
        self._reader = optuna.storages.journal.JournalFileBackend(self._path, lock_obj=lock)

    def read_logs(self, log_number_from: int) -> Any:
        """The records from ``log_number_from`` on (Optuna's reader)."""
        return self._reader.read_logs(log_number_from)

    def append_logs(self, logs: list[dict[str, Any]]) -> None:
        """Append ``logs`` as JSON lines; fsync unless they only add to running trials."""
        text = "\n".join(json.dumps(log, separators=(",", ":")) for log in logs) + "\n"
        sync = any(log.get("op_code") not in RUNNING_TRIAL_OPS for log in logs)
        self._lock.acquire()
        try:
            with open(self._path, "ab") as f:
                f.write(text.encode("utf-8"))
                f.flush()
                if sync:
                    os.fsync(f.fileno())
        finally:
            self._lock.release()


def open_storage(storage: str) -> optuna.storages.BaseStorage:
    """Open a storage (module docstring).

    Parameters
    ----------
    storage : str
        A journal file path or an RDB URL.

    Returns
    -------
    optuna.storages.BaseStorage

    Raises
    ------
    StorageError
        Unknown scheme, unreachable server, unwritable file.
    """
    if not is_url(storage):
        path = Path(storage)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            # Optuna's own symlink lock, with a short grace period: a lock left by a writer
            # killed inside an append (it holds the lock for milliseconds) is taken over after
            # JOURNAL_LOCK_GRACE_S instead of Optuna's default 30 s
            lock = optuna.storages.journal.JournalFileSymlinkLock(
                str(path), grace_period=JOURNAL_LOCK_GRACE_S)
            backend = TrialEndSyncBackend(path, lock)
        except OSError as exc:
            raise StorageError(f"{storage}: cannot open the journal file ({exc})") from None
        return optuna.storages.JournalStorage(backend)
    scheme = storage_scheme(storage)
    kwargs: dict[str, Any] = {}
    if scheme == "sqlite":
        file = local_file(storage)
        if file is not None:
            file.parent.mkdir(parents=True, exist_ok=True)
        kwargs["engine_kwargs"] = {"connect_args": {"timeout": 60}}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(storage, heartbeat_interval=HEARTBEAT_INTERVAL,
                                              grace_period=GRACE_PERIOD, **kwargs)
    except Exception as exc:  # SQLAlchemy/driver errors: connection refused, bad URL, ...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise argument_error(StorageError, "storage",
                             f"{redact_url(storage)}: cannot open ({first})") from None


def redact_url(url: str) -> str:
    """The URL without its password."""
    if "://" not in url or "@" not in url:
        return url
    scheme, rest = url.split("://", 1)
    cred, host = rest.rsplit("@", 1)
    user = cred.split(":", 1)[0]
    return f"{scheme}://{user}{':***' if ':' in cred else ''}@{host}"


@contextlib.contextmanager
def local_lock(storage: str) -> Iterator[bool]:
    """Hold a shared ``flock`` on ``<storage file>.tune-lock`` for the duration.

    Yields
    ------
    bool
        True if no other process held the lock when we took it (this ``tune`` is alone on the
        storage, so RUNNING trials are leftovers of a killed run). Always False for a server.
    """
    file = local_file(storage)
    if file is None:
        yield False
        return
    file.parent.mkdir(parents=True, exist_ok=True)
    lock_path = file.with_name(file.name + ".tune-lock")
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            alone = True
        except BlockingIOError:
            alone = False
        fcntl.flock(fd, fcntl.LOCK_SH)  # converts (or waits for a cleaner to finish)
        yield alone
    finally:
        os.close(fd)


def repair_journal(path: Path) -> bool:
    """Drop a torn last line of a journal file (a write cut by a crash). Only when alone.

    Returns
    -------
    bool
        True if the file was truncated.
    """
    if not path.exists() or path.stat().st_size == 0:
        return False
    with open(path, "rb+") as fh:
        fh.seek(0, os.SEEK_END)
        size = fh.tell()
        fh.seek(max(0, size - 1))
        if fh.read(1) == b"\n":
            return False
        # find the last newline
        pos = size
        block = 4096
        keep = 0
        while pos > 0:
            start = max(0, pos - block)
            fh.seek(start)
            chunk = fh.read(pos - start)
            idx = chunk.rfind(b"\n")
            if idx >= 0:
                keep = start + idx + 1
                break
            pos = start
        fh.truncate(keep)
        fh.flush()
        os.fsync(fh.fileno())
    return True


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
        ``wilcoxon``, ``median`` or ``none`` (:func:`make_pruner`); None: the study's own (a
        new study: :data:`DEFAULT_PRUNER`). Stored with the study when not ``median``: a study
        is resumed only with its own pruner.
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
    :data:`DEFAULT_PRUNER`; :func:`study_pruner` tells which).

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


def _quiet_optuna() -> None:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)


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


__all__ = ["DEFAULT_JOURNAL", "DEFAULT_PRUNER", "N_STARTUP_TRIALS", "PRUNERS", "RunSummary",
           "StorageError", "StudyMismatchError", "StudySpec", "WorkerError", "check_pruner",
           "default_study_name", "fail_leftover_trials", "finished", "local_file", "local_lock",
           "make_pruner", "open_storage", "prepare_study", "redact_url", "repair_journal",
           "run_study", "sampler_seed", "storage_scheme", "study_pruner", "trial_counts", "work"]
