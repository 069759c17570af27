"""Where a study lives: the journal file, RDB URLs, the lock of a local storage.

Storage (``--storage``):

* default: a journal file ``DIR/study.journal`` (Optuna's ``JournalStorage``; its records are
  written by :class:`TrialEndSyncBackend`). Every finished trial is an fsync'ed append, so
  ``kill -9`` loses at most the trials that were running; ``optuna-dashboard
  DIR/study.journal`` opens it.
* a path (any name not of the form ``scheme://``): a journal file at that path.
* ``sqlite:///path.db``, ``postgresql://user@host:port/db`` (or ``postgresql+psycopg2://``),
  ``mysql+pymysql://...``: Optuna's RDB storage, with a heartbeat every 10 s so that the trials
  of a killed worker are failed after 30 s (``optuna.storages.fail_stale_trials``).

A ``tune`` that finds no other ``tune`` on a local storage (:func:`local_lock`) drops a torn
last line a killed writer left in its journal (:func:`repair_journal`) before it opens the study,
and then fails the trials a killed run left RUNNING
(:func:`pneutune.tune.study.fail_leftover_trials`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import optuna

from pneutune.control.errors import PneutuneError, argument_error

#: Default journal file name in the output folder.
DEFAULT_JOURNAL = "study.journal"
#: A journal write lock unchanged for this long is a killed writer's and is taken over [s].
JOURNAL_LOCK_GRACE_S = 3
#: Heartbeat of RDB storages [s] and the silence after which a running trial is failed [s].
HEARTBEAT_INTERVAL = 10
GRACE_PERIOD = 30
_RDB_SCHEMES = ("sqlite", "postgresql", "postgres", "mysql", "mariadb", "oracle", "mssql")


class StorageError(PneutuneError, ValueError):
    """The storage URL or file cannot be used."""


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
        with _no_interrupt():
            self._lock.acquire()
            try:
                with open(self._path, "ab") as f:
                    f.write(text.encode("utf-8"))
                    f.flush()
                    if sync:
                        os.fsync(f.fileno())
            finally:
                self._lock.release()


@contextlib.contextmanager
def _no_interrupt() -> Iterator[None]:
    """SIGINT held back while the journal's lock is taken, written under and released (a few
    ms), then delivered. A Ctrl-C inside Optuna's lock release, between its unlink and the next
    bytecode, made its handler unlink the file again and turned the interrupt into a
    FileNotFoundError (exit 1 instead of 130). The handler is swapped rather than the signal
    masked: a SIGINT that arrived just before the block runs its Python handler at some later
    bytecode, which may be inside it. Outside the main thread nothing changes (Python runs
    signal handlers in the main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[tuple[int, Any]] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append((signum, frame)))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if held and callable(previous):
        previous(*held[0])


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


#: The lock file in a ``tune --out`` folder that serialises writing its outputs.
OUT_LOCK = ".tune-out.lock"


@contextlib.contextmanager
def out_lock(folder: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``folder/.tune-out.lock`` for the duration.

    Two ``tune`` runs with the same ``--out`` (sharing the study, or not) would otherwise
    interleave their files: one run's report.md beside the other's controller.yaml. Under the
    lock each run writes its controller.yaml, plants, report.md and plots together; the last
    to finish wins, whole.
    """
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / OUT_LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
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


__all__ = ["DEFAULT_JOURNAL", "GRACE_PERIOD", "HEARTBEAT_INTERVAL", "JOURNAL_LOCK_GRACE_S",
           "OUT_LOCK", "RUNNING_TRIAL_OPS", "StorageError", "TrialEndSyncBackend", "is_url",
           "local_file", "local_lock", "open_storage", "out_lock", "redact_url", "repair_journal",
           "storage_scheme"]
