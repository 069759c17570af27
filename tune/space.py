"""The search space of ``tune`` and the map from a trial's parameters to a controller.yaml.

What is searched (14 parameters, 15 on a model with a weakly identified valve b; named by their
controller.yaml key path; docs/tuning.md):

* ``gains.k1``, ``gains.k2``, ``gains.k3`` -- the backstepping gains of Eqs. (13), (17), (26).
* ``gains.h2``, ``gains.h3`` with ``eps2``/``eps3`` fixed at the paper's 0.05 and 250 (Sec. 5.1).
  With constant h (docs/controller.md) the robust terms of Eqs. (20) and (29) are
  ``-h2² e2 / (4 ε2)`` and ``-h3² e3 / (4 ε3)``: h and ε enter the law only through h²/ε
  (``control/law/darc.py``), so searching both would add a dimension with no effect. We search h and
  keep ε, the boundary-layer size of Eqs. (19)/(28), at the paper's value so that the guaranteed
  bound ε = r2 ε2 + r3 ε3 of Eq. (30) keeps its meaning. (κ2 = k2 + h2²/(4ε2) is the total e2
  gain; k2 and h2 are therefore partly redundant, which the multivariate TPE sampler handles --
  see docs/tuning.md.)
* ``gains.r3`` with ``r2`` = 1 fixed: r2 and r3 enter the law through the ratio r2/r3 in
  ``Q_Lda`` (Eq. 26) and as factors of τ (Eq. 26), which Γ absorbs; only the ratio matters.
* ``adaptation.gamma.<θ_i>`` -- the six diagonal entries of Γ (Eq. 9).
* ``adaptation.theta_0.b_v`` -- the initial estimate θ̂3(0) of the viscous coefficient, from the
  model's nominal θ3 up to four times it (the first trial: the nominal). θ3 multiplies the
  velocity in the model compensation of Eq. (15). On a model with wide, honest ranges from a
  short closed-loop log (fleet plant 1) no gains beat the paper's controller without a larger
  start, and over a 12 s scenario θ̂3 does not get there by adaptation (docs/tuning.md,
  "θ̂3(0)"). θ_max of b_v moves up in proportion (θ_max θ̂3(0) / θ3 nominal), so that the box
  keeps its room to adapt upwards; θ_min stays the model's, so the true b_v stays inside the
  box (Eq. 9's requirement). Searched only where some valve's b is weakly identified
  (:func:`searches_theta_0`); elsewhere θ̂3(0) is the model's nominal θ3.
* ``kalman.motion.Q`` and ``kalman.force.Q`` -- the process-noise variances of the two filters
  of Sec. 4. Their R are fixed: a Kalman filter's gains depend only on Q/R (the initial
  covariance is proportional to R too), so searching R as well would be a redundant dimension.
  The motion filter's R is the position-sensor variance of the model (``sensors.x_noise²``, the
  paper's 1e-10 m² when the model has none); the force filter's R is the paper's 1e-4 N².
  The motion filter's Q/R reaches 4.5 decades below the paper's (:data:`MOTION_Q_OVER_R`),
  poles down to 20 rad/s: with the lower end at 1e5 (43 rad/s) the best trials sat on it.

Every other range but θ̂3(0)'s spans one to three decades around the paper's value; all are
sampled on a log scale. Not searched: θ_min, θ_max and θ_0 other than θ3's (from model.yaml),
the rate limits θ̇_M and ``min_ref_speed`` (the paper's Sec. 5.1/5.3 values),
``position_feedback`` (``measured``, docs/controller.md), ``dead_zone`` (``up`` unless ``tune
--dead-zone dither``: fixed for a study, not searched, because dithering measured worse on four
of five fleet plants, docs/notes/2026-11-26-tune-levers.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import optuna

from pneutune.control.constants import CONTROLLER_SCHEMA, THETA_NAMES, WEAK_B_SPAN
from pneutune.control.contracts.controller import ControllerConfig, PidConfig
from pneutune.control.contracts.model import ModelConfig
from pneutune.control.contracts.yamlio import validate_model

#: The paper's Sec. 5.1 values that ``tune`` keeps fixed.
PAPER_EPS2: float = 0.05
PAPER_EPS3: float = 250.0
PAPER_R2: float = 1.0
PAPER_RATE_MAX: tuple[float, ...] = (50.0, 500.0, 2000.0, 100.0, 50.0, 50.0)
PAPER_MIN_REF_SPEED: float = 0.001
#: The paper's motion-filter R read in millimetres (docs/controller.md) [m^2].
PAPER_MOTION_R: float = 1.0e-10
#: The paper's force-filter R [N^2].
PAPER_FORCE_R: float = 1.0e-4
#: The paper's Q/R of both filters (3100 / 1e-4) [1/s^4].
PAPER_Q_OVER_R: float = 3.1e7
#: The motion filter's Q/R is searched over this range [1/s^4] (estimator poles about 20-430
#: rad/s; the paper's 3.1e7 gives about 112).
MOTION_Q_OVER_R: tuple[float, float] = (1.0e3, 1.0e11)
#: Index of the viscous coefficient b_v in θ.
THETA_B_V: int = THETA_NAMES.index("b_v")
#: The searched parameter θ̂3(0) (``adaptation.theta_0`` of b_v).
THETA_0_PARAM: str = "adaptation.theta_0.b_v"
#: θ̂3(0) is searched from the model's nominal θ3 up to this factor times it [-].
THETA_0_B_V_SPAN: float = 4.0
#: A kept parameter this share of its range's span from an end is reported as at that end.
RANGE_END_SHARE: float = 0.05
#: Headroom of the supervisor's pressure limit over the supply [Pa].
P_MAX_MARGIN: float = 0.5e5
#: Longest sensor silence the runtime tolerates (5 samples of 4 ms) [s].
SENSOR_TIMEOUT_S: float = 0.02


@dataclass(frozen=True)
class ParamSpec:
    """One searched parameter.

    Attributes
    ----------
    name : str
        Optuna parameter name: the controller.yaml key path (``gains.k1``,
        ``adaptation.gamma.M``, ``kalman.motion.Q``).
    low, high : float
        Range, in the parameter's SI unit.
    log : bool
        Sample on a log scale.
    unit : str
        SI unit, for reports.
    paper : float
        The paper's Sec. 5.1 value in the same unit (the first, enqueued trial).
    """

    name: str
    low: float
    high: float
    log: bool
    unit: str
    paper: float

    def distribution(self) -> optuna.distributions.FloatDistribution:
        """The Optuna distribution of this parameter."""
        return optuna.distributions.FloatDistribution(self.low, self.high, log=self.log)

    def clip(self, value: float) -> float:
        """``value`` clipped into [low, high]."""
        return min(self.high, max(self.low, value))


_GAMMA_UNITS = ("kg^2/(s N m/s)", "N^2/(s N)", "(N s/m)^2/(s N m/s)", "N^2/(s N)",
                "(Pa/s)^2/(s N m^2/s)", "(Pa/s)^2/(s N m^2/s)")


def motion_R(model: ModelConfig) -> float:
    """Fixed R of the motion filter: the model's position-noise variance [m^2].

    ``sensors.x_noise²`` of model.yaml, or the paper's 1e-10 m² when the model has no (or zero)
    position noise.
    """
    if model.sensors is not None and model.sensors.x_noise > 0.0:
        return float(model.sensors.x_noise) ** 2
    return PAPER_MOTION_R


@dataclass(frozen=True)
class SearchSpace:
    """The parameters searched for one model (the Kalman Q ranges scale with the model's R).

    Attributes
    ----------
    params : tuple of ParamSpec
        In a fixed order (the order Optuna suggests them).
    R_motion, R_force : float
        The fixed R of the motion [m^2] and force [N^2] filters.
    """

    params: tuple[ParamSpec, ...]
    R_motion: float
    R_force: float

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names, in order."""
        return tuple(p.name for p in self.params)

    def distributions(self) -> dict[str, optuna.distributions.FloatDistribution]:
        """Name -> Optuna distribution."""
        return {p.name: p.distribution() for p in self.params}

    def suggest(self, trial: optuna.Trial) -> dict[str, float]:
        """Ask ``trial`` for every parameter (in order)."""
        return {p.name: trial.suggest_float(p.name, p.low, p.high, log=p.log)
                for p in self.params}

    def paper_params(self) -> dict[str, float]:
        """The paper's values, clipped into the ranges (enqueued as the first trial)."""
        return {p.name: p.clip(p.paper) for p in self.params}

    def params_of(self, cfg: ControllerConfig) -> dict[str, float] | None:
        """A controller's searched parameters, clipped into the ranges, for an enqueued trial.

        The motion filter's Q keeps the controller's Q/R (its gains) under this space's R; a
        θ̂3(0) outside its range is clipped like any other. None when the controller is not
        of the variant this space searches.
        """
        darc = "gains.k1" in self.names
        if cfg.variant != ("modified_darc" if darc else "pid"):
            return None
        values = params_from_controller(cfg)
        values["kalman.motion.Q"] *= self.R_motion / cfg.kalman.motion.R
        return {p.name: p.clip(values[p.name]) for p in self.params}

    def signature(self) -> list[list[Any]]:
        """Plain data identifying the space (stored with a study, checked on resume)."""
        return [[p.name, p.low, p.high, p.log] for p in self.params]

    def at_ends(self, params: Mapping[str, float],
                share: float = RANGE_END_SHARE) -> list[tuple[str, str]]:
        """The parameters of ``params`` within ``share`` of their range's span (on the
        parameter's scale, log or linear) from one of its ends: ``(name, "low" | "high")``.

        A kept trial with a parameter there may have wanted a value outside the range: report.md
        says so, and on the fleet's studies it was how too narrow a range showed (the motion
        filter's Q, :data:`MOTION_Q_OVER_R`).
        """
        out = []
        for p in self.params:
            if p.name not in params:
                continue
            f = math.log if p.log else float
            pos = (f(params[p.name]) - f(p.low)) / (f(p.high) - f(p.low))
            if pos <= share:
                out.append((p.name, "low"))
            elif pos >= 1.0 - share:
                out.append((p.name, "high"))
        return out


#: Variants ``tune`` can search: the paper's modified DARC, and the PID baseline (on the same
#: valve logic and PWM inverse) so that the comparison with DARC is made on equal terms.
VARIANTS: tuple[str, ...] = ("modified_darc", "pid")


def search_space(model: ModelConfig, variant: str = "modified_darc") -> SearchSpace:
    """The search space for ``model``.

    Parameters
    ----------
    model : ModelConfig
        The identified model (its sensor noise sets the motion filter's R and Q range).
    variant : {"modified_darc", "pid"}
        What is tuned. ``pid``: the gains of the ``pid`` block (Q_Ld = -(kp e1 + ki ∫e1 +
        kd (v̂ - v_r))) and the motion filter's Q, which gives v̂; the first trial is
        contract 4's default PID (ki at its range's low end).

    Returns
    -------
    SearchSpace
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    r_m = motion_R(model)
    r_f = PAPER_FORCE_R
    q_lo, q_hi = MOTION_Q_OVER_R  # Q/R [1/s^4]; the module docstring says why these ends
    motion_q = ParamSpec("kalman.motion.Q", q_lo * r_m, q_hi * r_m, True, "m^2/s^4",
                         PAPER_Q_OVER_R * r_m)
    if variant == "pid":
        pid = PidConfig()
        params = [
            ParamSpec("pid.kp", 1.0e5, 1.0e9, True, "N/(s m)", pid.kp),
            ParamSpec("pid.ki", 1.0e5, 1.0e11, True, "N/(s^2 m)", pid.ki),
            ParamSpec("pid.kd", 1.0e3, 1.0e7, True, "N/m", pid.kd),
            ParamSpec("pid.i_max", 1.0e-5, 1.0e-2, True, "m s", pid.i_max),
            motion_q,
        ]
        return SearchSpace(tuple(params), r_m, r_f)
    gamma_paper = (0.2, 300.0, 2000.0, 500.0, 100.0, 100.0)
    gamma_range = ((0.005, 20.0), (3.0, 3.0e4), (20.0, 2.0e5), (5.0, 5.0e4), (1.0, 1.0e4),
                   (1.0, 1.0e4))
    params = [
        ParamSpec("gains.k1", 10.0, 400.0, True, "1/s", 65.0),
        ParamSpec("gains.k2", 300.0, 1.0e5, True, "N s/m", 6700.0),
        ParamSpec("gains.k3", 2.0, 1000.0, True, "1/s", 50.0),
        ParamSpec("gains.h2", 0.5, 100.0, True, "N", 10.0),
        ParamSpec("gains.h3", 5.0, 2000.0, True, "N/s", 100.0),
        ParamSpec("gains.r3", 0.01, 10.0, True, "-", 0.1),
    ]
    for name, (lo, hi), paper, unit in zip(THETA_NAMES, gamma_range, gamma_paper, _GAMMA_UNITS,
                                           strict=True):
        params.append(ParamSpec(f"adaptation.gamma.{name}", lo, hi, True, unit, paper))
    if searches_theta_0(model):
        b_v0 = _b_v_start(model)
        params.append(ParamSpec(THETA_0_PARAM, b_v0, THETA_0_B_V_SPAN * b_v0, True,
                                "N s/m", b_v0))
    params.append(motion_q)
    # Q/R of the force filter over 1e4..1e10 1/s^4: bandwidth ~ (Q/R)^(1/4), 10..316 rad/s.
    params.append(ParamSpec("kalman.force.Q", 1.0e4 * r_f, 1.0e10 * r_f, True, "N^2/s^4",
                            PAPER_Q_OVER_R * r_f))
    return SearchSpace(tuple(params), r_m, r_f)


def searches_theta_0(model: ModelConfig) -> bool:
    """Whether θ̂3(0) is searched on ``model``: some valve's b is weakly identified.

    That is a b range wider than :data:`~pneutune.control.constants.WEAK_B_SPAN`, what identify
    gives a valve that a closed-loop log never holds fully open (widened to at least ±0.12).
    There the plant draws reach flows the nominal model does not, and no gains beat the paper's
    controller without a larger start (fleet plant 1, kind e). On the fleet's identification and
    commissioning runs (b ranges 0.03-0.19 wide) searching it bought nothing and cost 5 of 24
    rows their win over the paper's gains (docs/tuning.md, "θ̂3(0)").

    Parameters
    ----------
    model : ModelConfig
        The identified model.

    Returns
    -------
    bool
    """
    return any(v.b_max - v.b_min > WEAK_B_SPAN for v in model.valves.ordered())


def _b_v_start(model: ModelConfig) -> float:
    """Low end of the θ̂3(0) range: the model's nominal θ3, or the top of its box where the
    nominal is not positive (a log range needs a positive start) [N s/m]."""
    b_v0 = model.theta.nominal[THETA_B_V]
    return b_v0 if b_v0 > 0.0 else max(model.theta.max[THETA_B_V], 1.0)


def variant_of(params: Mapping[str, float]) -> str:
    """The variant a parameter set belongs to (``pid`` if it has ``pid.*`` keys)."""
    return "pid" if any(k.startswith("pid.") for k in params) else "modified_darc"


def _inside(lo: float, value: float, hi: float) -> float:
    """``value`` moved strictly inside (lo, hi) if it sits on a bound (θ_0 must be interior)."""
    pad = 1e-6 * (hi - lo)
    return min(hi - pad, max(lo + pad, value))


def controller_dict(model: ModelConfig, params: Mapping[str, float],
                    provenance: Mapping[str, Any] | None = None,
                    dead_zone: str = "up") -> dict[str, Any]:
    """The controller.yaml data for ``params`` on ``model`` (not yet validated).

    The rig, the valves' C and b (for the fully-open flows of Eq. 32), the PWM curve and the θ box
    come from the model; θ_0 is the model's nominal θ (moved inside the box by 1e-6 of its span if
    it sits on a bound); limits are the stroke and the supply + 0.5 bar. A ``pid`` parameter set
    (:func:`variant_of`) keeps the paper's DARC gains, unused, and the paper's force filter.

    Parameters
    ----------
    model : ModelConfig
        The identified model.
    params : mapping
        A value for every name of :func:`search_space`.
    provenance : mapping, optional
        The ``provenance`` block.
    dead_zone : str
        The controller's ``dead_zone`` (``up`` or ``dither``; ``tune --dead-zone``).

    Returns
    -------
    dict
    """
    variant = variant_of(params)
    space = search_space(model, variant)
    missing = [n for n in space.names if n not in params]
    if missing:
        raise KeyError(f"parameters missing: {missing}")
    th = model.theta
    nominal, theta_max = list(th.nominal), list(th.max)
    if THETA_0_PARAM in params:
        nominal[THETA_B_V] = params[THETA_0_PARAM]
        # the box's top moves up with the start, in proportion (unchanged at the nominal)
        theta_max[THETA_B_V] = max(theta_max[THETA_B_V], nominal[THETA_B_V]
                                   * th.max[THETA_B_V] / _b_v_start(model))
    theta_0 = [_inside(lo, v, hi) for lo, v, hi in zip(th.min, nominal, theta_max, strict=True)]
    rig = model.rig
    if variant == "pid":  # the DARC blocks are required by contract 4 but unused: the paper's
        darc = search_space(model).paper_params()
        params = {**darc, **params, "kalman.force.Q": darc["kalman.force.Q"]}
    data: dict[str, Any] = {
        "schema": CONTROLLER_SCHEMA,
        "variant": variant,
        "position_feedback": "measured",
        "dead_zone": dead_zone,
        "rig": rig.model_dump(),
        "valves": {name: {"C": v.C, "b": v.b,
                          **({"pwm": {"duty": list(v.pwm.duty), "ratio": list(v.pwm.ratio)}}
                             if v.pwm is not None else {})}
                   for name, v in zip(("a_in", "a_out", "b_in", "b_out"),
                                      model.valves.ordered(), strict=True)},
        "pwm": {"duty": list(model.pwm.duty), "ratio": list(model.pwm.ratio)},
        "gains": {"k1": params["gains.k1"], "k2": params["gains.k2"], "k3": params["gains.k3"],
                  "r2": PAPER_R2, "r3": params["gains.r3"], "eps2": PAPER_EPS2,
                  "eps3": PAPER_EPS3, "h2": params["gains.h2"], "h3": params["gains.h3"]},
        "adaptation": {
            "gamma": [params[f"adaptation.gamma.{n}"] for n in THETA_NAMES],
            "rate_max": list(PAPER_RATE_MAX),
            "theta_min": list(th.min), "theta_max": theta_max, "theta_0": theta_0,
            "min_ref_speed": PAPER_MIN_REF_SPEED,
        },
        "kalman": {"motion": {"Q": params["kalman.motion.Q"], "R": space.R_motion},
                   "force": {"Q": params["kalman.force.Q"], "R": space.R_force}},
        "limits": {"x_min": rig.x_min, "x_max": rig.x_max, "p_max": rig.p_s + P_MAX_MARGIN,
                   "sensor_timeout_s": SENSOR_TIMEOUT_S},
    }
    if variant == "pid":
        data["pid"] = {k: params[f"pid.{k}"] for k in ("kp", "ki", "kd", "i_max")}
    if provenance is not None:
        data["provenance"] = dict(provenance)
    return data


def controller_from_params(model: ModelConfig, params: Mapping[str, float],
                           provenance: Mapping[str, Any] | None = None,
                           dead_zone: str = "up") -> ControllerConfig:
    """A validated :class:`ControllerConfig` for ``params`` on ``model`` (see
    :func:`controller_dict`).

    Raises
    ------
    ConfigError
        A value outside contract 4's ranges (e.g. a model whose θ box is degenerate).
    """
    clean = {k: float(v) for k, v in params.items()}
    if not all(math.isfinite(v) for v in clean.values()):
        raise ValueError(f"parameters must be finite, got {clean}")
    return validate_model(ControllerConfig, controller_dict(model, clean, provenance, dead_zone),
                          "<tune>")


def params_from_controller(cfg: ControllerConfig) -> dict[str, float]:
    """The searched parameters of a controller (inverse of :func:`controller_from_params`)."""
    if cfg.variant == "pid":
        p = cfg.pid
        return {"pid.kp": p.kp, "pid.ki": p.ki, "pid.kd": p.kd, "pid.i_max": p.i_max,
                "kalman.motion.Q": cfg.kalman.motion.Q}
    g = cfg.gains
    out = {"gains.k1": g.k1, "gains.k2": g.k2, "gains.k3": g.k3, "gains.h2": g.h2,
           "gains.h3": g.h3, "gains.r3": g.r3}
    for name, value in zip(THETA_NAMES, cfg.adaptation.gamma, strict=True):
        out[f"adaptation.gamma.{name}"] = value
    out[THETA_0_PARAM] = cfg.adaptation.theta_0[THETA_B_V]
    out["kalman.motion.Q"] = cfg.kalman.motion.Q
    out["kalman.force.Q"] = cfg.kalman.force.Q
    return out


__all__ = ["MOTION_Q_OVER_R", "RANGE_END_SHARE", "VARIANTS", "ParamSpec", "SearchSpace",
           "controller_dict", "controller_from_params", "motion_R", "params_from_controller",
           "search_space", "searches_theta_0", "variant_of"]
