"""Shared helpers of the tune tests: a truth model file, quick settings, reading a study."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import optuna

from pneutune.control.contracts.model import save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant

#: Quick objective settings for CLI tests: one scenario, two plants, 4 s runs (~10 ms a trial),
#: the draws in the tune process itself (no draw processes to start).
QUICK: list[str] = ["--scenarios", "sine-0.5hz", "--draws", "2", "--duration", "4.0", "--jobs",
                    "1"]
#: The CLI as a subprocess.
TUNE: list[str] = [sys.executable, "-m", "pneutune.tune.cli"]


def write_truth_model(folder: Path) -> Path:
    """``model_from_plant(PlantConfig())`` (the default plant, ranges ±20 %) as model.yaml."""
    path = folder / "model.yaml"
    save_model(model_from_plant(PlantConfig()), path)
    return path


def load_study(storage: str, name: str) -> optuna.Study:
    """Open a study read-only-ish (journal path or RDB URL)."""
    if "://" in storage:
        st: optuna.storages.BaseStorage = optuna.storages.RDBStorage(storage)
    else:
        st = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage))
    return optuna.load_study(study_name=name, storage=st)


def only_study_name(storage: str) -> str:
    """The name of the single study in a storage."""
    if "://" in storage:
        st: optuna.storages.BaseStorage = optuna.storages.RDBStorage(storage)
    else:
        st = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage))
    names = [s.study_name for s in optuna.get_all_study_summaries(st)]
    if len(names) != 1:
        raise AssertionError(f"expected one study in {storage}, got {names}")
    return names[0]


def run_tune(args: list[str], timeout: float = 300.0) -> tuple[int, dict[str, Any] | None, str]:
    """Run ``tune ... --json`` in a subprocess: (exit status, the JSON object, stderr)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.run([*TUNE, *args, "--json"], capture_output=True, text=True,
                          timeout=timeout, env=env)
    lines = proc.stdout.splitlines()
    obj = json.loads(lines[0]) if len(lines) == 1 else None
    return proc.returncode, obj, proc.stderr


def trial_table(study: optuna.Study) -> dict[int, tuple[str, dict[str, float], float | None]]:
    """number -> (state, params, value) of every trial."""
    return {t.number: (t.state.name, dict(t.params), t.value)
            for t in study.get_trials(deepcopy=False)}
