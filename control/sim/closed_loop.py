"""Plant and controller at Ts, compiled as one loop, and the paper's metrics.

:func:`run_kernel` is the inner loop of tuning: per sample it measures (noisy sensors), calls
the one controller step (:func:`pneutune.control.law.darc.step_into`), writes the duties and
advances the plant (:func:`pneutune.control.plant.dynamics.advance`) to the next sample. Nothing
else.

:func:`simulate_scenario` wraps it: it builds the plant for a scenario (payload, force steps),
starts the piston at rest where the reference starts with the chamber pressures in force
balance (:func:`pneutune.control.plant.dynamics.rest_pressures`), runs and computes
:class:`Metrics`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import prange

from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.darc import (
    CONTROL_STATE_FIELDS,
    MEAS_SIZE,
    S_THETA,
    init_state,
    step_into,
)
from pneutune.control.law.layout import pack
from pneutune.control.logs.recording import Recording
from pneutune.control.numba_cache import njit
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.dynamics import rest_pressures
from pneutune.control.plant.params import pack_plant
from pneutune.control.sim.scenarios import Scenario, metric_window

#: State indices logged on ``/control/state``: the named fields, then θ̂ (6).
LOG_INDEX = np.array([*CONTROL_STATE_FIELDS.values(), *range(S_THETA, S_THETA + 6)],
                     dtype=np.int64)

STATUS_OK, STATUS_UNSTABLE, STATUS_ABORTED = "ok", "unstable", "aborted"
#: θ̂ has settled when no estimate moves by more than this fraction of its box over the metric
#: window (Metrics.theta_drift).
THETA_SETTLED = 0.02
#: A full opening counts towards :attr:`Metrics.flow_limited` only when it lasts this long [s]
#: (six 60 Hz PWM periods): shorter bursts are the gains chattering, not the valves' limit.
FULL_OPEN_SUSTAIN = 0.1


@njit(cache=True)
def run_kernel(p: np.ndarray, s: np.ndarray, force_steps: np.ndarray, p_s: np.ndarray,
               cfg: np.ndarray, cs: np.ndarray, ref: np.ndarray, noise: np.ndarray, Ts: float,
               log_index: np.ndarray, abort_error: float, sensors: np.ndarray,
               duties: np.ndarray, cstate: np.ndarray, truth_out: np.ndarray) -> int:
    """Run the closed loop over ``ref.shape[0]`` samples.

    Parameters
    ----------
    p, s, force_steps : ndarray
        Packed plant, plant state (updated) and force steps.
    p_s : ndarray, (N,)
        Supply pressure per sample [Pa abs].
    cfg, cs : ndarray
        Packed controller config and controller state (updated).
    ref : ndarray, (N, 3)
        ``[x_r, v_r, a_r]`` per sample.
    noise : ndarray, (N, 4)
        Standard-normal draws for the sensors.
    Ts : float
        Sampling period [s].
    log_index : ndarray of int
        Controller-state indices to record per sample in ``cstate``.
    abort_error : float
        Stop early when the measured |e1| exceeds this [m] (use inf to never abort).
    sensors, duties, cstate : ndarray
        Outputs (N, 4), (N, 4), (N, len(log_index)).
    truth_out : ndarray
        (N, 6) to record ``/sim/truth``, or (0, 6) not to.

    Returns
    -------
    int
        Samples completed ``n`` if all went well; ``-(k+1)`` if the plant state became
        non-finite, or a chamber's absolute pressure fell to zero or below, at sample k
        (unstable); ``-(n + 1 + k)`` if aborted at sample k on
        ``abort_error``.
    """
    n = ref.shape[0]
    meas = np.empty(MEAS_SIZE)
    d = np.empty(4)
    want_truth = truth_out.shape[0] > 0
    for k in range(n):
        t = k * Ts
        plant.measure(p, s, p_s[k], noise[k], sensors[k])
        if want_truth:
            plant.truth(p, s, p_s[k], force_steps, truth_out[k])
        meas[0] = t
        meas[1] = sensors[k, 0]
        meas[2] = sensors[k, 1]
        meas[3] = sensors[k, 2]
        meas[4] = sensors[k, 3]
        meas[5] = ref[k, 0]
        meas[6] = ref[k, 1]
        meas[7] = ref[k, 2]
        step_into(cs, meas, cfg, d)
        for i in range(4):
            duties[k, i] = d[i]
        for j in range(log_index.shape[0]):
            cstate[k, j] = cs[log_index[j]]
        plant.set_duties(p, s, t, d)
        plant.advance(p, s, (k + 1) * Ts, p_s[k], force_steps)
        if plant.diverged(s):
            return -(k + 1)
        if abs(sensors[k, 0] - ref[k, 0]) > abort_error:
            return -(n + 1 + k)
    return n


@dataclass(frozen=True)
class Metrics:
    """The paper's indices (Sec. 5.1) and the health of a closed-loop run.

    Attributes
    ----------
    E_p_mm, E_rms_mm : float
        Peak and RMS of the measured tracking error e1 over the last three reference periods
        [mm].
    switches_per_s : float
        Valve mode changes (modes 1, 2, 3 of Sec. 3.2) per second over the same window.
    p_a_max_Pa, p_b_max_Pa, p_a_min_Pa, p_b_min_Pa : float
        Measured chamber pressure extremes over the whole run [Pa abs].
    theta_in_bounds : bool
        θ̂ stayed within [θ_min, θ_max] at every sample.
    end_stop_s : float
        Time the measured position spent within 0.2 mm of a stroke end [s].
    status : str
        ok | unstable | aborted.
    theta_drift : float
        How far θ̂ still moved over the metric window: the largest |Δθ̂_i| over the last three
        periods, as a fraction of its box θ_max,i - θ_min,i [-].
    theta_settled : bool
        ``theta_drift`` below :data:`THETA_SETTLED` (θ̂ has settled by the metric window, so
        the indices would not change much with a longer run).
    full_open : float
        Fraction of the metric window in which the controller commands a valve at its top duty
        (Eq. 33's sat(Q_Ld / Q_L,F) = 1: the valves' whole flow) [-]. Where it is large the
        error may be set by the valves' flow, or the gains may be chattering between the modes
        at full opening (nan when not computed).
    flow_limited : float
        The part of ``full_open`` spent with a valve in a full opening that lasts at least
        :data:`FULL_OPEN_SUSTAIN` without a break (:func:`sustained_runs`) [-]. Where it is
        large the reference asks for more flow than the valves give, so the error is set by the
        valves' flow, not by the gains (nan when not computed). A controller that chatters at
        full opening has a large ``full_open`` but a small ``flow_limited``.
    """

    E_p_mm: float
    E_rms_mm: float
    switches_per_s: float
    p_a_max_Pa: float
    p_b_max_Pa: float
    p_a_min_Pa: float
    p_b_min_Pa: float
    theta_in_bounds: bool
    end_stop_s: float
    status: str
    theta_drift: float = float("nan")
    theta_settled: bool = False
    full_open: float = float("nan")
    flow_limited: float = float("nan")

    def as_dict(self) -> dict[str, float | bool | str]:
        """Plain dict (the metrics of the run log contract plus the extra fields)."""
        return dict(self.__dict__)


@dataclass(frozen=True)
class ClosedLoopResult:
    """Everything one closed-loop run produced (arrays are per sample, truncated at a stop)."""

    scenario: Scenario
    plant: PlantConfig
    controller: ControllerConfig
    seed: int
    Ts: float
    reference: np.ndarray
    sensors: np.ndarray
    duties: np.ndarray
    control_state: np.ndarray
    truth: np.ndarray | None
    metrics: Metrics

    @property
    def t(self) -> np.ndarray:
        """Sample times [s]."""
        return np.arange(self.sensors.shape[0]) * self.Ts

    def recording(self) -> Recording:
        """The run as a :class:`Recording` (for an MCAP log)."""
        n = self.sensors.shape[0]
        rec = Recording(n, self.Ts, truth=self.truth is not None, reference=True,
                        control_state=True)
        rec.sensors_[:] = self.sensors
        rec.duties_[:] = self.duties
        rec.reference_[:] = self.reference[:n]
        rec.state_[:] = self.control_state
        if self.truth is not None:
            rec.truth_[:] = self.truth
        rec.segment(0.0, self.scenario.name, "scenario",
                    {"description": self.scenario.description,
                     "duration": self.scenario.duration})
        if self.metrics.status != STATUS_OK:
            rec.event(n * self.Ts, "error", f"run_{self.metrics.status}",
                      f"the closed loop stopped after {n} samples ({self.metrics.status})")
        return rec


@njit(cache=True)
def _sustained_mask(mask: np.ndarray, min_run: int) -> np.ndarray:
    """:func:`sustained_runs` on a (n, k) bool array (compiled)."""
    n, k = mask.shape
    out = np.zeros(n, dtype=np.bool_)
    need = max(min_run, 1)
    for j in range(k):
        start = -1
        for i in range(n + 1):
            on = i < n and mask[i, j]
            if on and start < 0:
                start = i
            elif not on and start >= 0:
                if i - start >= need:
                    out[start:i] = True
                start = -1
    return out


@njit(cache=True)
def _window_counts(x: np.ndarray, duties: np.ndarray, theta: np.ndarray,
                   theta_min: np.ndarray, theta_max: np.ndarray, duty_top: np.ndarray,
                   x_min: float, x_max: float, window: int,
                   min_run: int) -> tuple[int, bool, int, int, int]:
    """The counting parts of :func:`compute_metrics` (exact integers, compiled).

    Returns mode switches within the last ``window`` samples (the mode of a sample: 1 when
    a_in or b_out is driven, else 2 when a_out or b_in is, else 3), whether every θ̂ sample is
    inside its bounds (with a relative tolerance of 1e-12), samples within 0.2 mm of a stroke
    end, and within the window the samples with some valve at full opening (``duties >=
    duty_top - 1e-9``, one top duty per valve) and those inside a full opening of at least
    ``min_run`` samples (:func:`sustained_runs`). ``duty_top`` empty skips the last two
    (returned as 0).
    """
    n = x.shape[0]
    first = n - window
    switches = 0
    prev = 0
    for i in range(first, n):
        d = duties[i]
        mode = 1 if (d[0] > 0.0 or d[3] > 0.0) else (2 if (d[1] > 0.0 or d[2] > 0.0) else 3)
        if i > first and mode != prev:
            switches += 1
        prev = mode
    in_bounds = True
    for j in range(theta.shape[1]):
        tol = 1e-12 * max(1.0, abs(theta_max[j] - theta_min[j]))
        lo = theta_min[j] - tol
        hi = theta_max[j] + tol
        for i in range(theta.shape[0]):
            if not (theta[i, j] >= lo and theta[i, j] <= hi):
                in_bounds = False
    near = 0
    for i in range(n):
        if x[i] <= x_min + 2e-4 or x[i] >= x_max - 2e-4:
            near += 1
    full_count = 0
    sustained = 0
    if duty_top.shape[0] > 0:
        k = duties.shape[1]
        full = np.zeros((window, k), dtype=np.bool_)
        for i in range(window):
            for j in range(k):
                full[i, j] = duties[first + i, j] >= duty_top[j] - 1e-9
            for j in range(k):
                if full[i, j]:
                    full_count += 1
                    break
        for flag in _sustained_mask(full, min_run):
            if flag:
                sustained += 1
    return switches, in_bounds, near, full_count, sustained


def compute_metrics(scenario: Scenario, Ts: float, reference: np.ndarray, sensors: np.ndarray,
                    duties: np.ndarray, control_state: np.ndarray, theta_min: np.ndarray,
                    theta_max: np.ndarray, x_min: float, x_max: float, status: str,
                    duty_top: float | np.ndarray | None = None) -> Metrics:
    """The indices of Sec. 5.1 over the last three periods, plus health checks.

    ``duty_top`` is the duty from which a valve is fully open, one for all or one per valve
    (``controller.top_duties``), for
    :attr:`Metrics.full_open` and :attr:`Metrics.flow_limited`; None leaves them nan.
    """
    n = sensors.shape[0]
    window = min(n, metric_window(scenario.period, Ts))
    nan = float("nan")
    if n == 0:
        return Metrics(nan, nan, nan, nan, nan, nan, nan, False, nan, status)
    e1 = sensors[n - window:, 0] - reference[n - window:n, 0]
    theta = control_state[:, -6:]
    tops = (np.zeros(0) if duty_top is None else np.ascontiguousarray(
        np.broadcast_to(np.asarray(duty_top, dtype=np.float64), (duties.shape[1],))))
    switch_count, in_bounds, near, full_count, sustained = _window_counts(
        np.ascontiguousarray(sensors[:, 0]), np.ascontiguousarray(duties), theta,
        np.atleast_1d(np.asarray(theta_min, dtype=np.float64)),
        np.atleast_1d(np.asarray(theta_max, dtype=np.float64)), tops, float(x_min),
        float(x_max), int(window), round(FULL_OPEN_SUSTAIN / Ts))
    switches = float(switch_count) / (window * Ts)
    span = np.maximum(np.asarray(theta_max) - np.asarray(theta_min), 1e-300)
    drift = float(np.max(np.abs(theta[-1] - theta[n - window]) / span))
    full_open = flow_limited = nan
    if duty_top is not None:
        full_open = full_count / window
        flow_limited = sustained / window
    return Metrics(
        E_p_mm=float(np.max(np.abs(e1)) * 1e3),
        E_rms_mm=float(np.sqrt(np.mean(e1**2)) * 1e3),
        switches_per_s=switches,
        p_a_max_Pa=float(np.max(sensors[:, 1])), p_b_max_Pa=float(np.max(sensors[:, 2])),
        p_a_min_Pa=float(np.min(sensors[:, 1])), p_b_min_Pa=float(np.min(sensors[:, 2])),
        theta_in_bounds=bool(in_bounds), end_stop_s=float(near * Ts),
        status=status, theta_drift=drift, theta_settled=drift < THETA_SETTLED,
        full_open=full_open, flow_limited=flow_limited,
    )


def sustained_runs(mask: np.ndarray, min_run: int) -> np.ndarray:
    """Per sample, whether some column of ``mask`` is inside a run of at least ``min_run``
    consecutive Trues.

    Parameters
    ----------
    mask : (n, k) bool
        Per sample and valve, the condition (the valve at full opening). Each column's runs
        are separate: a controller switching between two valve pairs at full opening has short
        runs in each.
    min_run : int
        Shortest run counted [samples].

    Returns
    -------
    (n,) bool
    """
    m = np.asarray(mask, dtype=bool)
    if m.ndim == 1:
        m = m[:, None]
    return _sustained_mask(np.ascontiguousarray(m), int(min_run))


def scenario_plant(plant_cfg: PlantConfig, scenario: Scenario) -> PlantConfig:
    """The plant with the scenario's changes (payload, force steps) merged in."""
    if not scenario.plant_updates:
        return plant_cfg
    return plant_cfg.with_updates(scenario.plant_updates, source=f"scenario {scenario.name}")


@dataclass(frozen=True)
class PreparedRun:
    """Everything of a closed-loop run that does not depend on the controller.

    Built once by :func:`prepare_run`; :func:`run_prepared` and :func:`run_batch` (through
    :func:`prepare_batch`) run any number
    of controllers on it (tuning scores every trial on the same prepared runs).

    Attributes
    ----------
    scenario : Scenario
        The scenario (its plant changes already merged into ``plant``).
    plant : PlantConfig
        The plant of the run.
    seed : int
        Sensor-noise seed.
    Ts : float
        Sampling period [s].
    vec, force_steps : ndarray
        Packed plant and force steps (:func:`~pneutune.control.plant.params.pack_plant`).
    reference : ndarray, (N, 3)
        ``[x_r, v_r, a_r]`` per sample.
    noise : ndarray, (N, 4)
        Standard-normal draws for the sensors.
    p_s : ndarray, (N,)
        Supply pressure per sample [Pa abs].
    state0 : ndarray
        Plant state at the start: at rest at ``reference[0]``, pressures in force balance.
    p_a0, p_b0 : float
        Those pressures [Pa abs].
    """

    scenario: Scenario
    plant: PlantConfig
    seed: int
    Ts: float
    vec: np.ndarray
    force_steps: np.ndarray
    reference: np.ndarray
    noise: np.ndarray
    p_s: np.ndarray
    state0: np.ndarray
    p_a0: float
    p_b0: float

    @property
    def n(self) -> int:
        """Samples in the run."""
        return int(self.reference.shape[0])


def prepare_run(scenario: Scenario, plant_cfg: PlantConfig | None = None,
                seed: int | None = None) -> PreparedRun:
    """The controller-independent part of a run (module docstring).

    Parameters
    ----------
    scenario : Scenario
        What to track; its plant changes (payload, force steps) are merged into the plant.
    plant_cfg : PlantConfig, optional
        The plant; default the paper's rig.
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.

    Returns
    -------
    PreparedRun
    """
    base = plant_cfg if plant_cfg is not None else PlantConfig()
    pcfg = scenario_plant(base, scenario)
    pp = pack_plant(pcfg)
    Ts = pcfg.rig.Ts
    center = 0.5 * (pcfg.rig.x_min + pcfg.rig.x_max)
    ref = scenario.reference_array(Ts, center)
    n = ref.shape[0]
    seed_used = pcfg.sim.seed if seed is None else int(seed)
    noise = np.random.default_rng(seed_used).standard_normal((n, 4))
    f0 = float(plant.external_force(pp.vec, pp.force_steps, 0.0))
    pa0, pb0 = rest_pressures(pp.vec, f0)
    s0 = plant.initial_state(pp.vec, float(ref[0, 0]), pa0, pb0)
    for arr in (pp.vec, pp.force_steps, ref, noise, s0):
        arr.setflags(write=False)  # shared by every run; the kernels copy what they change
    p_s = np.full(n, pp.p_s)
    p_s.setflags(write=False)
    return PreparedRun(scenario, pcfg, seed_used, Ts, pp.vec, pp.force_steps, ref, noise, p_s,
                       s0, float(pa0), float(pb0))


def _status(code: int, n: int) -> tuple[int, str]:
    """Samples done and status from a :func:`run_kernel` return code."""
    if code >= 0:
        return code, STATUS_OK
    if -code <= n:
        return -code, STATUS_UNSTABLE
    return -code - n, STATUS_ABORTED


def _result(run: PreparedRun, controller: ControllerConfig, code: int, sensors: np.ndarray,
            duties: np.ndarray, cstate: np.ndarray,
            truth: np.ndarray | None) -> ClosedLoopResult:
    """Wrap a kernel's outputs, truncated at a stop, with their metrics."""
    done, status = _status(code, run.n)
    a = controller.adaptation
    pcfg = run.plant
    metrics = compute_metrics(run.scenario, run.Ts, run.reference, sensors[:done], duties[:done],
                              cstate[:done], np.asarray(a.theta_min), np.asarray(a.theta_max),
                              pcfg.rig.x_min, pcfg.rig.x_max, status,
                              duty_top=np.asarray(controller.top_duties))
    return ClosedLoopResult(run.scenario, pcfg, controller, run.seed, run.Ts, run.reference,
                            sensors[:done], duties[:done], cstate[:done],
                            truth[:done] if truth is not None else None, metrics)


def run_prepared(run: PreparedRun, controller: ControllerConfig, record_truth: bool = False,
                 abort_error: float = np.inf,
                 cfg_vec: np.ndarray | None = None) -> ClosedLoopResult:
    """Run ``controller`` on a prepared run (:func:`prepare_run`).

    Parameters
    ----------
    run : PreparedRun
    controller : ControllerConfig
    record_truth : bool
        Keep ``/sim/truth``.
    abort_error : float
        Stop when |e1| exceeds this [m].
    cfg_vec : ndarray, optional
        Pre-packed ``controller``.

    Returns
    -------
    ClosedLoopResult
    """
    n = run.n
    cfg = pack(controller) if cfg_vec is None else cfg_vec
    s = run.state0.copy()
    cs = init_state(cfg, float(run.reference[0, 0]), run.p_a0, run.p_b0)
    sensors = np.zeros((n, 4))
    duties = np.zeros((n, 4))
    cstate = np.zeros((n, LOG_INDEX.shape[0]))
    truth = np.zeros((n if record_truth else 0, 6))
    code = run_kernel(run.vec, s, run.force_steps, run.p_s, cfg, cs, run.reference, run.noise,
                      run.Ts, LOG_INDEX, float(abort_error), sensors, duties, cstate, truth)
    return _result(run, controller, code, sensors, duties, cstate,
                   truth if record_truth else None)


@dataclass(frozen=True)
class PreparedBatch:
    """Prepared runs of equal length stacked for :func:`run_batch` (built once per scenario by
    :func:`prepare_batch`; row r of every array is run r).

    Attributes
    ----------
    runs : tuple of PreparedRun
    vecs, states, force_steps, n_force, p_s, refs, noise, Ts : ndarray
        The runs' arrays stacked; ``force_steps[r, :n_force[r]]`` are run r's force steps.
    """

    runs: tuple[PreparedRun, ...]
    vecs: np.ndarray
    states: np.ndarray
    force_steps: np.ndarray
    n_force: np.ndarray
    p_s: np.ndarray
    refs: np.ndarray
    noise: np.ndarray
    Ts: np.ndarray


def prepare_batch(runs: Sequence[PreparedRun]) -> PreparedBatch:
    """Stack prepared runs of the same number of samples (the draws of one scenario).

    Raises
    ------
    ValueError
        No runs, or runs of different lengths.
    """
    if not runs:
        raise ValueError("prepare_batch needs at least one run")
    n = runs[0].n
    if any(r.n != n for r in runs):
        raise ValueError(f"prepare_batch needs runs of equal length, got "
                         f"{sorted({r.n for r in runs})} samples")
    k_max = max(1, max(r.force_steps.shape[0] for r in runs))
    fsteps = np.zeros((len(runs), k_max, 2))
    for i, r in enumerate(runs):
        fsteps[i, :r.force_steps.shape[0]] = r.force_steps
    arrays = (np.stack([r.vec for r in runs]), np.stack([r.state0 for r in runs]), fsteps,
              np.array([r.force_steps.shape[0] for r in runs], dtype=np.int64),
              np.stack([r.p_s for r in runs]), np.stack([r.reference for r in runs]),
              np.stack([r.noise for r in runs]), np.array([r.Ts for r in runs]))
    for arr in arrays:
        arr.setflags(write=False)  # shared by every call; the kernel copies the states it changes
    return PreparedBatch(tuple(runs), *arrays)


@njit(cache=True, parallel=True)
def run_batch_kernel(vecs: np.ndarray, states: np.ndarray, force_steps: np.ndarray,
                     n_force: np.ndarray, p_s: np.ndarray, cfg: np.ndarray, cstates: np.ndarray,
                     refs: np.ndarray, noise: np.ndarray, Ts: np.ndarray, log_index: np.ndarray,
                     abort_error: float, sensors: np.ndarray, duties: np.ndarray,
                     cstate: np.ndarray, codes: np.ndarray) -> None:
    """:func:`run_kernel` on R runs of equal length, in parallel over the runs (``prange``).

    Run r uses row r of every per-run array. Each run is computed exactly as by
    :func:`run_kernel` alone, so the results do not depend on the number of threads.
    """
    no_truth = np.zeros((0, 6))
    for r in prange(vecs.shape[0]):
        codes[r] = run_kernel(vecs[r], states[r].copy(), force_steps[r, :n_force[r]], p_s[r],
                              cfg, cstates[r], refs[r], noise[r], Ts[r], log_index,
                              abort_error, sensors[r], duties[r], cstate[r], no_truth)


def run_batch(batch: PreparedBatch, controller: ControllerConfig, abort_error: float = np.inf,
              cfg_vec: np.ndarray | None = None) -> list[ClosedLoopResult]:
    """Run ``controller`` on every run of a batch in one compiled, multi-threaded call.

    Parameters
    ----------
    batch : PreparedBatch
        From :func:`prepare_batch`.
    controller : ControllerConfig
    abort_error : float
        Stop a run when its |e1| exceeds this [m].
    cfg_vec : ndarray, optional
        Pre-packed ``controller``.

    Returns
    -------
    list of ClosedLoopResult
        In the order of ``batch.runs``; each equal, bit for bit, to :func:`run_prepared` on it.

    Notes
    -----
    The threads are numba's (``numba.set_num_threads`` sets how many are used).
    """
    runs = batch.runs
    R, n = len(runs), runs[0].n
    cfg = pack(controller) if cfg_vec is None else cfg_vec
    cstates = np.stack([init_state(cfg, float(r.reference[0, 0]), r.p_a0, r.p_b0)
                        for r in runs])
    sensors = np.zeros((R, n, 4))
    duties = np.zeros((R, n, 4))
    cstate = np.zeros((R, n, LOG_INDEX.shape[0]))
    codes = np.zeros(R, dtype=np.int64)
    run_batch_kernel(batch.vecs, batch.states, batch.force_steps, batch.n_force, batch.p_s, cfg,
                     cstates, batch.refs, batch.noise, batch.Ts, LOG_INDEX, float(abort_error),
                     sensors, duties, cstate, codes)
    return [_result(r, controller, int(codes[i]), sensors[i], duties[i], cstate[i], None)
            for i, r in enumerate(runs)]


def simulate_scenario(controller: ControllerConfig, scenario: Scenario,
                      plant_cfg: PlantConfig | None = None, seed: int | None = None,
                      record_truth: bool = False, abort_error: float = np.inf,
                      cfg_vec: np.ndarray | None = None) -> ClosedLoopResult:
    """Run one scenario in closed loop on the simulated rig.

    :func:`prepare_run` then :func:`run_prepared`.

    Parameters
    ----------
    controller : ControllerConfig
        The controller.
    scenario : Scenario
        What to track (and the plant changes it implies).
    plant_cfg : PlantConfig, optional
        The plant; default the paper's rig.
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.
    record_truth : bool
        Keep ``/sim/truth``.
    abort_error : float
        Stop when |e1| exceeds this [m] (tuning prunes hopeless trials with it).
    cfg_vec : ndarray, optional
        Pre-packed ``controller`` (saves the packing in tight loops).

    Returns
    -------
    ClosedLoopResult
    """
    return run_prepared(prepare_run(scenario, plant_cfg, seed), controller,
                        record_truth=record_truth, abort_error=abort_error, cfg_vec=cfg_vec)
