"""tune on a PostgreSQL study: a throw-away server on loopback.

The fixture starts a cluster of the Debian ``postgresql-15`` server in a temporary folder, as an
unprivileged user when the tests run as root (initdb refuses root), listening on 127.0.0.1 at a
free port with trust authentication, and stops it (``pg_ctl stop -m immediate``) and removes the
folder in a finalizer. Without the server binaries the test is skipped with the reason.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from tune_helpers import QUICK, load_study, run_tune, write_truth_model

PG_BIN = Path(os.environ.get("PNEUTUNE_PG_BIN", "/usr/lib/postgresql/15/bin"))
FINISHED = ("COMPLETE", "PRUNED")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def postgres_url() -> Iterator[str]:
    """``postgresql+psycopg2://tune@127.0.0.1:<port>/pneutune`` of a fresh cluster."""
    missing = [b for b in ("initdb", "pg_ctl", "postgres", "createdb")
               if not (PG_BIN / b).is_file()]
    if missing:
        pytest.skip(f"PostgreSQL server binaries not found in {PG_BIN} (missing: "
                    f"{', '.join(missing)}); install postgresql-15 or set PNEUTUNE_PG_BIN")
    pytest.importorskip("psycopg2", reason="psycopg2 (the PostgreSQL driver) is not installed")
    root = Path(tempfile.mkdtemp(prefix="pneutune-pg-"))
    prefix: list[str] = []
    if os.geteuid() == 0:  # initdb refuses to run as root: run the server as nobody
        if shutil.which("runuser") is None:
            shutil.rmtree(root, ignore_errors=True)
            pytest.skip("running as root and runuser is missing: cannot start PostgreSQL as an "
                        "unprivileged user")
        user = pwd.getpwnam("nobody")
        os.chown(root, user.pw_uid, user.pw_gid)
        prefix = ["runuser", "-u", "nobody", "--"]
    data = root / "data"
    port = _free_port()

    def pg(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*prefix, *args], capture_output=True, text=True, timeout=120,
                              cwd=root)

    started = False
    try:
        r = pg(str(PG_BIN / "initdb"), "-D", str(data), "-U", "tune", "--auth=trust",
               "--no-sync", "-E", "UTF8")
        assert r.returncode == 0, r.stderr
        r = pg(str(PG_BIN / "pg_ctl"), "-D", str(data), "-l", str(root / "server.log"), "-w",
               "-t", "60", "-o", f"-p {port} -k {root} -c listen_addresses=127.0.0.1 "
               "-c fsync=off -c max_connections=40", "start")
        assert r.returncode == 0, r.stderr + (root / "server.log").read_text()
        started = True
        r = pg(str(PG_BIN / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "tune",
               "pneutune")
        assert r.returncode == 0, r.stderr
        yield f"postgresql+psycopg2://tune@127.0.0.1:{port}/pneutune"
    finally:
        if started:
            pg(str(PG_BIN / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(root, ignore_errors=True)


def test_two_workers_share_a_postgresql_study_and_resume(postgres_url: str,
                                                         tmp_path: Path) -> None:
    model = write_truth_model(tmp_path)
    args = ["--model", str(model), "--out", str(tmp_path / "out"), "--storage", postgres_url,
            "--study", "axis1", "--workers", "2", *QUICK]
    code, res, err = run_tune([*args, "--trials", "12"])
    assert code == 0, err
    assert res is not None and res["storage"] == postgres_url  # no password to hide
    study = load_study(postgres_url, "axis1")
    trials = study.get_trials(deepcopy=False)
    assert 12 <= sum(t.state.name in FINISHED for t in trials) <= 13
    assert all(t.state.name in FINISHED for t in trials)
    assert len({tuple(sorted(t.params.items())) for t in trials}) == len(trials)
    assert not (tmp_path / "out" / "study.journal").exists()  # the study is on the server
    first = {t.number: (t.params, t.value) for t in trials}

    # a second host (here: a second command) joins the study and completes it to 16
    code, res, err = run_tune([*args, "--trials", "16", "--workers", "1"])
    assert code == 0, err
    trials = load_study(postgres_url, "axis1").get_trials(deepcopy=False)
    assert sum(t.state.name in FINISHED for t in trials) == 16
    for t in trials:
        if t.number in first:
            assert (t.params, t.value) == first[t.number]
