"""tune's storage: resume after kill -9, several workers on one journal/SQLite study.

Each test runs the real ``tune`` command in a subprocess with the quick objective settings
(``tune_helpers.QUICK``: one 4 s scenario on two plants).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import optuna
import pytest
from tune_helpers import (
    QUICK,
    TUNE,
    load_study,
    only_study_name,
    run_tune,
    trial_table,
    write_truth_model,
)

from pneutune.tune.storage import JOURNAL_LOCK_GRACE_S, open_storage, repair_journal

FINISHED = ("COMPLETE", "PRUNED")


def _finished(study: optuna.Study) -> int:
    return sum(1 for t in study.get_trials(deepcopy=False) if t.state.name in FINISHED)


def _wait_for(journal: Path, n: int, proc: subprocess.Popen, timeout: float = 120.0) -> str:
    """Wait until the journal's one study has >= n finished trials; return its name."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc.poll() is not None:
            raise AssertionError(f"tune ended early ({proc.returncode}): {proc.stderr.read()}")
        if journal.exists() and journal.stat().st_size > 0:
            try:
                name = only_study_name(str(journal))
                if _finished(load_study(str(journal), name)) >= n:
                    return name
            except AssertionError:
                pass
        time.sleep(0.05)
    raise AssertionError(f"fewer than {n} finished trials after {timeout} s")


def test_resume_after_kill_9_keeps_every_finished_trial(tmp_path: Path) -> None:
    model = write_truth_model(tmp_path)
    out = tmp_path / "out"
    journal = out / "study.journal"
    args = ["--model", str(model), "--trials", "60", "--out", str(out), *QUICK]
    proc = subprocess.Popen([*TUNE, *args, "--json"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        name = _wait_for(journal, 8, proc)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    before = trial_table(load_study(str(journal), name))
    done_before = {n: row for n, row in before.items() if row[0] in FINISHED}
    assert 8 <= len(done_before) < 60  # killed mid-study

    code, res, err = run_tune(args)
    assert code == 0, err
    after = trial_table(load_study(str(journal), name))
    for n, row in done_before.items():  # no finished trial lost or changed
        assert after[n] == row
    states = [row[0] for row in after.values()]
    assert sum(s in FINISHED for s in states) == 60  # the remainder was completed
    assert "RUNNING" not in states
    # a trial killed while running is failed on resume, not counted, not left running
    running_before = [n for n, row in before.items() if row[0] == "RUNNING"]
    assert res is not None and res["trials"]["leftovers_failed"] == len(running_before)
    for n in running_before:
        assert after[n][0] == "FAIL"


def test_ctrl_c_says_where_the_finished_trials_are_and_how_to_resume(tmp_path: Path) -> None:
    """SIGINT mid-study: exit 130, one line naming the journal that keeps the finished trials
    and how to resume, then ``error: interrupted``."""
    model = write_truth_model(tmp_path)
    out = tmp_path / "out"
    journal = out / "study.journal"
    proc = subprocess.Popen([*TUNE, "--model", str(model), "--trials", "60", "--out", str(out),
                             *QUICK], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        _wait_for(journal, 4, proc)
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert (f"tune: every finished trial is kept in {journal}; run the same command again to "
            "resume the study") in err
    assert err.rstrip().endswith("error: interrupted")


@pytest.mark.parametrize("storage", ["journal", "sqlite"])
def test_two_workers_give_unique_complete_trials(storage: str, tmp_path: Path) -> None:
    model = write_truth_model(tmp_path)
    out = tmp_path / "out"
    url = str(out / "study.journal") if storage == "journal" else f"sqlite:///{out}/study.db"
    n = 24
    code, res, err = run_tune(["--model", str(model), "--trials", str(n), "--out", str(out),
                               "--storage", url, "--workers", "2", *QUICK])
    assert code == 0, err
    assert res is not None
    study = load_study(url, res["study"])
    trials = study.get_trials(deepcopy=False)
    states = [t.state.name for t in trials]
    # complete + pruned reaches N; two racing workers may overshoot by at most one
    assert n <= sum(s in FINISHED for s in states) <= n + 1
    assert all(s in FINISHED for s in states), states
    assert len({t.number for t in trials}) == len(trials)
    keys = {tuple(sorted(t.params.items())) for t in trials}
    assert len(keys) == len(trials)  # no parameter set evaluated twice
    assert all(len(t.params) == 14 for t in trials)  # no θ̂3(0): b ranges 0.074 wide
    assert trials[0].system_attrs.get("fixed_params") is not None  # the paper's, enqueued


def test_killing_tune_stops_its_workers(tmp_path: Path) -> None:
    """Workers exit when their parent dies: the journal stops growing after kill -9."""
    model = write_truth_model(tmp_path)
    out = tmp_path / "out"
    journal = out / "study.journal"
    proc = subprocess.Popen([*TUNE, "--model", str(model), "--trials", "100000", "--out",
                             str(out), "--workers", "2", *QUICK], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(journal, 4, proc)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate()
    time.sleep(2.0)  # a worker finishes its current trial (~20 ms), then sees the parent gone
    size = journal.stat().st_size
    time.sleep(1.5)
    assert journal.stat().st_size == size


def test_a_torn_journal_line_is_dropped(tmp_path: Path) -> None:
    path = tmp_path / "j"
    path.write_bytes(b'{"a":1}\n{"b":2}\n{"c":')
    assert repair_journal(path)
    assert path.read_bytes() == b'{"a":1}\n{"b":2}\n'
    assert not repair_journal(path)


def test_a_stale_journal_write_lock_is_taken_over(tmp_path: Path) -> None:
    """Optuna's symlink lock left by a writer killed inside an append is taken over after the
    grace period tune gives the lock (JOURNAL_LOCK_GRACE_S = 3 s; Optuna's default is 30 s):
    a study opens and records a trial within a few seconds."""
    journal = tmp_path / "study.journal"
    journal.write_bytes(b"")
    os.symlink(journal, tmp_path / "study.journal.lock")  # what the killed writer left
    t0 = time.monotonic()
    study = optuna.create_study(storage=open_storage(str(journal)), study_name="s")
    study.optimize(lambda t: t.suggest_float("x", 0.0, 1.0), n_trials=1)
    assert time.monotonic() - t0 < JOURNAL_LOCK_GRACE_S + 10.0
    assert len(study.trials) == 1
    assert not os.path.lexists(tmp_path / "study.journal.lock")


def test_the_journal_is_fsynced_when_a_trial_ends(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """The records that only add to a running trial (its parameters, intermediate values,
    attributes) are written at once but not fsync'ed; the one that ends it is, and Optuna's own
    reader reads the file as its own backend would have written it."""
    from optuna.storages.journal._storage import JournalOperation as Op

    from pneutune.tune import storage as storage_mod

    # the op codes are the journal file format's, spelt as numbers in storage.py
    assert {int(op) for op in (Op.CREATE_TRIAL, Op.SET_TRIAL_PARAM,
                               Op.SET_TRIAL_INTERMEDIATE_VALUE, Op.SET_TRIAL_USER_ATTR,
                               Op.SET_TRIAL_SYSTEM_ATTR)} == set(storage_mod.RUNNING_TRIAL_OPS)
    synced: list[int] = []
    real_fsync = os.fsync
    monkeypatch.setattr(storage_mod.os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    journal = tmp_path / "study.journal"
    study = optuna.create_study(storage=open_storage(str(journal)), study_name="s")
    at_start = len(synced)  # creating the study

    def objective(trial: optuna.Trial) -> float:
        x = sum(trial.suggest_float(f"x{i}", 0.0, 1.0) for i in range(5))
        for step in range(3):
            trial.report(x + step, step)
        trial.set_user_attr("note", "n")
        return x

    study.optimize(objective, n_trials=3)
    assert len(synced) - at_start == 3  # one per trial: 3 x 11 records written
    plain = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
    again = optuna.load_study(study_name="s", storage=plain)
    assert [t.params for t in again.trials] == [t.params for t in study.trials]
    assert [t.intermediate_values for t in again.trials] == [t.intermediate_values
                                                             for t in study.trials]
    assert [t.value for t in again.trials] == [t.value for t in study.trials]


def test_an_interrupted_trial_leaves_no_traceback() -> None:
    """Ctrl-C inside a trial: Optuna reports the trial with the traceback of the interrupted
    simulation, then "Trial N failed with value None."; tune says "error: interrupted" itself,
    so both are dropped, and other reports pass."""
    import logging
    import sys

    from pneutune.tune.study import _NoInterruptTraceback

    f = _NoInterruptTraceback()
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:
        info = sys.exc_info()

    def record(msg: str, exc_info=None) -> logging.LogRecord:
        return logging.LogRecord("optuna.study._optimize", logging.WARNING, __file__, 1, msg,
                                 (), exc_info)

    assert f.filter(record("Trial 3 failed with parameters: {}", info)) is False
    assert f.filter(record("Trial 3 failed with value None.")) is False
    assert f.filter(record("Trial 4 failed with value None.")) is True
    assert f.filter(record("Trial 5 failed because of the following error: X")) is True


def test_a_failure_raised_while_a_ctrl_c_went_through_a_library_is_the_interrupt(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Optuna's journal lock, interrupted inside its release, fails with FileNotFoundError in
    its own clean-up (and its trial loop with UnboundLocalError): an exception whose context
    holds a KeyboardInterrupt exits 130 with ``error: interrupted``, not as an internal
    failure (exit 1)."""
    from pneutune.control.cli.common import run_cli

    def main(argv: object) -> int:
        try:
            raise KeyboardInterrupt
        except BaseException:
            raise FileNotFoundError(2, "No such file or directory") from None

    def main_chained(argv: object) -> int:
        try:
            raise KeyboardInterrupt
        except BaseException:
            raise FileNotFoundError(2, "No such file or directory")  # noqa: B904

    with pytest.raises(SystemExit) as exc:
        run_cli(main_chained, [])
    assert exc.value.code == 130
    assert capsys.readouterr().err == "error: interrupted\n"
    with pytest.raises(SystemExit) as exc:  # `from None` hides the context: a real failure
        run_cli(main, [])
    assert exc.value.code == 1
