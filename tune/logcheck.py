"""The model against its own log: does the model's nominal plant track like the rig did?

tune optimises on plants drawn from the model, so its controller is only as good as the model's
closed loop is like the rig's. When the model came from a closed-loop log (``deploy --log``), the
log holds one closed loop of the rig itself: a known controller on a known scenario, with its
measured tracking error. identify records what of it the check needs in model.yaml, each source
log's ``source.run`` (:class:`~pneutune.control.contracts.model.LoggedRun`): the scenario, the
contract-4 content of the controller that ran (when identify found its file unchanged since the
run), the closed loop's length in samples and the log's E_p and E_rms over its last three
reference periods. This module reads only those records, never the log or the controller file:
it replays that controller on the model's nominal plant over the same scenario and length, on
:data:`NOISE_SEEDS` sensor-noise seeds, and puts the model's E_p beside the log's. It also runs
the tuned controller there, so the report reads "model: logged controller a mm, tuned b mm; rig:
logged controller c mm".

Two warnings. When the rig tracked :data:`RATIO` times better or worse than every replay, the
model is pessimistic (optimistic) about this rig's closed loop, and the tuned controller's
advantage over the logged one is the model's, not yet the rig's. When the model does track like
the rig but the tuned controller does worse than the logged one on the nominal plant, the study
traded the plant the log shows for robustness over the model's ranges. On another simulator of
the same physics (``benchmarks/other_sim.py``, the paper's rig with LuGre friction) the paper's
gains gave 0.105 mm on the rig, 0.13-0.22 mm on the model's nominal plant, and the tuned
controller 0.20-0.25 mm there; on the rig it lost the sines (0.24 mm). Both warnings say to
deploy both controllers (docs/tuning.md, "The log's own closed loop").

Nothing is checked, and the report says why, when model.yaml has no ``source.run`` for the log
(run identify again to record it), the log is not a closed-loop run of a known scenario (an
identification or commissioning run, or a homing move a fault stopped), identify recorded no
controller for it (``controller_missing``: its file was not found, had changed since the run,
or did not load), or it is shorter than the indices' window.

A model fitted to several logs (model.yaml's ``source`` a list) is checked log by log
(:func:`check_logs`): each closed-loop source log is replayed, the others are listed as not
checked. The controller that ran (:func:`logged_controller`) is taken from the closed-loop
logs' records; when several ran different controllers, the later log's in ``source`` is taken
(the order identify was given the logs in; file dates are not looked at), and tune says so.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.model import ModelConfig, SourceInfo
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.model_box import nominal_plant
from pneutune.control.sim.scenarios import SCENARIOS, metric_window

#: The rig's E_p outside [min / RATIO, max x RATIO] of the replays' is a warning [-]. E_p is a
#: maximum over the window and moves by up to ±50 % with the noise seed alone (README), so a
#: factor 2 beyond every seed's is a model that does not track like the rig.
RATIO: float = 2.0
#: The tuned controller's mean E_p on the nominal plant above this times the logged one's is a
#: warning [-] (beyond the seed-to-seed spread of the mean of three).
TUNED_RATIO: float = 1.2
#: Sensor-noise seeds of the replays (offsets from tune's --seed).
NOISE_SEEDS: tuple[int, ...] = (0, 1, 2)


@dataclass(frozen=True)
class LogCheck:
    """The log's closed loop against the model's.

    Attributes
    ----------
    log : str
        The log checked (as model.yaml names it).
    skipped : str or None
        Why nothing was checked, or None.
    scenario, controller : str or None
        The logged scenario and controller file.
    measured : (float, float) or None
        The log's E_p and E_rms over its last three reference periods [mm].
    logged_on_model, tuned_on_model : tuple of (float, float)
        E_p and E_rms [mm] of the logged and of the tuned controller on the model's nominal
        plant, one per noise seed (nan for a run that stopped).
    """

    log: str
    skipped: str | None = None
    scenario: str | None = None
    controller: str | None = None
    measured: tuple[float, float] | None = None
    logged_on_model: tuple[tuple[float, float], ...] = ()
    tuned_on_model: tuple[tuple[float, float], ...] = ()

    def warnings(self) -> list[str]:
        """``warning:`` lines: the rig tracked :data:`RATIO` times better or worse than every
        replay (the model's fidelity); or the model does track like the rig and the tuned
        controller is :data:`TUNED_RATIO` times worse than the logged one on the nominal plant
        (mean E_p over the seeds)."""
        if self.measured is None or not self.logged_on_model:
            return []
        model = [e for e, _ in self.logged_on_model if math.isfinite(e)]
        tuned = [e for e, _ in self.tuned_on_model if math.isfinite(e)]
        if not model:
            return []
        rig, lo, hi = self.measured[0], min(model), max(model)
        where = f"on the log's own closed loop ({self.scenario}, `{self.controller}`)"
        if rig * RATIO < lo or rig > RATIO * hi:
            how, what = (("better", "pessimistic about this rig (more friction or stiction "
                          "than it has, slower valves)") if rig * RATIO < lo
                         else ("worse", "optimistic about this rig"))
            return [f"warning: {where} the rig tracked {how} than the model: E_p {rig:.3g} mm "
                    f"on the rig, {lo:.3g}-{hi:.3g} mm on the model's nominal plant; the "
                    f"model is {what}, so the tuned controller's advantage is the model's: "
                    "deploy both controllers on the rig and keep the better, or identify from "
                    "a richer log"]
        if not tuned or len(tuned) < len(model):
            return [f"warning: {where} the tuned controller stops on the model's nominal plant "
                    "in some replays: deploy the logged controller beside it"]
        t_mean, m_mean = float(np.mean(tuned)), float(np.mean(model))
        if t_mean > TUNED_RATIO * m_mean:
            return [f"warning: {where} the model tracks like the rig (E_p {rig:.3g} mm on the "
                    f"rig, {lo:.3g}-{hi:.3g} mm on the model), and there the tuned controller "
                    f"does worse than the logged one ({t_mean:.3g} against {m_mean:.3g} mm, "
                    "mean over the replays): the study traded this plant for robustness over "
                    "the model's ranges, which this rig may not need: deploy both controllers "
                    "and keep the better"]
        return []

    def lines(self) -> list[str]:
        """The report.md section."""
        out = ["## The log's own closed loop", ""]
        if self.skipped is not None:
            return [*out, f"Not checked: {self.skipped}.", ""]
        assert self.measured is not None

        def rng(vals: tuple[tuple[float, float], ...], i: int) -> str:
            v = [x[i] for x in vals]
            return f"{min(v):.3f}-{max(v):.3f}" if v else "-"

        out += [f"`{self.log}` is a closed loop of `{self.controller}` on `{self.scenario}`. "
                f"The same controller replayed on the model's nominal plant over the same "
                f"length, noise seeds +{', +'.join(str(s) for s in NOISE_SEEDS)} "
                "(docs/tuning.md):", "",
                "| | E_p [mm] | E_rms [mm] |", "|---|---|---|",
                f"| the rig (the log) | {self.measured[0]:.3f} | {self.measured[1]:.3f} |",
                f"| logged controller, model | {rng(self.logged_on_model, 0)} | "
                f"{rng(self.logged_on_model, 1)} |",
                f"| tuned controller, model | {rng(self.tuned_on_model, 0)} | "
                f"{rng(self.tuned_on_model, 1)} |", ""]
        warn = self.warnings()
        return [*out, *([f"**{w}**" for w in warn] or [
            f"The rig tracked like the model (within a factor {RATIO:g} of the replays), and "
            "the tuned controller does at least as well there as the logged one."]), ""]

    def as_dict(self) -> dict[str, object]:
        """Plain data for ``tune --json``."""
        return {"log": self.log, "skipped": self.skipped, "scenario": self.scenario,
                "controller": self.controller, "measured": self.measured,
                "logged_on_model": self.logged_on_model, "tuned_on_model": self.tuned_on_model,
                "warnings": self.warnings()}


class LogChecks(tuple[LogCheck, ...]):
    """The check of every log a model came from (:func:`check_logs`), one :class:`LogCheck`
    each. With one log it reads exactly as that log's check."""

    def warnings(self) -> list[str]:
        """Every log's ``warning:`` lines."""
        return [w for c in self for w in c.warnings()]

    def lines(self) -> list[str]:
        """The report.md section: the one log's, or a subsection per log."""
        if len(self) == 1:
            return self[0].lines()
        out = ["## The logs' own closed loops", "",
               f"The model came from {len(self)} logs; each closed-loop one is replayed on "
               "the model's nominal plant.", ""]
        for c in self:
            body = c.lines()[2:]  # without the one-log heading
            out += [f"### `{c.log}`", "", *body]
        return out

    def as_dict(self) -> dict[str, object]:
        """Plain data for ``tune --json``: the one log's, or ``{"logs": [...], "warnings":
        [...]}``."""
        if len(self) == 1:
            return self[0].as_dict()
        return {"logs": [c.as_dict() for c in self], "warnings": self.warnings()}


#: Why nothing is checked for a source log without ``source.run``.
NO_RECORD = ("model.yaml has no record of this log's run (`source.run`): run identify again on "
             "the log to record it")


def _record_controller(src: SourceInfo) -> tuple[ControllerConfig | None, str]:
    """The controller that ran in one source log, as identify recorded it, or None and why
    not."""
    run = src.run
    if run is None:
        return None, NO_RECORD
    if not run.closed_loop:
        return None, "not a closed-loop run"
    if run.controller_config is None:
        return None, f"identify recorded no controller: {run.controller_missing}"
    return run.controller_config, run.controller or ""


def logged_controller(model: ModelConfig, model_path: str | None = None,
                      notes: Callable[[str], None] | None = None,
                      ) -> tuple[ControllerConfig | None, str]:
    """The controller that ran in ``model``'s log (a closed-loop run that ``deploy --log``
    wrote), as identify recorded it in ``source.run``; ``(None, why not)`` otherwise.

    ``tune`` enqueues its parameters as a trial, so that a re-tune after a re-identification
    starts from the controller on the rig. For a model fitted to several logs, every source's
    record is looked at: the controller comes from the closed-loop ones, and when they ran
    different controllers, from the later of them in ``source`` (file dates are not looked
    at), which ``notes`` (default: stderr) is told. Neither the logs nor the controller files
    are opened.

    Parameters
    ----------
    model : ModelConfig
        The identified model (its ``source`` holds the records).
    model_path : str, optional
        Where model.yaml was read from; not needed, as the records are in ``model``.
    notes : callable, optional
        Receives the line saying which of several different logged controllers was taken
        (default: written to stderr).

    Returns
    -------
    (ControllerConfig or None, str)
        The controller and its file name as the run record names it, or None and the reason.
    """
    del model_path  # the records are in model.yaml
    sources = model.sources
    if len(sources) == 1:
        return _record_controller(sources[0])
    found: list[tuple[ControllerConfig, str, str]] = []
    why: list[str] = []
    for src in sources:
        cfg, what = _record_controller(src)
        if cfg is None:
            why.append(f"`{src.log}`: {what}")
        else:
            found.append((cfg, what, src.log))
    if not found:
        return None, "; ".join(why)
    cfg, ctrl_name, log_name = found[-1]
    if any(f[0] != cfg for f in found):
        ran = ", ".join(f"`{f[1]}` in `{f[2]}`" for f in found)
        line = (f"the model's closed-loop logs ran different controllers ({ran}); the later "
                f"log's in model.yaml's source, `{ctrl_name}` in `{log_name}`, is the logged "
                "controller")
        if notes is not None:
            notes(line)
        else:
            sys.stderr.write(line + "\n")
    return cfg, ctrl_name


def check_logs(model: ModelConfig, tuned: ControllerConfig, seed: int,
               model_path: str | None = None) -> LogChecks:
    """:func:`check_log` for every log ``model`` came from (one for a single-log model).

    Parameters
    ----------
    model : ModelConfig
        The identified model (its ``source`` holds the records).
    tuned : ControllerConfig
        The tuned controller, replayed beside each logged one.
    seed : int
        tune's seed.
    model_path : str, optional
        Where model.yaml was read from; not needed, as the records are in ``model``.

    Returns
    -------
    LogChecks
    """
    return LogChecks(check_log(model, tuned, seed, model_path, source=src)
                     for src in model.sources)


def check_log(model: ModelConfig, tuned: ControllerConfig, seed: int,
              model_path: str | None = None, source: SourceInfo | None = None) -> LogCheck:
    """Replay the controller of ``model``'s log on its nominal plant (module docstring).

    Only ``source.run`` is read: the log and the controller file are not opened.

    Parameters
    ----------
    model : ModelConfig
        The identified model (its ``source`` holds the log's record).
    tuned : ControllerConfig
        The tuned controller, replayed beside the logged one.
    seed : int
        tune's seed; the replays use noise seeds ``seed + NOISE_SEEDS``.
    model_path : str, optional
        Where model.yaml was read from; not needed, as the record is in ``model``.
    source : SourceInfo, optional
        The log to check: one of ``model.sources``; default the model's only log
        (:func:`check_logs` checks each of several).

    Returns
    -------
    LogCheck

    Raises
    ------
    ValueError
        ``source`` not given for a model of several logs.
    """
    del model_path  # the record is in model.yaml
    if source is None:
        if len(model.sources) != 1:
            raise ValueError(f"the model came from {len(model.sources)} logs: name the one "
                             f"to check (source=...), or use check_logs")
        source = model.sources[0]
    name, run = source.log, source.run
    if run is None:
        return LogCheck(name, NO_RECORD)
    if not run.closed_loop:
        return LogCheck(name, "it is not a closed-loop run (no /control/state): an "
                        "identification or commissioning run")
    if run.homing_fault:
        return LogCheck(name, "it holds only a homing move that a fault stopped before the "
                        "scenario (run record `homing: fault`)")
    scenario = SCENARIOS.get(run.scenario or "")
    if scenario is None:
        return LogCheck(name, f"its run record names no scenario this version knows "
                        f"({run.scenario or 'none'!r}; `deploy --log` writes one), "
                        "so there is no reference to replay")
    ctrl_name = run.controller or ""
    logged = run.controller_config
    if logged is None:
        return LogCheck(name, f"identify recorded no controller for it: "
                        f"{run.controller_missing}", scenario.name, ctrl_name or None)
    Ts = model.rig.Ts
    if not math.isclose(Ts, logged.rig.Ts):
        return LogCheck(name, f"its Ts {Ts:g} s is not the controller's ({logged.rig.Ts:g} s)",
                        scenario.name, ctrl_name)
    n = run.samples or 0
    if run.E_p_mm is None or run.E_rms_mm is None or n < metric_window(scenario.period, Ts):
        return LogCheck(name, f"it is shorter ({n * Ts:.3g} s) than the three reference periods "
                        "of the indices", scenario.name, ctrl_name)
    run_sc = dataclasses.replace(scenario, duration=n * Ts)

    def replay(ctrl: ControllerConfig) -> tuple[tuple[float, float], ...]:
        out = []
        for k in NOISE_SEEDS:
            m = simulate_scenario(ctrl, run_sc, nominal_plant(model, seed=seed + k)).metrics
            ok = m.status == "ok"
            out.append((m.E_p_mm if ok else math.nan, m.E_rms_mm if ok else math.nan))
        return tuple(out)

    return LogCheck(name, None, scenario.name, ctrl_name,
                    (run.E_p_mm, run.E_rms_mm), replay(logged), replay(tuned))


__all__ = ["NOISE_SEEDS", "NO_RECORD", "RATIO", "TUNED_RATIO", "LogCheck", "LogChecks",
           "check_log", "check_logs", "logged_controller"]
