"""What a log's run record says of the run: model.yaml's ``source.run``.

A closed-loop log (``deploy --log``, ``simulate --controller``) is one closed loop of the rig
itself: a known controller (the run record's ``controller`` and ``controller_sha256``) on a
known scenario (``scenario``), with its measured tracking error. tune replays that controller
on the model's nominal plant and compares (tune/logcheck.py); :func:`run_record` collects what
that needs while identify holds the log, so that model.yaml alone carries it:

* ``closed_loop``: the log has ``/control/state`` and ``/control/reference``;
* ``scenario``, ``controller``, ``controller_sha256``, ``homing_fault``: from the run record;
* ``controller_config``: the controller file's contract-4 content, when the file is found (as
  the run record names it, from the working directory, else beside the log), its sha256 is the
  run record's and it loads; otherwise ``controller_missing`` says why not;
* ``samples``, ``E_p_mm``, ``E_rms_mm``: the closed loop's samples and its indices over the last
  three reference periods (:func:`~pneutune.control.sim.closed_loop.compute_metrics` over
  :func:`~pneutune.control.sim.scenarios.metric_window`), for a known scenario whose homing move
  did not fault and a log at least that long.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.errors import PneutuneError
from pneutune.control.logs.reader import RunLog
from pneutune.control.sim.closed_loop import compute_metrics
from pneutune.control.sim.scenarios import SCENARIOS, metric_window

_SHA256 = re.compile(r"^[0-9a-f]{64}$")


def find_controller(name: str, log_path: str) -> Path | None:
    """The controller file a run record names: as named (from the working directory), else
    beside the log; None when neither is a file.

    Parameters
    ----------
    name : str
        The run record's ``controller``.
    log_path : str
        The log's path.

    Returns
    -------
    Path or None
    """
    cands = [Path(name)]
    if not Path(name).is_absolute():
        cands.append(Path(log_path).resolve().parent / name)
    return next((p for p in cands if p.is_file()), None)


def _controller(name: str, sha: str | None, log_path: str
                ) -> tuple[ControllerConfig | None, str | None]:
    """The controller that ran, unchanged since the run, or None and why not."""
    if not name:
        return None, "the run record names no controller"
    path = find_controller(name, log_path)
    if path is None:
        return None, f"the controller that ran (`{name}`) is not at that path nor beside the log"
    if sha is not None and sha256_file(path) != sha:
        return None, f"`{name}` has changed since the run (sha256)"
    try:
        return load_controller(path), None
    except (PneutuneError, OSError) as exc:
        return None, f"`{name}` does not load: {exc}"


def _measured(log: RunLog, scenario: str | None, cfg: ControllerConfig | None
              ) -> tuple[int, float | None, float | None]:
    """Closed-loop samples and the log's E_p, E_rms [mm] over the last three reference periods
    (None, None when the scenario is unknown or the log is shorter)."""
    ref = log.topics["/control/reference"].to_numpy(float)
    sensors = log.topics["/rig/sensors"].to_numpy(float)
    duties = log.topics["/rig/valves"].to_numpy(float)
    state = log.topics["/control/state"].to_numpy(float)
    n = min(len(ref), len(sensors), len(duties), len(state))
    sc = SCENARIOS.get(scenario or "")
    Ts = float(log.rig["Ts"])
    if sc is None or n < metric_window(sc.period, Ts):
        return n, None, None
    if cfg is not None:
        lo, hi = np.asarray(cfg.adaptation.theta_min), np.asarray(cfg.adaptation.theta_max)
    else:  # the bounds enter only the health checks, not E_p or E_rms
        lo, hi = np.full(6, -1.0e300), np.full(6, 1.0e300)
    m = compute_metrics(sc, Ts, ref[:n], sensors[:n], duties[:n], state[:n], lo, hi,
                        float(log.rig["x_min"]), float(log.rig["x_max"]), "ok")
    if not (math.isfinite(m.E_p_mm) and math.isfinite(m.E_rms_mm)):
        return n, None, None
    return n, m.E_p_mm, m.E_rms_mm


def run_record(log: RunLog) -> dict[str, Any]:
    """model.yaml's ``source.run`` of one log (module docstring).

    Parameters
    ----------
    log : RunLog
        The log as :func:`~pneutune.control.logs.reader.read_run_log` read it.

    Returns
    -------
    dict
        Plain data that validates as :class:`~pneutune.control.contracts.model.LoggedRun`:
        ``closed_loop``, ``homing_fault``, ``controller_config`` (as controller.yaml holds it)
        or ``controller_missing``, and ``scenario``, ``controller``, ``controller_sha256``,
        ``samples``, ``E_p_mm``, ``E_rms_mm`` where known.
    """
    run = log.run
    closed = log.has("/control/state") and log.has("/control/reference")
    homing_fault = run.get("homing") == "fault"
    scenario = run.get("scenario") or None
    name = run.get("controller", "")
    sha = run.get("controller_sha256") or None
    out: dict[str, Any] = {"closed_loop": closed, "scenario": scenario,
                           "controller": name or None}
    if sha is not None and not _SHA256.match(sha):
        cfg, missing = None, f"the run record's controller_sha256 {sha!r} is not a sha256"
        sha = None
    else:
        cfg, missing = _controller(name, sha, log.path)
    out["controller_sha256"] = sha
    if cfg is not None:
        out["controller_config"] = cfg.to_dict()
    else:
        out["controller_missing"] = missing
    out["homing_fault"] = homing_fault
    if closed:
        n, e_p, e_rms = _measured(log, None if homing_fault else scenario, cfg)
        out.update(samples=n, E_p_mm=e_p, E_rms_mm=e_rms)
    return {k: v for k, v in out.items() if v is not None}


__all__ = ["find_controller", "run_record"]
