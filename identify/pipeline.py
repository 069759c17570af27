"""From run logs to model.yaml: the steps of ``identify`` in order.

1. :func:`~pneutune.identify.dataset.load_datasets`: data checks, aligned arrays, one rig;
   :func:`~pneutune.identify.dataset.pool`: several logs side by side at the control instants,
   no fit window straddling two (with one log, the log itself).
2. :class:`~pneutune.identify.valves.ValveIdentifier`: C, b per valve, leak, D_a, D_b, the PWM
   curves (QP).
3. :class:`~pneutune.identify.motion.FrictionIdentifier`: Stribeck friction, F_n, the smooth
   model; :class:`~pneutune.identify.motion.MassIdentifier`: the mass and its interval.
4. :func:`~pneutune.identify.bounds.theta_bounds`: θ nominal and bounds.
5. :func:`~pneutune.identify.validation.validate`: the model simulated on the held-out part.
6. :func:`~pneutune.identify.crosscheck.cross_check`: every range end (and the corners) that
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
cannot run on what the logs hold falls back to its prior range, and the notes say so.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.constants import MODEL_SCHEMA, VALVES, WEAK_B_SPAN
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError, LogError, argument_error
from pneutune.control.logs.reader import RunLog
from pneutune.control.sim.scenarios import SCENARIOS

from .bounds import FrictionFit, ThetaBounds, theta_bounds
from .coverage import Coverage, coverage, lacks_mass_segments
from .crosscheck import CrossCheck, cross_check, narrowed_model
from .dataset import Dataset, IdentificationError, Pool, display_names, load_datasets, pool
from .friction_prior import PriorFriction
from .mass import MIN_SAMPLES_PER_PWM, LagMassIdentifier, samples_per_pwm
from .mass_prior import mass_prior
from .motion import V_SLIDE, FrictionIdentifier, MassIdentifier
from .stiction import StictionBounds, force_noise_std, position_noise_std, stiction_bounds
from .validation import Validation, validate
from .valves import LOOP_DELAY_TOLERANCE, ValveIdentifier, _longest_run

#: An interval wider than this ratio (hi / lo) means "not identifiable".
MASS_IDENTIFIABLE_RATIO = 1.5


#: Structural half-width added to the integrated mass estimate's bootstrap interval, as a
#: multiple of b_v Ts [kg]. The estimate runs high by 2-15 %, growing with b_v Ts / M, which the
#: bootstrap does not see. Calibrated on five simulated rigs (200 mm stroke, 50 mm bore, b_v
#: 200-800 N s/m, M 1-4 kg): bias +4 % to +15 %, and 0.15 b_v Ts covers each with room
#: (docs/identification.md).
MASS_BIAS_MARGIN = 0.15


def mass_sampling_limit(b_v: float, Ts: float) -> float:
    """Smallest mass whose mechanical pole b_v/M lies below the Nyquist frequency π/Ts [kg].

    Parameters
    ----------
    b_v : float
        Viscous coefficient [N s/m].
    Ts : float
        Sampling period [s].

    Returns
    -------
    float
        ``b_v Ts / π`` [kg].

    Below it the piston follows the force within one sample and the mass shows only as a lag
    M/b_v shorter than Ts/π. The integrated motion equation then carries a structural bias
    (the force path inside each sample is unknown) that its bootstrap does not see: on a
    noise-free identification run of the default plant (M = 1.05 kg) with 10 s of extra
    position steps it returned [1.84, 2.10] kg. Such an interval is not reported
    (docs/identifiability.md).
    """
    return b_v * Ts / np.pi


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


def _lag_mass(log: Dataset | Sequence[Dataset], friction: FrictionIdentifier,
              fit: np.ndarray | Sequence[np.ndarray], seed: int,
              notes: list[str]) -> LagMassIdentifier | None:
    """The lag estimate of the mass when its interval is narrow enough, else None (noted)."""
    try:
        est = LagMassIdentifier(friction, seed=seed).fit(log, fit)
    except (LogError, ValueError, np.linalg.LinAlgError) as exc:
        notes.append(f"mass: the lag of the motion behind the pressure force gives no estimate "
                     f"({exc})")
        return None
    lo, hi = est.ci_
    if lo > 0.0 and hi / lo <= MASS_IDENTIFIABLE_RATIO:
        return est
    notes.append(f"mass: the lag of the motion behind the pressure force gives {est.M_:.3g} kg "
                 f"in [{lo:.3g}, {hi:.3g}] kg, wider than a factor {MASS_IDENTIFIABLE_RATIO:g} "
                 f"(on every other sample: {est.M_half_:.3g} kg)")
    return None


def _mass(data: Dataset, friction: FrictionIdentifier | PriorFriction, fit: np.ndarray,
          mass: float | None, mass_tol: float, seed: int, notes: list[str],
          log: Dataset | Sequence[Dataset] | None = None,
          log_fit: np.ndarray | Sequence[np.ndarray] | None = None,
          names: Sequence[str] = (), pooled: Pool | None = None,
          ) -> tuple[float, tuple[float, float], str, MassIdentifier | LagMassIdentifier | None]:
    """The mass, its range, their basis and the estimator (None for a given or prior mass).

    ``log``: the log, or the logs, at their own sampling period that the lag estimate may use
    (``log_fit`` their fit masks, ``names`` their short names, for the basis of several);
    ``pooled``: the pool behind ``data``, to name the logs of the integrated estimate.
    """
    if mass is not None:
        rng = (mass * (1.0 - mass_tol), mass * (1.0 + mass_tol))
        return mass, rng, f"given by the user (±{mass_tol:.0%})", None
    prior, prior_nominal, prior_basis = mass_prior(data.rig, data.mass_hint)
    if isinstance(friction, PriorFriction):
        notes.append(f"mass: not estimated (the friction fit, which its estimates need, could "
                     f"not run); {prior_basis}: [{prior[0]:.3g}, {prior[1]:.3g}] kg, narrowed "
                     f"by the cross-check")
        return prior_nominal, prior, prior_basis, None
    logs = [] if log is None else [log] if isinstance(log, Dataset) else list(log)
    fits = ([] if log_fit is None else [log_fit] if isinstance(log, Dataset)
            else list(log_fit))
    fast = [j for j, d in enumerate(logs) if samples_per_pwm(d) >= MIN_SAMPLES_PER_PWM]
    if fast:
        one = len(logs) == 1
        lag = _lag_mass(logs[0] if one else [logs[j] for j in fast], friction,
                        fits[0] if one else [fits[j] for j in fast], seed, notes)
        if lag is not None:
            periods = "/".join(f"{h * 1e3:g}" for h in sorted({logs[j].Ts for j in fast}))
            where = (f"{periods} ms samples" if len(names) <= 1 else
                     f"{periods} ms samples of {', '.join(names[j] for j in fast)}")
            notes.append(
                f"mass: {lag.M_:.3g} kg from the lag of the measured position behind the "
                f"measured pressure force, which holds the sensors' lags too: each ms the "
                f"position sensor lags more than the pressure transmitters adds "
                f"{friction.b_v_ * 1e-3:.2g} kg (b_v times the lag), each ms less takes it "
                f"off; where the sensors' datasheets say they differ, give --mass KG")
            return lag.M_, lag.ci_, (
                f"99 % bootstrap interval of tau b_v, tau the lag of the motion behind the "
                f"pressure force ({where}), widened by "
                f"{lag.discretisation_:.3g} kg, the change on every other sample"), lag
    try:
        est = MassIdentifier(friction, seed=seed).fit(data, fit)
    except (LogError, ValueError, np.linalg.LinAlgError) as exc:
        notes.append(f"mass: not estimated ({exc}); {prior_basis}: [{prior[0]:.3g}, "
                     f"{prior[1]:.3g}] kg, narrowed by the cross-check")
        return prior_nominal, prior, prior_basis, None
    margin = MASS_BIAS_MARGIN * friction.b_v_ * data.Ts
    lo, hi = max(est.ci_[0] - margin, 0.0), est.ci_[1] + margin
    limit = mass_sampling_limit(friction.b_v_, data.Ts)
    if lo > limit and hi / lo <= MASS_IDENTIFIABLE_RATIO:
        both = (max(lo, prior[0]), min(hi, prior[1]))
        basis = ("99 % bootstrap interval of the integrated motion equation, widened by "
                 f"{margin:.3g} kg for its bias (0.15 b_v Ts)")
        if pooled is not None and len(pooled.names) > 1:
            basis += _from(pooled.names_where(fit & (np.abs(data.v) > V_SLIDE)))
        if both[0] < both[1]:
            if both != (lo, hi):
                basis += f", intersected with the {prior_basis}"
            return float(np.clip(est.M_, *both)), both, basis, est
        notes.append(f"mass: the estimate's interval [{lo:.3g}, {hi:.3g}] kg lies outside the "
                     f"{prior_basis} [{prior[0]:.3g}, {prior[1]:.3g}] kg; the data win")
        return est.M_, (lo, hi), basis, est
    if fast:
        # the log is sampled fast enough for the lag estimate, which failed (its note says why)
        why = ("At this sampling the mass comes from the lag of the motion behind the pressure "
               "force, which gave no usable estimate (see its note); the integrated motion "
               "equation cannot replace it.")
    elif lo <= limit:
        why = (f"With a viscous coefficient of {friction.b_v_:.0f} N s/m the mechanical pole "
               f"b_v/M lies above the Nyquist frequency of the {data.Ts * 1e3:g} ms sampling "
               f"for any mass below {limit:.3g} kg, where this estimate is biased "
               f"(docs/identifiability.md); an identification run logged every 0.5 ms "
               f"resolves the mass (record --sample-period 0.0005).")
    else:
        why = f"It is wider than a factor {MASS_IDENTIFIABLE_RATIO:g}."
    interval = (f"is [{lo:.3g}, {hi:.3g}] kg" if hi > lo else
                f"lies below zero (its upper end is {hi:.3g} kg): the accelerations do not "
                f"follow the pressure force as the model has it (a lag between them, such as "
                f"a pressure transmitter's, or dynamics the model lacks)")
    notes.append(
        f"mass: not identifiable from this log: the 99 % interval of the estimate "
        f"{interval}. {why} θ1 uses the {prior_basis}: [{prior[0]:.3g}, "
        f"{prior[1]:.3g}] kg (nominal {prior_nominal:.3g} kg), narrowed by the cross-check "
        f"where the log contradicts its ends; give --mass KG (datasheet plus weighed payload) "
        f"or a rig.mass hint in the log to narrow it")
    return prior_nominal, prior, prior_basis, est


def check_arguments(holdout: float, mass: float | None, mass_tol: float) -> None:
    """The rules for :func:`identify`'s arguments (the command's flags).

    Raises
    ------
    ExperimentError
        ``holdout`` outside [0.05, 0.5], ``mass`` outside (0, 1000] kg, ``mass_tol`` outside
        [0, 1).
    """
    if mass is not None and not 0.0 < mass <= 1000.0:
        raise argument_error(ExperimentError, "mass", f"must be in (0, 1000] kg, got {mass}")
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
    for d, n in zip(ctrl, names, strict=True):
        notes += _scenario_notes(d, n if several else None)
    members = _pool_members(ctrl, names, notes)
    pl = pool([ctrl[j] for j in members], [names[j] for j in members])
    data = pl.data
    fit, held = pl.masks(holdout)
    # the valves on the pool of the logs that test them (with one log: that log)
    vpl = _valve_pool(pl, fit, notes)
    vfit = vpl.masks(holdout)[0]
    valves = (ValveIdentifier(allow_unopened=True) if partial else ValveIdentifier()).fit(
        vpl.data, vfit, fast=full)
    notes += valves.notes_
    friction = _friction(data, fit, mass if mass is not None else 1.0, partial, notes)
    # the mass's lag estimate: every log sampled fast enough, but not a protocol run without the
    # segments that excite the mass (coverage.lacks_mass_segments)
    lag_logs = [j for j in range(len(full)) if not lacks_mass_segments(covs[j])]
    M, M_range, M_basis, M_est = _mass(
        data, friction, fit, mass, mass_tol, seed, notes,
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
    theta = theta_bounds(
        mass=M, mass_range=M_range, mass_basis=M_basis,
        friction=FrictionFit(smooth=friction.smooth_, smooth_boot=boot,
                             stribeck_b_v=friction.b_v_, F_C=friction.F_C_, F_S=friction.F_S_,
                             low_speed_margin=_low_speed_margin(data, friction, notes),
                             stiction_resolved=friction.stiction_resolved_),
        D=valves.D_, D_std=valves.D_std_)
    if isinstance(friction, PriorFriction):
        theta = _prior_theta(theta, friction)
    elif not friction.stiction_resolved_:
        notes.append("friction: the stiction peak is not resolved by the sliding samples "
                     f"(F_S {friction.F_S_:.3g} N, F_C {friction.F_C_:.3g} N, exponent "
                     f"{friction.alpha_:.3g}); the Stribeck velocity and exponent are weakly "
                     f"identified from the {data.Ts * 1e3:g} ms samples the friction fit uses, "
                     "and θ4 allows a stiction excess of half F_C")
    sources = _Sources(pl, vpl, vfit, valves, friction) if several else None
    if sources is not None:
        theta = sources.theta(theta)
    notes += _coverage_notes(covs, pl, valves, friction, M_est, M_basis, sources)
    period = 1.0 / data.rig.pwm_hz
    plant_cfg = _plant(data, valves, friction, M)
    validation = validate(data, held, plant_cfg)
    model, ranges = _model(data, full, valves, friction, M, M_range, M_basis, theta,
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


def _pool_members(ctrl: Sequence[Dataset], names: Sequence[str], notes: list[str]) -> list[int]:
    """The logs the pooled fits use: those at the control instants (``rig.Ts``); if none is,
    those at the sampling period with the most data. A log left out is noted."""
    if len(ctrl) == 1:
        return [0]
    rig_Ts = ctrl[0].rig.Ts
    at = [j for j, d in enumerate(ctrl) if np.isclose(d.Ts, rig_Ts, rtol=1e-9)]
    if not at:
        totals: dict[float, float] = {}
        for d in ctrl:
            totals[d.Ts] = totals.get(d.Ts, 0.0) + d.duration
        best = max(totals, key=lambda h: totals[h])
        at = [j for j, d in enumerate(ctrl) if d.Ts == best]
    for j, d in enumerate(ctrl):
        if j not in at:
            notes.append(
                f"log {names[j]}: sampled every {d.Ts * 1e3:g} ms with duties that change "
                f"inside a {rig_Ts * 1e3:g} ms control period, so it cannot be cut to the "
                f"control instants of the others; the valve, friction and validation fits "
                f"leave it out (its samples still enter the mass, stiction and noise "
                f"estimates)")
    return at


def _valve_pool(pl: Pool, fit: np.ndarray, notes: list[str]) -> Pool:
    """The logs the valve fit uses, pooled: the logs that test the valves, and the others only
    where they hold the one record of a valve those do not test.

    A valve is tested by a log that holds it at full duty for :data:`FULL_OPEN_PIN_S` at a
    stretch (a whole charge or vent): that pins its C and b (within 0.1 % and 1 % on
    data/run.mcap). Partial openings under a closed loop give C within 4 % at best
    (docs/identification.md), and pooled with the tests they only pull C and b off them: on
    data/run.mcap with a 12 s closed loop of the same plant, b of a_out moved from +0.63 % to
    +0.81 %. With one log, or no log that tests a valve, every log is used.
    """
    if len(pl.spans) == 1:
        return pl
    u = pl.data.u
    pins = []
    for a, b in pl.spans:
        f = fit[a:b]
        pins.append({i for i in range(4)
                     if _longest_run(f & (u[a:b, i] >= 0.999)) * pl.data.Ts >= FULL_OPEN_PIN_S})
    tested = set().union(*pins)
    if not tested:
        return pl
    use = []
    for (a, b), pinned in zip(pl.spans, pins, strict=True):
        opens = {i for i in range(4) if np.any(fit[a:b] & (u[a:b, i] > 0.0))}
        use.append(bool(pinned) or bool(opens - tested))
    left = [n for n, keep in zip(pl.names, use, strict=True) if not keep]
    if left:
        by = ", ".join(n for n, keep in zip(pl.names, use, strict=True) if keep)
        notes.append(f"valves: C, b, the PWM curves, the valve timing and D_a, D_b from {by}, "
                     f"whose valve tests hold every valve the logs open fully open for "
                     f"{FULL_OPEN_PIN_S:g} s or more; the partial openings of "
                     f"{', '.join(left)} are left out of that fit")
        keep = [j for j, k in enumerate(use) if k]
        return pool([pl.parts[j] for j in keep], [pl.names[j] for j in keep])
    return pl


def _friction(data: Dataset, fit: np.ndarray, mass: float, partial: bool,
              notes: list[str]) -> FrictionIdentifier | PriorFriction:
    """The friction fit; for a protocol run cut short on which it cannot run, the prior
    (:mod:`.friction_prior`), noted. Any other log that cannot support it is bad input."""
    try:
        return FrictionIdentifier(mass=mass).fit(data, fit)
    except IdentificationError as exc:
        if not partial:
            raise
        prior = PriorFriction(data.rig, data.n, exc.message)
        notes.append(f"friction: not identifiable from these logs ({exc.message}); F_C in "
                     f"[{prior.F_C_range_[0]:.3g}, {prior.F_C_range_[1]:.3g}] N, b_v in "
                     f"[{prior.b_v_range_[0]:.3g}, {prior.b_v_range_[1]:.3g}] N s/m and F_n in "
                     f"[{prior.F_n_range_[0]:.3g}, {prior.F_n_range_[1]:.3g}] N are a prior "
                     f"from the rig's geometry and supply; the cross-check narrows b_v and F_n "
                     f"where the log rules their ends out")
        return prior


#: Two logs disagree on a friction coefficient when their estimates lie this many combined
#: standard errors apart ...
DISAGREE_SIGMAS = 5.0
#: ... and differ by this fraction of the smaller one.
DISAGREE_FRACTION = 0.05


def friction_disagreements(pl: Pool, fit: np.ndarray, mass: float) -> list[str]:
    """Notes for pooled logs whose own friction fits disagree (the rig changed between them).

    Each pooled log that supports a friction fit of its own is fitted alone; two logs whose
    F_C or b_v lie more than :data:`DISAGREE_SIGMAS` combined standard errors and
    :data:`DISAGREE_FRACTION` apart show two states of the rig (a seal change, a new load),
    which the pooled fit blends.

    Parameters
    ----------
    pl : Pool
        The pooled logs.
    fit : ndarray of bool
        The pooled fit mask.
    mass : float
        The moving mass of the fits' inertial term [kg].

    Returns
    -------
    list of str
        One note per coefficient on which some pair disagrees (empty when they agree).
    """
    own: list[tuple[str, FrictionIdentifier]] = []
    for name, (a, b) in zip(pl.names, pl.spans, strict=True):
        mask = np.zeros_like(fit)
        mask[a:b] = fit[a:b]
        try:
            own.append((name, FrictionIdentifier(mass=mass).fit(pl.data, mask)))
        except IdentificationError:
            continue  # too little motion in this log for a fit of its own
    notes = []
    for key, unit, attr in (("F_C", "N", "F_C_"), ("b_v", "N s/m", "b_v_")):
        worst = None
        for i in range(len(own)):
            for j in range(i + 1, len(own)):
                (na, fa), (nb, fb) = own[i], own[j]
                va, vb = getattr(fa, attr), getattr(fb, attr)
                sd = math.hypot(fa.std_[key], fb.std_[key])
                gap = abs(va - vb)
                if gap > DISAGREE_SIGMAS * sd and gap > DISAGREE_FRACTION * min(abs(va), abs(vb)):
                    z = gap / sd if sd > 0 else math.inf
                    if worst is None or z > worst[0]:
                        worst = (z, na, va, nb, vb)
        if worst is not None:
            z, na, va, nb, vb = worst
            notes.append(f"friction: the logs disagree on {key}: {va:.4g} {unit} from {na}, "
                         f"{vb:.4g} {unit} from {nb} ({z:.0f} standard errors apart): the rig "
                         f"changed between them (a seal, a load, the supply?), and the model "
                         f"blends the two; identify the logs of the rig as it is now")
    return notes


def _prior_theta(theta: ThetaBounds, prior: PriorFriction) -> ThetaBounds:
    """θ2..θ4 from the friction prior (F_n, b_v, and A_f over the Coulomb range up to the
    stiction prior)."""
    lo, hi = theta.lo.copy(), theta.hi.copy()
    lo[1], hi[1] = prior.F_n_range_
    lo[2], hi[2] = prior.b_v_range_
    lo[3], hi[3] = prior.F_C_range_[0], STICTION_PRIOR_MAX * prior.F_C_range_[1]
    basis = list(theta.basis)
    basis[1] = basis[2] = basis[3] = prior.basis_
    return dataclasses.replace(theta, lo=lo, hi=hi, basis=tuple(basis))


def _from(names: Sequence[str]) -> str:
    """`` (from a.mcap, b.mcap)`` for a basis, or "" when no log is named."""
    return f" (from {', '.join(names)})" if names else ""


class _Sources:
    """Which of several pooled logs each fit drew on, for the bases (one log: not used)."""

    def __init__(self, pl: Pool, vpl: Pool, vfit: np.ndarray, valves: ValveIdentifier,
                 friction: FrictionIdentifier | PriorFriction) -> None:
        self.pool = pl
        self.valve = [vpl.names_where(vfit & (vpl.data.u[:, i] > 0.0)) for i in range(4)]
        self.friction = ("" if isinstance(friction, PriorFriction)
                         else _from(pl.names_where(friction.sliding_)))
        self.chamber = []
        for ch in range(2):
            if valves.D_closed_[ch]:
                shut = vfit & np.all(vpl.data.u[:, 2 * ch:2 * ch + 2] <= 0.0, axis=1)
                used = tuple(n for n, (a, b) in zip(vpl.names, vpl.spans, strict=True)
                             if _longest_run(shut[a:b]) > valves.window_)
            else:
                used = vpl.names_where(vfit)
            self.chamber.append(_from(used))

    def theta(self, theta: ThetaBounds) -> ThetaBounds:
        """θ's bases with the logs behind θ2..θ6 (θ1's, the mass basis, names its own)."""
        b = list(theta.basis)
        for i in (1, 2, 3):
            b[i] += self.friction
        b[4] += self.chamber[0]
        b[5] += self.chamber[1]
        return dataclasses.replace(theta, basis=tuple(b))


def _coverage_notes(covs: Sequence[Coverage | None], pl: Pool,
                    valves: ValveIdentifier, friction: FrictionIdentifier | PriorFriction,
                    M_est: MassIdentifier | LagMassIdentifier | None, M_basis: str,
                    sources: _Sources | None) -> list[str]:
    """For each protocol run cut short: what its missing segments leave each fit resting on."""
    out: list[str] = []
    for cov in covs:
        if cov is None or not cov.partial:
            continue
        if cov.lacks("constant_speed"):
            if isinstance(friction, PriorFriction):
                rest = "friction is the prior"
            else:
                rest = "friction from " + (", ".join(pl.names_where(friction.sliding_))
                                           if len(pl.names) > 1 else
                                           "the other motion of the log")
            out.append(f"log {cov.name}: no constant-speed segments: {rest}")
        if lacks_mass_segments(cov):
            kinds = "acceleration" if cov.experiment == "identification" else "burst"
            if M_est is None or "prior" in M_basis:
                rest = ("the mass is the prior" if "given" not in M_basis
                        else "the mass is the one given (--mass)")
            elif isinstance(M_est, LagMassIdentifier):
                rest = "the mass from the other logs sampled fast enough"
            else:
                rest = (f"the mass from the integrated motion equation of the "
                        f"{pl.data.Ts * 1e3:g} ms samples")
            out.append(f"log {cov.name}: no {kinds} segments: {rest}")
        if cov.untested:
            for v in cov.untested:
                i = VALVES.index(v)
                if getattr(valves, "unopened_", np.zeros(4, bool))[i]:
                    rest = "its C and b are a prior"
                elif sources is not None and sources.valve[i]:
                    rest = f"its C and b from {', '.join(sources.valve[i])}"
                else:
                    rest = "its C and b from its other openings in the log"
                out.append(f"log {cov.name}: no valve tests of {v}: {rest}")
    return out


#: Slow sliding samples (2-20 mm/s) below which the Coulomb level is poorly separated from the
#: viscous term, and the Coulomb error then allowed for (relative to F_C).
LOW_SPEED_SAMPLES, LOW_SPEED_FC_ERROR = 500, 0.1


def _low_speed_margin(data: Dataset, friction: FrictionIdentifier,
                      notes: list[str]) -> tuple[float, float]:
    """Extra half-widths of θ3, θ4 when few sliding samples are slow (see theta_bounds)."""
    v = np.abs(data.v[friction.sliding_])
    slow = int(np.count_nonzero(v < 0.02))
    if slow >= LOW_SPEED_SAMPLES or v.size == 0:
        return 0.0, 0.0
    dF = LOW_SPEED_FC_ERROR * friction.F_C_
    v_rms = float(np.sqrt(np.mean(v**2)))
    notes.append(f"friction: only {slow} sliding samples below 20 mm/s, so the Coulomb level "
                 f"and the viscous coefficient trade off; θ3 and θ4 are widened by "
                 f"{dF / v_rms:.0f} N s/m and {dF:.0f} N ({LOW_SPEED_FC_ERROR:.0%} of F_C)")
    return dF / v_rms, dF


def _plant(data: Dataset, valves: ValveIdentifier, friction: FrictionIdentifier,
           mass: float) -> PlantConfig:
    """The identified model as a simulated rig."""
    period = 1.0 / data.rig.pwm_hz
    vdict = {}
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]),
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
    f = friction
    return PlantConfig.model_validate({
        "io": {"delay": float(valves.loop_delay_ or 0.0)},
        "rig": data.rig.model_dump(), "mass": float(mass), "payload": 0.0,
        "friction": {"F_S": f.F_S_, "F_C": f.F_C_, "v_s": f.v_s_, "alpha": f.alpha_,
                     "b_v": f.b_v_},
        "valves": vdict, "leak": {"C": min(valves.leak_C_, 1e-7)},
        "disturbance": {"F_n": f.F_n_, "D_a": float(valves.D_[0]), "D_b": float(valves.D_[1])},
    })


#: Relative half-width of C for a valve never run at full duty whose C comes from the timing
#: stage (the exact opening per sample).
CLOSED_LOOP_C_ERROR = 0.12
#: Smallest half-width of b for a valve never run at full duty [-].
PARTIAL_B_ERROR = 0.12
#: A valve counts as fully open for its C and b only if the log holds it at duty 1 for this long
#: at a stretch [s]: a whole charge or vent (the identification run's last 1.5 s and more). A
#: closed-loop log has every valve at duty 1 in bursts of 0.01-0.28 s (benchmarks/fleet.py,
#: kind c), which left C and b ranges that missed the truth on 7 of 12 fleet plants.
FULL_OPEN_PIN_S = 0.5
#: Prior ranges of the Stribeck velocity [m/s] and exponent [-] of pneumatic cylinder seals,
#: joined with the fit's: both are weakly identified from samples that miss the stiction peak.
V_S_PRIOR, ALPHA_PRIOR = (1.0e-3, 1.0e-2), (0.5, 3.0)


def _hull(a: tuple[float, float], b: tuple[float, float]) -> list[float]:
    """The smallest interval holding both."""
    return [min(a[0], b[0]), max(a[1], b[1])]


def _range(value: float, sd: float, rel_floor: float, lo_floor: float = 0.0,
           hi_cap: float = np.inf) -> tuple[float, float]:
    half = max(3.29 * sd, rel_floor * abs(value))
    return max(lo_floor, value - half), min(hi_cap, value + half)


#: Stiction excess allowed for when the log shows no break-away: F_S <= this times F_C (a prior:
#: cylinder seals break away at 1.1-2 times their sliding friction).
STICTION_PRIOR_MAX = 2.0


@dataclass(frozen=True)
class Ranges:
    """The ranges of the model's plant coordinates and where each came from.

    Attributes
    ----------
    basis : dict
        Coordinate key path (as :func:`pneutune.control.sim.model_box.uncertainty_box` names it)
        -> one sentence: ``statistics: ...``, ``data bound: ...`` or ``prior: ...``.
    unsupported : frozenset of str
        The coordinates whose range is not a statistical fit (a prior, a structural margin, an
        unidentifiable parameter): those the cross-check tests against the log.
    """

    basis: dict[str, str]
    unsupported: frozenset[str]


def _stiction_range(logs: Dataset | Sequence[Dataset], friction: FrictionIdentifier,
                    F_C_range: tuple[float, float], theta: ThetaBounds, notes: list[str],
                    names: Sequence[str] = ()) -> tuple[float, tuple[float, float], str]:
    """F_S nominal, range and basis: stick and break-away events bound F_S from both sides
    (:mod:`.stiction`); where the log has none, a prior (F_C .. STICTION_PRIOR_MAX F_C).

    With several logs (``names`` theirs) each is read at its own sampling period, and the
    highest lower bound and the lowest upper bound are kept, each naming its log.
    """
    many = not isinstance(logs, Dataset)
    datasets = list(logs) if many else [logs]
    F_n = float(theta.nominal[1])
    F_n_half = 0.5 * float(theta.hi[1] - theta.lo[1])
    found: list[tuple[str, StictionBounds]] = []
    for j, log in enumerate(datasets):
        where = f" in {names[j]}" if many else ""
        try:
            found.append((where, stiction_bounds(log, F_n, F_n_half,
                                                 b_v_max=float(theta.hi[2]),
                                                 m_max=float(theta.hi[0]))))
        except (ValueError, np.linalg.LinAlgError) as exc:  # too little data for the events
            notes.append(f"friction: no stick or break-away events could be read{where} "
                         f"({exc})")
    lows = [(w, b) for w, b in found if b.lo is not None]
    highs = [(w, b) for w, b in found if b.hi is not None and np.isfinite(b.hi)]
    lo_w, sb_lo = max(lows, key=lambda wb: wb[1].lo) if lows else ("", None)
    hi_w, sb_hi = min(highs, key=lambda wb: wb[1].hi) if highs else ("", None)
    sb = found[0][1] if found and not many else None
    lo = F_C_range[0]
    hi = STICTION_PRIOR_MAX * F_C_range[1]
    parts = []
    if sb_lo is not None and sb_lo.lo > lo:
        lo = float(sb_lo.lo)
        e = sb_lo.lo_event
        parts.append((f"at rest under {abs(e.F):.4g} N at t = {e.t:.3f} s" if e else
                      f"at rest under {lo:.4g} N") + lo_w)
    if sb_hi is not None:
        e = sb_hi.hi_event
        parts.append((f"broke away at {abs(e.F):.4g} N at t = {e.t:.3f} s" if e else
                      f"broke away below {sb_hi.hi:.4g} N") + hi_w)
        if sb_hi.hi < hi:
            hi = float(sb_hi.hi)
            kind = "data bound"
        else:
            kind = "prior"
            parts.append(f"the prior F_S <= {STICTION_PRIOR_MAX:g} F_C_max = {hi:.4g} N is "
                         f"tighter than the break-aways ({sb_hi.hi:.4g} N)")
    else:
        kind = "prior"
        notes.append(f"friction: the {'logs show' if many else 'log shows'} no break-away "
                     f"from rest away from the end "
                     f"stops, so nothing bounds the stiction force from above; F_S <= "
                     f"{STICTION_PRIOR_MAX:g} F_C_max = {hi:.4g} N is a prior (cylinder seals "
                     f"break away at 1.1-2 times their sliding friction)")
    if lo > hi:  # events inconsistent with each other or with F_C: trust the events' span
        notes.append(f"friction: the stick and break-away bounds of F_S ({lo:.4g} N, "
                     f"{hi:.4g} N) contradict each other or F_C; F_S is taken in between")
        lo, hi = min(lo, hi), max(lo, hi)
    nominal = float(np.clip(friction.F_S_, lo, hi))
    if not friction.stiction_resolved_:  # the sliding samples do not show the peak
        nominal = 0.5 * (lo + hi)
    detail = "; ".join(parts) if parts else "no rest or break-away events"
    if many:  # each log's events and noise
        sb_text = "; ".join(f"{w.strip()}: {b.basis}" for w, b in found)
    else:
        sb_text = sb.basis if sb is not None else ""
    basis = (f"{kind}: {detail}" + (f"; {sb_text}" if sb_text else "")
             + ("" if kind == "data bound" else f"; F_S <= {STICTION_PRIOR_MAX:g} F_C (prior)"))
    return nominal, (lo, hi), basis


#: Range of a valve's conductance that no log opens, as a factor either side of the geometric
#: mean of the conductances the logs do identify (the valves of one rig are mostly of one
#: type): a prior.
UNOPENED_C_FACTOR = 4.0


def _model(data: Dataset, logs: Dataset | Sequence[Dataset], valves: ValveIdentifier,
           friction: FrictionIdentifier | PriorFriction, mass: float,
           mass_range: tuple[float, float], mass_basis: str, theta: ThetaBounds,
           validation: Validation, notes: list[str], period: float,
           sources: _Sources | None = None) -> tuple[ModelConfig, Ranges]:
    """model.yaml's document and the ranges' bases. ``logs``: the log, or every log, at its
    own sampling period; ``sources``: which logs each fit drew on (several logs only)."""
    datasets = [logs] if isinstance(logs, Dataset) else list(logs)
    names = display_names([d.path for d in datasets])
    log = datasets[0]
    vdict = {}
    basis: dict[str, str] = {}
    unsupported: set[str] = set()
    unopened = getattr(valves, "unopened_", np.zeros(4, dtype=bool))
    opened_C = valves.C_[~unopened] if np.any(~unopened) else valves.C_
    C_ref = float(np.exp(np.mean(np.log(opened_C))))
    for i, name in enumerate(VALVES):
        sw = valves.switching(period, i)
        if unopened[i]:
            # never commanded open in any log: C and b are a prior, checked against the logs
            c_lo, c_hi = C_ref / UNOPENED_C_FACTOR, min(C_ref * UNOPENED_C_FACTOR, 1e-6)
            basis[f"valves.{name}.C"] = (
                f"prior: never commanded open in the logs; within a factor "
                f"{UNOPENED_C_FACTOR:g} of the geometric mean {C_ref:.4g} m^3/(s Pa) of the "
                f"conductances the logs identify")
            basis[f"valves.{name}.b"] = "prior: never commanded open in the logs; 0-0.95"
            unsupported |= {f"valves.{name}.C", f"valves.{name}.b"}
            vdict[name] = {"C": C_ref, "b": float(np.clip(valves.b_[i], 0.0, 0.95)),
                           "C_min": c_lo, "C_max": c_hi, "b_min": 0.0, "b_max": 0.95,
                           "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                           "min_pulse": sw["min_pulse"]}
            v_duty, v_ratio = _curve_points(valves.knots_, valves.curves_[i])
            vdict[name]["pwm"] = {"duty": v_duty, "ratio": v_ratio}
            continue
        c_lo, c_hi = _range(valves.C_[i], valves.C_std_[i], 0.03, 1e-12, 1e-6)
        c_basis = f"statistics: ±3.29 s.e. ({valves.C_std_[i]:.2g}), at least ±3 %"
        pinned = valves.full_open_s_[i] >= FULL_OPEN_PIN_S
        if not pinned and valves.timing_ is not None:
            # never held fully open, C from the exact opening per sample: C within 4 % on most
            # closed-loop logs of simulated rigs, 9 % where b traded off (benchmarks/fleet.py)
            c_lo, c_hi = _range(valves.C_[i], valves.C_std_[i], CLOSED_LOOP_C_ERROR, 1e-12,
                                1e-6)
            c_basis = (f"statistics and a structural margin: never held fully open for "
                       f"{FULL_OPEN_PIN_S:g} s, C from the exact opening per sample, "
                       f"±{CLOSED_LOOP_C_ERROR:.0%}")
            unsupported.add(f"valves.{name}.C")
        elif valves.max_duty_[i] < 0.999:
            # never fully open: only C r(u) over the duties seen is determined; with
            # r(u_max) <= r_true(u_max) <= 1 the conductance lies in [C r(u_max), C / r(u_max)]
            r_top = float(max(valves.ratio(valves.max_duty_[i], i), 0.05))
            c_lo = min(c_lo, valves.C_[i] * r_top)
            c_hi = min(max(c_hi, valves.C_[i] / r_top), 1e-6)
            c_basis = (f"structural: never fully open, C r(u) known to u = "
                       f"{valves.max_duty_[i]:.2f} only, [C r(u_max), C / r(u_max)]")
            unsupported.add(f"valves.{name}.C")
        b_lo, b_hi = _range(valves.b_[i], valves.b_std_[i], 0.05, 0.0, 0.95)
        b_basis = f"statistics: ±3.29 s.e. ({valves.b_std_[i]:.2g}), at least ±5 %"
        if not pinned:
            # never held fully open: b shows only through partial openings; on closed-loop logs of
            # the fleet it came out up to 0.1 off, several times its statistical error
            b_lo = max(0.0, min(b_lo, valves.b_[i] - PARTIAL_B_ERROR))
            b_hi = min(0.95, max(b_hi, valves.b_[i] + PARTIAL_B_ERROR))
            b_basis += (f", at least ±{PARTIAL_B_ERROR:g} (never held fully open for "
                        f"{FULL_OPEN_PIN_S:g} s)")
            unsupported.add(f"valves.{name}.b")
        if b_hi - b_lo > WEAK_B_SPAN:
            unsupported.add(f"valves.{name}.b")
            b_basis = "weakly identified: " + b_basis
        if b_hi - b_lo > 0.5:
            # b unidentifiable: the subsonic flow, hence C, is then only known to a factor
            c_lo, c_hi = min(c_lo, 0.5 * valves.C_[i]), min(max(c_hi, 2.0 * valves.C_[i]), 1e-6)
            c_basis = "structural: b not identifiable, so C to a factor 2"
            unsupported.add(f"valves.{name}.C")
        if sources is not None:
            c_basis += _from(sources.valve[i])
            b_basis += _from(sources.valve[i])
        basis[f"valves.{name}.C"] = c_basis
        basis[f"valves.{name}.b"] = b_basis
        vdict[name] = {"C": float(valves.C_[i]), "b": float(valves.b_[i]), "C_min": c_lo,
                       "C_max": c_hi, "b_min": b_lo, "b_max": b_hi,
                       "delay_on": sw["delay_on"], "delay_off": sw["delay_off"],
                       "min_pulse": sw["min_pulse"]}
        v_duty, v_ratio = _curve_points(valves.knots_, valves.curves_[i])
        vdict[name]["pwm"] = {"duty": v_duty, "ratio": v_ratio}
    f = friction
    sd = f.std_
    prior = isinstance(f, PriorFriction)
    F_C_range = f.F_C_range_ if prior else _range(f.F_C_, sd["F_C"], 0.1)
    b_v_range = f.b_v_range_ if prior else _range(f.b_v_, sd["b_v"], 0.05)
    F_S, F_S_range, basis["friction.F_S"] = _stiction_range(
        log if len(datasets) == 1 else datasets, f, F_C_range, theta, notes, names)
    unsupported |= {"friction.F_S", "friction.v_s", "friction.alpha"}
    fsrc = sources.friction if sources is not None else ""
    if prior:
        basis["friction.F_C"] = basis["friction.b_v"] = f.basis_
        # b_v and F_n are replayed against the log; the Coulomb level is not: on a log whose
        # piston hardly moves the corners cannot tell it from the viscous term, and halving its
        # range toward the prior's geometric mean (88 N) cut off the truth (50 N) on
        # data/run.mcap cut before its ramps
        unsupported |= {"friction.b_v", "disturbance.F_n"}
    else:
        basis["friction.F_C"] = (f"statistics: ±3.29 s.e. ({sd['F_C']:.3g} N), at least ±10 %"
                                 + fsrc)
        basis["friction.b_v"] = (f"statistics: ±3.29 s.e. ({sd['b_v']:.3g} N s/m), at least "
                                 f"±5 %" + fsrc)
    basis["friction.v_s"] = (f"prior {V_S_PRIOR[0] * 1e3:g}-{V_S_PRIOR[1] * 1e3:g} mm/s "
                             "joined with the fit's ±3.29 s.e. (at least ±50 %): weakly "
                             "identified" + fsrc)
    basis["friction.alpha"] = (f"prior {ALPHA_PRIOR[0]:g}-{ALPHA_PRIOR[1]:g} joined with the "
                               "fit's ±3.29 s.e. (at least ±50 %): weakly identified" + fsrc)
    basis["mass"] = mass_basis
    if "prior" in mass_basis:
        unsupported.add("mass")
    for key, i in (("disturbance.F_n", 1), ("disturbance.D_a", 4), ("disturbance.D_b", 5)):
        basis[key] = ("" if prior and i == 1 else "statistics: ") + theta.basis[i]
    for ch, key in enumerate(("disturbance.D_a", "disturbance.D_b")):
        if valves.D_closed_[ch] is False:
            unsupported.add(key)
            basis[key] = ("weakly identified: the chamber's valves are never all shut, "
                          "widened to cover zero")
    duty, ratio = _curve_points(valves.knots_, valves.curve_)
    src = [{"log": d.path, "sha256": d.sha256, "duration_s": d.duration,
            **({"run": d.run_record} if d.run_record is not None else {})} for d in datasets]
    data_dict = {
        "schema": MODEL_SCHEMA,
        # one log: the mapping outside readers know; several: one mapping per log
        "source": src[0] if len(src) == 1 else src,
        "rig": data.rig.model_dump(),
        "valves": vdict,
        "pwm": {"duty": duty, "ratio": ratio},
        "friction": {
            "F_S": max(F_S, f.F_C_), "F_C": f.F_C_, "v_s": f.v_s_, "alpha": f.alpha_,
            "b_v": f.b_v_, "A_f": float(theta.nominal[3]),
            "ranges": {
                "F_S": [min(F_S_range[0], f.F_C_), max(F_S_range[1], F_S, f.F_C_)],
                "F_C": list(F_C_range),
                "v_s": _hull(_range(f.v_s_, sd["v_s"], 0.5, 1e-4, 1.0), V_S_PRIOR),
                "alpha": _hull(_range(f.alpha_, sd["alpha"], 0.5, 0.3, 10.0), ALPHA_PRIOR),
                "b_v": list(b_v_range),
            },
        },
        "mass": float(mass),
        "mass_range": list(mass_range),
        "theta": {"nominal": theta.nominal.tolist(), "min": theta.lo.tolist(),
                  "max": theta.hi.tolist()},
        "uncertainty": {"F_max": f.residual_max_, "D_a_max": float(valves.D_max_[0]),
                        "D_b_max": float(valves.D_max_[1])},
        "fit": {"nrmse_x": validation.nrmse["x"], "nrmse_p_a": validation.nrmse["p_a"],
                "nrmse_p_b": validation.nrmse["p_b"]},
        "leak": {"C": min(valves.leak_C_, 1e-7)},
        "sensors": _noise_levels(datasets),
        "basis": basis,
        "notes": notes,
    }
    data_dict.update(_loop_delay(valves, vdict, basis))
    return ModelConfig.model_validate(data_dict), Ranges(basis, frozenset(unsupported))


def _loop_delay(valves: ValveIdentifier, vdict: dict[str, dict[str, Any]],
                basis: dict[str, str]) -> dict[str, Any]:
    """model.yaml's ``effects.io.delay`` and ``loop_delay`` from the timing stage (none
    without it), with their bases added to ``basis``.

    ``io.delay`` is the part of the loop delay the valves' delays do not hold: a duty acting
    later than its sample, which the log separates only where it holds both steady duties
    (valve tests) and changing ones (a closed loop). ``loop_delay`` is the whole of it, from a
    written duty to the chamber flow's response: the valves' opening delays plus ``io.delay``.
    """
    if valves.loop_delay_ is None or valves.loop_delay_range_ is None:
        return {}
    d = float(valves.loop_delay_)
    lo, hi = (float(x) for x in valves.loop_delay_range_)
    grid, costs = valves.loop_delay_costs_
    best = (f"best {d * 1e3:g} ms, against which none leaves {costs[0] / costs.min():.3g} "
            f"times the residual" if d > 0.0 else "best none")
    basis["io.delay"] = (
        f"data: the chamber fit's residual over duties acting 0-{grid[-1] * 1e3:g} ms after "
        f"their samples, with the valves' delays as fitted: every delay within "
        f"{LOOP_DELAY_TOLERANCE:.0%} of the best ({best}); the valves' delays hold the rest "
        f"of the loop delay")
    ons = [float(v["delay_on"]) for v in vdict.values()]
    basis["loop_delay"] = (
        "data: the valves' opening delays (shortest to longest) plus io.delay's range: from a "
        "written duty to the chamber flow")
    return {"effects": {"io.delay": {"nominal": d, "range": [lo, hi]}},
            "loop_delay": {"nominal": float(np.mean(ons)) + d,
                           "range": [min(ons) + lo, max(ons) + hi]}}


def _curve_points(knots: np.ndarray, curve: np.ndarray) -> tuple[list[float], list[float]]:
    """The curve as contract-3 points, rounded, starting at (0, 0)."""
    duty = [round(float(k), 6) for k in knots]
    ratio = [round(float(r), 6) for r in np.maximum.accumulate(np.clip(curve, 0.0, 1.0))]
    ratio[0] = 0.0
    return duty, ratio


def _noise_levels(data: Dataset | Sequence[Dataset]) -> dict[str, float]:
    """Sensor noise [m, Pa] from third differences where the signal is smooth at the sample
    scale (:func:`~pneutune.identify.stiction.position_noise_std`: the piston at rest;
    :func:`~pneutune.identify.stiction.force_noise_std`: the chambers with their valves shut, or the
    supply sensor). A smoothing residual would count the PWM ripple of a closed-loop log as
    noise (10 times the truth, measured).

    With several logs, the smallest level any log shows: what a log's estimate fails to
    separate from the signal (ripple, motion) only adds to it."""
    datasets = [data] if isinstance(data, Dataset) else list(data)
    x_noise, p_noise = np.inf, np.inf
    for d in datasets:
        r = d.rig
        sigma_F, _ = force_noise_std(d)
        p_noise = min(p_noise, sigma_F / float(np.hypot(r.A_a, r.A_b)))
        x_noise = min(x_noise, position_noise_std(d.x))
    return {"x_noise": float(min(x_noise, 1e-3)),
            "p_noise": float(min(p_noise, 1e5))}
