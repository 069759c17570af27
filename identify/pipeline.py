"""From run logs to model.yaml: the steps of ``identify`` in order.

1. :func:`~pneutune.identify.dataset.load_datasets`: data checks, aligned arrays, one rig;
   :func:`~pneutune.identify.sources.pool_members` and
   :func:`~pneutune.identify.dataset.pool`: several logs side by side at the control instants,
   no fit window straddling two (with one log, the log itself).
2. :func:`~pneutune.identify.sources.valve_pool` and
   :class:`~pneutune.identify.valves.ValveIdentifier`: C, b per valve, leak, D_a, D_b, the PWM
   curves (QP), the valve timing, on the logs that test the valves.
3. :func:`~pneutune.identify.friction_choice.fit_friction`: Stribeck friction, F_n, the smooth
   model (:class:`~pneutune.identify.motion.FrictionIdentifier`, or the prior for a protocol
   run cut short); :func:`~pneutune.identify.mass_choice.choose_mass`: the mass and its
   interval (given, from the lag estimate, the integrated motion equation or the prior), then
   the friction refitted with it.
4. :func:`~pneutune.identify.bounds.theta_bounds`: θ nominal and bounds
   (:mod:`~pneutune.identify.friction_choice` for the friction's share,
   :class:`~pneutune.identify.sources.Sources` for the logs each basis rests on).
5. :func:`~pneutune.identify.model_build.build_plant`: the model as a simulated rig;
   :func:`~pneutune.identify.validation.validate`: that rig simulated on the held-out part.
6. :func:`~pneutune.identify.model_build.build_model`: model.yaml's document, its ranges and
   their bases.
7. :func:`~pneutune.identify.crosscheck.cross_check`: every range end (and the corners) that
   ``tune`` would sample must reproduce the held-out part nearly as well as the best fit; the
   ends the log rules out are moved in.

Everything is fitted on the first ``1 - holdout`` of every 10 s of each log; the rest of each
10 s is for validation (:meth:`~pneutune.identify.dataset.Dataset.split`, per log).

Several logs of one rig (docs/identification.md, "Several logs"): the valve, friction and
smooth-model fits, the validation and the cross-check run on the pooled control instants (each
log's rows in one regression); the mass's lag estimate pools the windows of the logs sampled
fast enough; the stiction bounds are read from each log at its own sampling period and the
tightest kept; the sensor noise is the smallest any log shows. Each basis names the logs it
came from. A protocol run cut short (:mod:`.coverage`) is used for what it holds: a fit that
cannot run on what the logs hold falls back to its prior range, and the notes say so
(:func:`~pneutune.identify.sources.coverage_notes`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from pneutune.control.constants import RIG_HINT_RANGES
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError, argument_error
from pneutune.control.logs.reader import RunLog
from pneutune.control.sim.scenarios import SCENARIOS

from .bounds import FrictionFit, ThetaBounds, theta_bounds
from .coverage import Coverage, coverage, lacks_mass_segments
from .crosscheck import CrossCheck, cross_check, narrowed_model
from .dataset import Dataset, Pool, display_names, load_datasets, pool, supply_note
from .friction_choice import (
    check_force_balance,
    fit_friction,
    friction_disagreements,
    low_speed_margin,
    prior_theta,
)
from .friction_prior import PriorFriction
from .mass import MIN_SAMPLES_PER_PWM, LagMassIdentifier, samples_per_pwm
from .mass_choice import choose_mass
from .model_build import build_model, build_plant
from .motion import FrictionIdentifier, MassIdentifier
from .sources import Sources, coverage_notes, pool_members, valve_pool
from .transmitters import check_transmitters
from .validation import Validation, validate
from .valves import ValveIdentifier


@dataclass(frozen=True, repr=False)
class IdentifyResult:
    """Everything ``identify`` learned, for model.yaml and the report.

    ``model`` is contract 3 (model.yaml); :meth:`save` writes it and the report. ``repr``
    shows the logs, θ's nominal and range, the held-out NRMSE and the number of notes.
    """

    data: Dataset
    valves: ValveIdentifier
    friction: FrictionIdentifier | PriorFriction
    mass: float
    mass_range: tuple[float, float]
    mass_basis: str
    mass_estimate: MassIdentifier | LagMassIdentifier | None
    theta: ThetaBounds
    validation: Validation
    model: ModelConfig
    plant: PlantConfig
    notes: tuple[str, ...] = ()
    #: the log at its own sampling period (``data`` holds the control instants the fits use)
    log: Dataset | None = None
    #: the cross-check of the ranges against the held-out log (None when skipped)
    crosscheck: CrossCheck | None = None
    #: every log at its own sampling period, in the order given (``log`` is the first)
    logs: tuple[Dataset, ...] = ()
    #: the logs as pooled into ``data`` (one log: the log itself)
    pool: Pool | None = None
    #: what each protocol run holds (None for a log without segment labels)
    coverage: tuple[Coverage | None, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        """Short names of the logs (:func:`~pneutune.identify.dataset.display_names`)."""
        return display_names([d.path for d in self.logs]) if self.logs else (self.data.path,)

    def __repr__(self) -> str:
        th = self.model.theta
        theta = ", ".join(f"{lo:.4g}<={nom:.4g}<={hi:.4g}" for lo, nom, hi in
                          zip(th.min, th.nominal, th.max, strict=True))
        fit = ", ".join(f"{k} {v:.3g}" for k, v in self.validation.nrmse.items())
        lo, hi = self.mass_range
        return (f"IdentifyResult(logs={list(self.names)}, mass={self.mass:.4g} kg in "
                f"[{lo:.4g}, {hi:.4g}], theta=[{theta}], held-out NRMSE: {fit}, "
                f"{len(self.notes)} notes)")

    def save(self, out: str | os.PathLike[str], report: bool = True,
             header: str | None = None) -> dict[str, str]:
        """Write ``out/model.yaml`` (contract 3, atomically) and, with ``report``,
        ``out/report.md`` with its figures.

        Parameters
        ----------
        out : path-like
            Output folder (made if missing).
        report : bool
            Write the report and its figures too.
        header : str, optional
            Comment lines at the top of model.yaml; default names the logs.

        Returns
        -------
        dict
            ``model`` and, with ``report``, ``report``: the paths written.
        """
        from pneutune.control.contracts.model import save_model

        from .report import write_report

        folder = Path(out)
        model_path = folder / "model.yaml"
        logs = " ".join(d.path for d in self.logs) if self.logs else self.data.path
        save_model(self.model, model_path, header=header or (
            f"pneutune identify {logs}\nsee report.md beside this file" if report else
            f"pneutune identify {logs}"))
        paths = {"model": str(model_path)}
        if report:
            paths["report"] = str(write_report(self, folder))
        return paths


def check_arguments(holdout: float, mass: float | None, mass_tol: float) -> None:
    """The rules for :func:`identify`'s arguments (the command's flags).

    Raises
    ------
    ExperimentError
        ``holdout`` outside [0.05, 0.5], ``mass`` outside the ``rig.mass`` hint's range
        (``RIG_HINT_RANGES``: 1 g to 1000 kg), ``mass_tol`` outside [0, 1).
    """
    m_lo, m_hi, _ = RIG_HINT_RANGES["mass"]
    if mass is not None and not m_lo <= mass <= m_hi:
        raise argument_error(ExperimentError, "mass",
                             f"must be in [{m_lo:g}, {m_hi:g}] kg, got {mass}")
    if not 0.0 <= mass_tol < 1.0:
        raise argument_error(ExperimentError, "mass_tol", f"must be in [0, 1), got {mass_tol}")
    if not 0.05 <= holdout <= 0.5:
        raise argument_error(ExperimentError, "holdout",
                             f"must be in [0.05, 0.5], got {holdout}")


def _scenario_notes(data: Dataset, name: str | None = None) -> list[str]:
    """What the run record's scenario (``deploy --log``) puts in the log that the model lacks.

    A scenario with timed external force steps (``disturbance-0.5hz``: 30 N from 7.6 s, 80 N
    from 9.8 s, off at 11.9 s) pushes the piston with forces no term of the model stands for:
    the fits lend them to F_n and friction. Measured with the paper's controller on the paper's
    rig: F_C -17 %, b_v +5 % and F_n 14.9 N (the truth 50 N, 3500 N s/m, 0 N), the ranges wide
    enough to hold the truth; on another simulator F_C +10 %, b_v -4 %.
    """
    scenario = SCENARIOS.get(data.scenario)
    steps = scenario.plant_updates.get("disturbance", {}).get("force_steps") if scenario else None
    if not steps:
        return []
    listed = ", ".join(f"{f:g} N from {t:g} s" for t, f in steps)
    which = "log" if name is None else f"log {name}"
    return [f"{which}: its run record names the scenario {scenario.name}, whose external "
            f"force steps ({listed}) the model has no term for: F_n and the friction fit "
            f"absorb them, and their ranges widen; identify a run without them (e.g. `deploy "
            f"--scenario sine-0.5hz --log`) for the model tune should use"]


#: One run log: its path, or the log as read by :func:`~pneutune.control.logs.reader.read_run_log`.
LogSource = str | os.PathLike[str] | RunLog
LogPaths = LogSource | Sequence[LogSource]


def log_paths(logs: LogPaths) -> list[LogSource]:
    """The run logs of :func:`identify`'s ``logs`` argument, as a list.

    Raises
    ------
    ExperimentError
        No log, or one log given twice (one file, as a path or read).
    """
    paths = [logs] if isinstance(logs, (str, os.PathLike, RunLog)) else list(logs)
    if not paths:
        raise ExperimentError("identify needs at least one run log")
    seen: dict[str, str] = {}
    for p in paths:
        name = p.path if isinstance(p, RunLog) else str(p)
        key = os.path.realpath(name)
        if key in seen:
            raise ExperimentError(f"{name}: given twice (as {seen[key]}); give each log once")
        seen[key] = name
    return paths


def identify(logs: LogPaths, holdout: float = 0.2, mass: float | None = None,
             mass_tol: float = 0.05, seed: int = 0, check: bool = True,
             out: str | os.PathLike[str] | None = None) -> IdentifyResult:
    """Identify the plant behind one run log, or one model behind several logs of one rig.

    What the ``identify`` command does, with the same checks; it writes files only when
    ``out`` is given (:meth:`IdentifyResult.save`)::

        from pneutune.identify import identify
        result = identify("data/run.mcap")
        result.model            # contract 3, as model.yaml holds it
        result.save("reports/identify")

    Parameters
    ----------
    logs : path-like or RunLog, or a sequence of them
        The MCAP run log (contract 1), as a path or as read by
        :func:`~pneutune.control.logs.reader.read_run_log`, or several logs of one rig (equal
        ``rig`` metadata; their sampling periods may differ): one model is fitted to all of
        them (docs/identification.md, "Several logs").
    holdout : float
        Fraction of every 10 s of each log kept for validation (its end), in [0.05, 0.5].
    mass : float, optional
        Known total moving mass [kg]; otherwise it is estimated (or the prior range is used).
    mass_tol : float
        Relative tolerance of a known mass, in [0, 1).
    seed : int
        Seed of the bootstraps.
    check : bool
        Cross-check every range end against the held-out logs and move in those they rule out
        (:mod:`~pneutune.identify.crosscheck`).
    out : path-like, optional
        Write model.yaml and report.md there (:meth:`IdentifyResult.save`); default: nothing
        is written.

    Returns
    -------
    IdentifyResult

    Raises
    ------
    LogError
        A bad log (typed, naming the file and what is wrong), logs of different rigs
        (:class:`~pneutune.identify.dataset.RigMismatchError`, naming both files and the key)
        or too little excitation.
    ExperimentError
        An argument out of range (:func:`check_arguments`), or a log given twice.
    """
    check_arguments(holdout, mass, mass_tol)
    paths = log_paths(logs)
    full = load_datasets(paths)
    names = display_names([d.path for d in full])
    several = len(full) > 1
    log = full[0]
    # valves, PWM curve, friction and validation work on the control instants; the mass on
    # every logged sample (an identification run logs 8 samples per control period)
    ctrl = [d.at_control_rate() for d in full]
    covs = tuple(coverage(d, n) for d, n in zip(full, names, strict=True))
    partial = any(c is not None and c.partial for c in covs)
    notes: list[str] = [c.summary() for c in covs if c is not None and c.partial]
    notes += [d.repairs + (f" in {n}" if several else "")
              for d, n in zip(full, names, strict=True) if d.repairs]
    for d, n in zip(ctrl, names, strict=True):
        notes += _scenario_notes(d, n if several else None)
        if (note := supply_note(d, n if several else None)) is not None:
            notes.append(note)
    members = pool_members(ctrl, names, notes)
    pl = pool([ctrl[j] for j in members], [names[j] for j in members])
    data = pl.data
    fit, held = pl.masks(holdout)
    # the valves on the pool of the logs that test them (with one log: that log)
    vpl = valve_pool(pl, fit, notes)
    vfit = vpl.masks(holdout)[0]
    valves = (ValveIdentifier(allow_unopened=True) if partial else ValveIdentifier()).fit(
        vpl.data, vfit, fast=full)
    notes += valves.notes_
    friction = fit_friction(data, fit, mass if mass is not None else 1.0, partial, notes)
    # the mass's lag estimate: every log sampled fast enough, but not a protocol run without the
    # segments that excite the mass (coverage.lacks_mass_segments)
    lag_logs = [j for j in range(len(full)) if not lacks_mass_segments(covs[j])]
    # logs fast enough for the lag estimate that lack those segments: what they need is the
    # segments, not faster sampling
    unexcited = [covs[j].experiment for j in range(len(full))
                 if j not in lag_logs and samples_per_pwm(full[j]) >= MIN_SAMPLES_PER_PWM]
    # transmitters that read upstream of a restriction lead the chambers: no mass estimate
    tx = check_transmitters(full)
    tx_note = None if tx is None else tx.note()
    if tx_note is not None:
        notes.append(tx_note)
    M, M_range, M_basis, M_est = choose_mass(
        data, friction, fit, mass, mass_tol, seed, notes, unexcited=unexcited,
        readings_lead=tx_note is not None,
        log=(log if not several else [full[j] for j in lag_logs]) if lag_logs else None,
        log_fit=(log.split(holdout)[0] if not several else
                 [full[j].split(holdout)[0] for j in lag_logs]) if lag_logs else None,
        names=[names[j] for j in lag_logs] if several else (), pooled=pl)
    if mass is None and not isinstance(friction, PriorFriction):
        # redo the (small) inertial term with the mass used
        friction = FrictionIdentifier(mass=M).fit(data, fit)
    if len(pl.spans) > 1 and not isinstance(friction, PriorFriction):
        notes += friction_disagreements(pl, fit, M)
    boot = friction.smooth_bootstrap(n_boot=300, block=50, seed=seed)
    if not isinstance(friction, PriorFriction):
        check_force_balance(", ".join(names), friction, boot)
    theta = theta_bounds(
        mass=M, mass_range=M_range, mass_basis=M_basis,
        friction=FrictionFit(smooth=friction.smooth_, smooth_boot=boot,
                             stribeck_b_v=friction.b_v_, F_C=friction.F_C_, F_S=friction.F_S_,
                             low_speed_margin=low_speed_margin(data, friction, notes),
                             stiction_resolved=friction.stiction_resolved_),
        D=valves.D_, D_std=valves.D_std_)
    if isinstance(friction, PriorFriction):
        theta = prior_theta(theta, friction)
    elif not friction.stiction_resolved_:
        notes.append("friction: the stiction peak is not resolved by the sliding samples "
                     f"(their fit: F_S {friction.F_S_:.3g} N, F_C {friction.F_C_:.3g} N, "
                     f"exponent {friction.alpha_:.3g}; model.yaml's F_S also weighs the stick "
                     "and break-away samples); the Stribeck velocity and exponent are weakly "
                     f"identified from the {data.Ts * 1e3:g} ms samples the friction fit uses, "
                     "and θ4 allows a stiction excess of half F_C")
    sources = Sources(pl, vpl, vfit, valves, friction) if several else None
    if sources is not None:
        theta = sources.theta(theta)
    notes += coverage_notes(covs, pl, valves, friction, M_est, M_basis, sources)
    period = 1.0 / data.rig.pwm_hz
    plant_cfg = build_plant(data, valves, friction, M)
    validation = validate(data, held, plant_cfg)
    model, ranges = build_model(data, full, valves, friction, M, M_range, M_basis, theta,
                                validation, notes, period, sources)
    cc = None
    if check:
        cc = cross_check(data, held, model, keys=ranges.unsupported)
        notes += cc.notes()
        model = narrowed_model(model, cc.box).model_copy(update={"notes": tuple(notes)})
        M_range = (model.theta.min[0], model.theta.max[0])
    result = IdentifyResult(data, valves, friction, M, M_range, M_basis, M_est, theta,
                            validation, model, plant_cfg, tuple(notes), log, cc, tuple(full), pl,
                            covs)
    if out is not None:
        result.save(out)
    return result

