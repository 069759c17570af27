"""The library API: identify, tune and deploy as functions, and the README's notebook example.

The README's example runs as written except for its sizes: 2 trials on one short scenario
instead of 200 on the full protocol, and a 2 s deploy. Each substitution must match exactly
once, so an edit of the README that breaks the example fails here.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import pytest

from pneutune.control import deploy
from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.errors import ExperimentError, command_message
from pneutune.control.logs.reader import read_run_log
from pneutune.identify import IdentifyResult, identify
from pneutune.tune.objective import ObjectiveSettings

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "data" / "run.mcap"
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
QUICK = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=2, duration=4.0)


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## From Python", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def _substitute(code: str, old: str, new: str) -> str:
    assert code.count(old) == 1, f"the README example no longer holds {old!r}"
    return code.replace(old, new)


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_the_readme_example_runs_the_loop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """identify -> tune -> save -> deploy from Python, as the README shows it."""
    code = _readme_example()
    code = _substitute(code, "TuneSettings(trials=200, seed=1)",
                       "TuneSettings(trials=2, seed=1, jobs=1, objective=QUICK)")
    code = _substitute(code, 'scenarios="table1", seed=1)',
                       'scenarios="sine-0.5hz", seed=1, duration=2.0)')
    code = _substitute(code, 'identify("data/run.mcap")', f"identify({str(RUN)!r})")
    monkeypatch.chdir(tmp_path)
    ns: dict[str, object] = {"QUICK": QUICK}
    exec(compile(code, "README.md", "exec"), ns)
    identified, tuned, run = ns["identified"], ns["tuned"], ns["run"]
    assert isinstance(identified, IdentifyResult) and isinstance(identified.model, ModelConfig)
    assert repr(identified).startswith("IdentifyResult(logs=['run.mcap'], mass=")
    # only tuned.save wrote files, into the folder it was given
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reports"]
    written = tmp_path / "reports" / "tune"
    assert load_controller(written / "controller.yaml") == tuned.controller
    assert (written / "report.md").is_file() and tuned.paths == {}
    assert "best=#" in repr(tuned) and "written=nothing" in repr(tuned)
    # a 2 s sine: the paper's gains give E_p 0.76 mm on the default sim rig over the same 2 s
    # (deploy data/controller-paper.yaml --duration 2); a controller that fails to track is
    # tens of mm off; 2 trials keep the tune near the paper's gains
    m = run["sine-0.5hz"].metrics
    assert m["status"] == "ok" and 0.0 < m["E_p_mm"] < 2.0, m
    assert run.exit_status == 0 and run.runs[0].log is None
    out = capsys.readouterr().out
    assert "E_p [mm]" in out and "sine-0.5hz" in out


def test_library_errors_name_the_argument() -> None:
    """The same check as the command; the message names the argument, the command's the
    flag."""
    with pytest.raises(ExperimentError) as info:
        identify(RUN, holdout=0.9)
    assert str(info.value) == "holdout must be in [0.05, 0.5], got 0.9"
    assert command_message(info.value) == "--holdout must be in [0.05, 0.5], got 0.9"
    with pytest.raises(ExperimentError, match=r"^seed must be >= 0"):
        deploy(PAPER_YAML, seed=-1)
    with pytest.raises(ExperimentError, match=r"^rig 'lab' is an unknown rig"):
        deploy(PAPER_YAML, rig="lab")


def test_deploy_writes_logs_only_when_asked(tmp_path: Path) -> None:
    """No log without ``log``; with it, the same metrics and a log that reads back."""
    config = load_controller(PAPER_YAML)
    quiet = deploy(config, scenarios="sine-0.5hz", duration=1.0)
    assert quiet.controller == "<controller>" and quiet.runs[0].log is None
    logged = deploy(PAPER_YAML, scenarios="sine-0.5hz", duration=1.0, log=tmp_path / "r.mcap")
    assert os.listdir(tmp_path) == ["r.mcap"]
    assert logged.runs[0].metrics["E_p_mm"] == quiet.runs[0].metrics["E_p_mm"]
    log = read_run_log(tmp_path / "r.mcap")
    assert log.run["controller"] == str(PAPER_YAML)
    assert math.isfinite(quiet.summary()["scenarios"]["sine-0.5hz"]["E_rms_mm"])
    assert isinstance(quiet.config, ControllerConfig)


@pytest.mark.slow  # over 20 s; `make test-slow` and CI run it
def test_identify_takes_a_log_already_read() -> None:
    """A RunLog gives the model its file gives (the fits see the same samples)."""
    log = read_run_log(RUN)
    from_log = identify(log, check=False)
    from_path = identify(RUN, check=False)
    assert from_log.model.theta == from_path.model.theta
    with pytest.raises(ExperimentError, match="given twice"):
        identify([log, RUN])
