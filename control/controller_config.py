"""controller.yaml (contract 4, ``pneutune.controller/1``): what ``tune`` writes, ``deploy`` loads.

Strict pydantic models (unknown keys rejected, no type coercion, ranges, θ_min < θ_0 < θ_max,
vector lengths, a monotone PWM curve); :func:`load_controller` turns any failure into one
:class:`~pneutune.control.errors.ConfigError` naming the key path and the rule.
A controller.yaml is complete: there is no merge over defaults, except for the keys this project
adds to contract 4 (``position_feedback``, ``pid``), which have documented defaults.

:func:`pack` flattens a config into the float64 vector that the compiled step
(:func:`pneutune.control.darc.step`) reads, at the module-level ``CFG_*`` indices below.
Derived slots (Kalman matrices of Eq. 34, nR, A_r) are computed here once, not per step.

Numba note: the compiled step freezes these indices at compile time, and numba's on-disk cache
does not notice a change of this module. :data:`CFG_LAYOUT_ID` is stored in the vector and checked
by the step (a mismatch closes every valve and sets the state's status); clear ``__pycache__``
after editing the layout.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from .constants import CONTROLLER_SCHEMA, THETA_NAMES, VALVES
from .kalman import force_model, motion_model, process_cov
from .plant_config import RigConfig
from .yamlio import load_config, write_yaml

#: Controller variants, in the order of their integer codes (``cfg[CFG_VARIANT]``).
VARIANTS: tuple[str, ...] = ("modified_darc", "original_darc", "direct_diff", "pid")
VARIANT_MODIFIED_DARC, VARIANT_ORIGINAL_DARC, VARIANT_DIRECT_DIFF, VARIANT_PID = 0, 1, 2, 3
#: Which position enters e1 (``cfg[CFG_POS_FB]``).
POSITION_FEEDBACK: tuple[str, ...] = ("measured", "filtered")
POS_FB_MEASURED, POS_FB_FILTERED = 0, 1
#: Which dx2/dt enters the calculable dF_pd/dt of original_darc (``cfg[CFG_ORIG_ACCEL]``).
ORIGINAL_DARC_ACCEL: tuple[str, ...] = ("filtered", "model")
ORIG_ACCEL_FILTERED, ORIG_ACCEL_MODEL = 0, 1
#: Largest number of points of the PWM curve.
PWM_MAX_POINTS: int = 128


class _Strict(BaseModel):
    """Frozen, strict (no coercion; an int is accepted for a float), finite, no unknown keys."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _vector6(value: Any) -> Any:
    if isinstance(value, list):
        value = tuple(value)
    if isinstance(value, tuple) and len(value) != 6:
        raise ValueError(f"expected 6 values, one per θ = [{', '.join(THETA_NAMES)}], "
                         f"got {len(value)}")
    return value


def _list_to_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


_F = Annotated[float, Field(allow_inf_nan=False)]
_NonNeg = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
_Pos = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
_Unit = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
Vec6 = Annotated[tuple[_F, _F, _F, _F, _F, _F], BeforeValidator(_vector6)]
Vec6NonNeg = Annotated[tuple[_NonNeg, _NonNeg, _NonNeg, _NonNeg, _NonNeg, _NonNeg],
                       BeforeValidator(_vector6)]
Vec6Pos = Annotated[tuple[_Pos, _Pos, _Pos, _Pos, _Pos, _Pos], BeforeValidator(_vector6)]


class ControllerValve(_Strict):
    """ISO 6358 constants of one valve (Eq. 7), for the fully-open flows of Eq. (32)."""

    C: float = Field(gt=0.0, le=1.0e-6, description="Sonic conductance [m^3/(s Pa)]")
    b: float = Field(ge=0.0, le=0.95, description="Critical pressure ratio [-]")


class ControllerValves(_Strict):
    """The four valves, in the order a_in, a_out, b_in, b_out."""

    a_in: ControllerValve
    a_out: ControllerValve
    b_in: ControllerValve
    b_out: ControllerValve

    def ordered(self) -> tuple[ControllerValve, ...]:
        """The valves in the contract order (:data:`~pneutune.control.constants.VALVES`)."""
        return tuple(getattr(self, name) for name in VALVES)


class PwmCurve(_Strict):
    """Effective open fraction (``ratio``) versus commanded duty (``duty``) of the valves.

    Piecewise linear between the points; both sequences non-decreasing, in [0, 1], starting at
    (0, 0). Two points with the same duty make a vertical step (the dead-zone jump). The
    controller inverts it (:func:`pneutune.control.duty.pwm_inverse`).
    """

    duty: Annotated[tuple[_Unit, ...], BeforeValidator(_list_to_tuple)] = Field(
        min_length=2, max_length=PWM_MAX_POINTS, description="Commanded duty, 0..1")
    ratio: Annotated[tuple[_Unit, ...], BeforeValidator(_list_to_tuple)] = Field(
        min_length=2, max_length=PWM_MAX_POINTS, description="Effective open fraction, 0..1")

    @model_validator(mode="after")
    def _check(self) -> PwmCurve:
        d, r = self.duty, self.ratio
        if len(d) != len(r):
            raise ValueError(f"duty and ratio must have the same length, got {len(d)} and {len(r)}")
        if d[0] != 0.0 or r[0] != 0.0:
            raise ValueError(f"the curve must start at (duty, ratio) = (0, 0), "
                             f"got ({d[0]}, {r[0]})")
        for name, seq in (("duty", d), ("ratio", r)):
            for i in range(1, len(seq)):
                if seq[i] < seq[i - 1]:
                    raise ValueError(f"{name} must be non-decreasing, but {name}[{i}] = {seq[i]} "
                                     f"< {name}[{i - 1}] = {seq[i - 1]}")
        if not r[-1] > 0.0:
            raise ValueError(f"ratio must reach a value > 0 (the valves must open), got {r[-1]}")
        return self


class GainsConfig(_Strict):
    """Backstepping gains of Eqs. (13), (17), (20), (24), (26), (29)."""

    k1: float = Field(gt=0.0, le=1.0e4, description="e2 = de1/dt + k1 e1, Eq. (13) [1/s]")
    k2: float = Field(gt=0.0, le=1.0e8, description="F_pds1 = -k2 e2, Eq. (17) [N s/m]")
    k3: float = Field(gt=0.0, le=1.0e6, description="Q_Lds1 = -k3 e3, Eq. (26) [1/s]")
    r2: float = Field(gt=0.0, le=1.0e6, description="Weight of V2, Eq. (15) [-]")
    r3: float = Field(gt=0.0, le=1.0e6,
                      description="Weight of e3 in V3, Eq. (24) [(m/s)^2/N^2 relative to r2]")
    eps2: float = Field(gt=0.0, le=1.0e9, description="Boundary layer of Eq. (20) [N m/s]")
    eps3: float = Field(gt=0.0, le=1.0e12, description="Boundary layer of Eq. (29) [N^2/s]")
    h2: float = Field(ge=0.0, le=1.0e9,
                      description="Constant bound of Eq. (20): F_pds2 = -h2^2 e2/(4 eps2) [N]")
    h3: float = Field(ge=0.0, le=1.0e12,
                      description="Constant bound of Eq. (29): Q_Lds2 = -h3^2 e3/(4 eps3) [N/s]")


class AdaptationConfig(_Strict):
    """Rate-limited projection adaptation, Eqs. (9)-(11); θ = [M, F_n, b_v, A_f, D_an, D_bn]
    in kg, N, N s/m, N, Pa/s, Pa/s."""

    gamma: Vec6NonNeg = Field(description="Diagonal of Γ, Eq. (9); 0 freezes θ_i "
                              "[units of θ_i^2 per (s * unit of τ_i)]")
    rate_max: Vec6Pos = Field(description="Rate limit θ̇_M, Eq. (11) [units of θ_i per s]")
    theta_min: Vec6 = Field(description="Lower bound of Ω_θ (Assumption 1)")
    theta_max: Vec6 = Field(description="Upper bound of Ω_θ (Assumption 1)")
    theta_0: Vec6 = Field(description="Initial estimate θ̂(0), strictly inside Ω_θ")
    min_ref_speed: float = Field(ge=0.0, le=1.0, description="θ̂ adapts only while |v_r| > "
                                 "min_ref_speed (Sec. 5.3) [m/s]")

    @model_validator(mode="after")
    def _check(self) -> AdaptationConfig:
        for i, name in enumerate(THETA_NAMES):
            lo, th0, hi = self.theta_min[i], self.theta_0[i], self.theta_max[i]
            if not lo < th0 < hi:
                raise ValueError(f"theta_min < theta_0 < theta_max must hold elementwise, but for "
                                 f"{name} (index {i}) got theta_min={lo}, theta_0={th0}, "
                                 f"theta_max={hi}")
        if not self.theta_min[0] > 0.0:
            raise ValueError(f"theta_min[0] (M, the mass) must be > 0 kg, "
                             f"got {self.theta_min[0]}")
        return self


class KalmanFilterConfig(_Strict):
    """Noise variances of one Sec. 4 filter (Eq. 34)."""

    Q: float = Field(gt=0.0, le=1.0e15, description="Process-noise variance: motion filter "
                     "[m^2/s^4] (w is an acceleration), force filter [N^2/s^4]")
    R: float = Field(gt=0.0, le=1.0e15, description="Measurement-noise variance: motion filter "
                     "[m^2] (position), force filter [N^2] (F_pd)")


class KalmanConfig(_Strict):
    """The two filters of Sec. 4: motion (x, v, a) and force (F_pd, dF_pd/dt)."""

    motion: KalmanFilterConfig
    force: KalmanFilterConfig


class LimitsConfig(_Strict):
    """Safety limits for the runtime supervisor (not used by the control law itself)."""

    x_min: float = Field(ge=-1.0, le=2.0, description="Lowest allowed position [m]")
    x_max: float = Field(ge=-1.0, le=2.0, description="Highest allowed position [m]")
    p_max: float = Field(gt=0.0, le=2.0e6, description="Highest allowed chamber pressure [Pa abs]")
    sensor_timeout_s: float = Field(gt=0.0, le=10.0, description="Longest sensor silence [s]")

    @model_validator(mode="after")
    def _check(self) -> LimitsConfig:
        if not self.x_max > self.x_min:
            raise ValueError(f"x_max > x_min must hold, got x_min={self.x_min}, x_max={self.x_max}")
        return self


class PidConfig(_Strict):
    """Gains of the ``pid`` variant (added to contract 4 by this project).

    Q_Ld = -(kp e1 + ki ∫e1 dt + kd (v̂ - v_r)), then the valve logic of Eqs. (32)-(33) and the PWM
    inverse, as in the DARC variants. The integral is clamped to ±i_max.
    """

    kp: float = Field(3.0e6, ge=0.0, le=1.0e12, description="Proportional gain [N/(s m)]")
    ki: float = Field(0.0, ge=0.0, le=1.0e14, description="Integral gain [N/(s^2 m)]")
    kd: float = Field(2.0e5, ge=0.0, le=1.0e10, description="Derivative gain [N/m]")
    i_max: float = Field(1.0e-3, ge=0.0, le=1.0, description="Clamp of the integral of e1 [m s]")


def _list_to_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


class ProvenanceConfig(_Strict):
    """Where a tuned config came from (all optional)."""

    model_sha256: str | None = Field(None, description="sha256 of the model.yaml tuned on")
    study: str | None = Field(None, description="Optuna study name")
    trial: int | None = Field(None, ge=0, description="Optuna trial number")
    objective: float | None = Field(None, description="Objective value of that trial")
    created: str | None = Field(None, description="ISO 8601 creation time")
    version: str | None = Field(None, description="pneutune version that wrote the file")
    seed: int | None = Field(None, ge=0, description="Added by pneutune: seed of the tune study "
                             "(plant draws, sensor noise, samplers)")
    notes: Annotated[tuple[str, ...] | None, BeforeValidator(_list_to_tuple)] = Field(
        None, description="Added by pneutune: what tune had to assume or change, e.g. ranges of "
        "the model narrowed because no controller tracked plants at their ends")


class ControllerConfig(_Strict):
    """The whole controller.yaml document (contract 4)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False,
                              populate_by_name=True)

    schema_: Literal["pneutune.controller/1"] = Field(CONTROLLER_SCHEMA, alias="schema")
    variant: Literal["modified_darc", "original_darc", "direct_diff", "pid"] = Field(
        description="Control law: modified_darc (Eqs. 9-36, dF_pd from the force Kalman filter), "
        "original_darc (dF_pd from its calculable part, docs/original_darc.md), direct_diff "
        "(dF_pd by backward difference, the paper's Fig. 11), pid (position PID on the same "
        "valve logic)")
    position_feedback: Literal["measured", "filtered"] = Field(
        "measured", description="Added by pneutune: the position entering e1 = x - x_r and the "
        "chamber volumes: 'measured' (the sensor sample) or 'filtered' (the motion Kalman "
        "filter's a posteriori estimate). The paper does not say (DESIGN.md).")
    original_darc_accel: Literal["filtered", "model"] = Field(
        "filtered", description="Added by pneutune: the dx2/dt in the calculable dF_pd/dt of "
        "original_darc (docs/original_darc.md): 'filtered' (the motion Kalman filter's "
        "acceleration) or 'model' ((F_p + θ̂2 - θ̂3 x2 - θ̂4 S_f(x2))/θ̂1). Unused by other "
        "variants.")
    rig: RigConfig
    valves: ControllerValves
    pwm: PwmCurve
    gains: GainsConfig
    adaptation: AdaptationConfig
    kalman: KalmanConfig
    pid: PidConfig = Field(PidConfig(), description="Added by pneutune: gains of the pid variant")
    limits: LimitsConfig
    provenance: ProvenanceConfig | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form, as written to controller.yaml (tuples as lists)."""
        return self.model_dump(by_alias=True, mode="json")

    @property
    def variant_code(self) -> int:
        """Integer code of :attr:`variant` (index in :data:`VARIANTS`)."""
        return VARIANTS.index(self.variant)


def load_controller(path: str | os.PathLike[str]) -> ControllerConfig:
    """Load and validate a controller.yaml.

    Parameters
    ----------
    path : path-like
        The file.

    Returns
    -------
    ControllerConfig

    Raises
    ------
    ConfigError
        Bad YAML, unknown or missing key, wrong type (including ``6.0e5`` read as a string),
        out-of-range value, inconsistent bounds or PWM curve; names the file and key path.
    """
    return load_config(path, ControllerConfig, CONTROLLER_SCHEMA)


def save_controller(cfg: ControllerConfig, path: str | os.PathLike[str],
                    header: str = "") -> None:
    """Write ``cfg`` to ``path`` atomically (it loads back equal: :func:`load_controller`).

    Parameters
    ----------
    cfg : ControllerConfig
        The config.
    path : path-like
        Destination.
    header : str
        Optional comment lines written at the top.
    """
    write_yaml(path, cfg.to_dict(), header=header)


# ---------------------------------------------------------------------------------------------
# JSON Schema
# ---------------------------------------------------------------------------------------------

#: The committed JSON Schema of contract 4.
SCHEMA_PATH: Path = Path(__file__).resolve().parent / "schemas" / "controller.schema.json"


def controller_json_schema() -> dict[str, Any]:
    """The JSON Schema of controller.yaml (:func:`pneutune.control.json_schemas.json_schema`)."""
    from .json_schemas import json_schema

    return json_schema("controller")


def schema_text() -> str:
    """The schema as the committed file's text."""
    from .json_schemas import schema_text as text

    return text("controller")


def write_schema(path: str | os.PathLike[str] | None = None) -> Path:
    """Regenerate the committed schema file (``python -m pneutune.control.json_schemas``)."""
    from .atomic import atomic_write_text

    target = Path(path) if path is not None else SCHEMA_PATH
    atomic_write_text(target, schema_text())
    return target


# ---------------------------------------------------------------------------------------------
# Flat config vector read by the compiled step
# ---------------------------------------------------------------------------------------------

_next = 0


def _slot(size: int = 1) -> int:
    global _next
    index = _next
    _next += size
    return index


CFG_LAYOUT = _slot()       #: layout id written by pack, checked by the step
CFG_VARIANT = _slot()      #: variant code (VARIANTS)
CFG_POS_FB = _slot()       #: position feedback code (POSITION_FEEDBACK)
CFG_ORIG_ACCEL = _slot()   #: original_darc dx2/dt code (ORIGINAL_DARC_ACCEL)
CFG_TS = _slot()           #: rig.Ts [s]
CFG_A_A = _slot()          #: rig.A_a [m^2]
CFG_A_B = _slot()          #: rig.A_b [m^2]
CFG_A_R = _slot()          #: A_a - A_b [m^2]
CFG_X_MIN = _slot()        #: rig.x_min [m]
CFG_X_MAX = _slot()        #: rig.x_max [m]
CFG_V0A = _slot()          #: rig.V0a [m^3]
CFG_V0B = _slot()          #: rig.V0b [m^3]
CFG_P0 = _slot()           #: rig.p0 [Pa]
CFG_T0 = _slot()           #: rig.T0 [K]
CFG_N = _slot()            #: rig.n, polytropic exponent [-]
CFG_NR = _slot()           #: rig.n * rig.R [J/(kg K)]
CFG_VALVE_C = _slot(4)     #: C of a_in, a_out, b_in, b_out [m^3/(s Pa)]
CFG_VALVE_B = _slot(4)     #: b of a_in, a_out, b_in, b_out [-]
CFG_K1 = _slot()
CFG_K2 = _slot()
CFG_K3 = _slot()
CFG_R2 = _slot()
CFG_R3 = _slot()
CFG_EPS2 = _slot()
CFG_EPS3 = _slot()
CFG_H2 = _slot()
CFG_H3 = _slot()
CFG_GAMMA = _slot(6)
CFG_RATE_MAX = _slot(6)
CFG_THETA_MIN = _slot(6)
CFG_THETA_MAX = _slot(6)
CFG_THETA_0 = _slot(6)
CFG_MIN_REF_SPEED = _slot()
CFG_KM_Q = _slot()         #: motion filter Q [m^2/s^4]
CFG_KM_R = _slot()         #: motion filter R [m^2]
CFG_KF_Q = _slot()         #: force filter Q [N^2/s^4]
CFG_KF_R = _slot()         #: force filter R [N^2]
CFG_KM_A = _slot(9)        #: motion A_d (3x3 row-major), Eq. (34)
CFG_KM_WQW = _slot(9)      #: motion W_d Q W_d^T (3x3)
CFG_KM_H = _slot(3)        #: motion H_d
CFG_KF_A = _slot(4)        #: force A_d (2x2)
CFG_KF_WQW = _slot(4)      #: force W_d Q W_d^T (2x2)
CFG_KF_H = _slot(2)        #: force H_d
CFG_PID_KP = _slot()
CFG_PID_KI = _slot()
CFG_PID_KD = _slot()
CFG_PID_IMAX = _slot()
CFG_PWM_N = _slot()        #: number of PWM curve points m
CFG_PWM_DUTY = _slot(PWM_MAX_POINTS)   #: duty[:m]
CFG_PWM_RATIO = _slot(PWM_MAX_POINTS)  #: ratio[:m]
CFG_SIZE: int = _next
#: Identifies this layout; changes whenever a slot is added or moved.
CFG_LAYOUT_ID: float = float(1_000_000 + CFG_SIZE * 100 + CFG_PWM_DUTY % 100)


def pack(cfg: ControllerConfig) -> np.ndarray:
    """Flatten a config into the float64 vector read by the compiled step.

    Parameters
    ----------
    cfg : ControllerConfig
        A validated config.

    Returns
    -------
    (CFG_SIZE,) float64
        Values at the ``CFG_*`` indices of this module, SI units.
    """
    v = np.zeros(CFG_SIZE)
    rig = cfg.rig
    v[CFG_LAYOUT] = CFG_LAYOUT_ID
    v[CFG_VARIANT] = VARIANTS.index(cfg.variant)
    v[CFG_POS_FB] = POSITION_FEEDBACK.index(cfg.position_feedback)
    v[CFG_ORIG_ACCEL] = ORIGINAL_DARC_ACCEL.index(cfg.original_darc_accel)
    v[CFG_TS] = rig.Ts
    v[CFG_A_A], v[CFG_A_B], v[CFG_A_R] = rig.A_a, rig.A_b, rig.A_a - rig.A_b
    v[CFG_X_MIN], v[CFG_X_MAX] = rig.x_min, rig.x_max
    v[CFG_V0A], v[CFG_V0B] = rig.V0a, rig.V0b
    v[CFG_P0], v[CFG_T0], v[CFG_N], v[CFG_NR] = rig.p0, rig.T0, rig.n, rig.n * rig.R
    for i, valve in enumerate(cfg.valves.ordered()):
        v[CFG_VALVE_C + i] = valve.C
        v[CFG_VALVE_B + i] = valve.b
    g = cfg.gains
    v[CFG_K1], v[CFG_K2], v[CFG_K3] = g.k1, g.k2, g.k3
    v[CFG_R2], v[CFG_R3], v[CFG_EPS2], v[CFG_EPS3] = g.r2, g.r3, g.eps2, g.eps3
    v[CFG_H2], v[CFG_H3] = g.h2, g.h3
    a = cfg.adaptation
    v[CFG_GAMMA:CFG_GAMMA + 6] = a.gamma
    v[CFG_RATE_MAX:CFG_RATE_MAX + 6] = a.rate_max
    v[CFG_THETA_MIN:CFG_THETA_MIN + 6] = a.theta_min
    v[CFG_THETA_MAX:CFG_THETA_MAX + 6] = a.theta_max
    v[CFG_THETA_0:CFG_THETA_0 + 6] = a.theta_0
    v[CFG_MIN_REF_SPEED] = a.min_ref_speed
    k = cfg.kalman
    v[CFG_KM_Q], v[CFG_KM_R] = k.motion.Q, k.motion.R
    v[CFG_KF_Q], v[CFG_KF_R] = k.force.Q, k.force.R
    A, W, H = motion_model(rig.Ts)
    v[CFG_KM_A:CFG_KM_A + 9] = A.ravel()
    v[CFG_KM_WQW:CFG_KM_WQW + 9] = process_cov(W, k.motion.Q).ravel()
    v[CFG_KM_H:CFG_KM_H + 3] = H
    A, W, H = force_model(rig.Ts)
    v[CFG_KF_A:CFG_KF_A + 4] = A.ravel()
    v[CFG_KF_WQW:CFG_KF_WQW + 4] = process_cov(W, k.force.Q).ravel()
    v[CFG_KF_H:CFG_KF_H + 2] = H
    p = cfg.pid
    v[CFG_PID_KP], v[CFG_PID_KI], v[CFG_PID_KD], v[CFG_PID_IMAX] = p.kp, p.ki, p.kd, p.i_max
    m = len(cfg.pwm.duty)
    v[CFG_PWM_N] = m
    v[CFG_PWM_DUTY:CFG_PWM_DUTY + m] = cfg.pwm.duty
    v[CFG_PWM_RATIO:CFG_PWM_RATIO + m] = cfg.pwm.ratio
    return v


if __name__ == "__main__":  # pragma: no cover
    print(write_schema())
