"""controller.yaml (contract 4, ``pneutune.controller/1``): what ``tune`` writes, ``deploy`` loads.

Strict pydantic models (unknown keys rejected, no type coercion, ranges, θ_min < θ_0 < θ_max,
vector lengths, a monotone PWM curve); :func:`load_controller` turns any failure into one
:class:`~pneutune.control.errors.ConfigError` naming the key path and the rule.
A controller.yaml is complete: there is no merge over defaults, except for the keys this project
adds to contract 4 (``position_feedback``, ``dead_zone``, ``pid``), which have documented
defaults.

The flat vector the compiled step reads is the law's business: :mod:`pneutune.control.law.layout`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from pneutune.control.constants import CONTROLLER_SCHEMA, THETA_NAMES, VALVES
from pneutune.control.contracts.plant import RigConfig
from pneutune.control.contracts.yamlio import load_config, write_yaml

#: Controller variants, in the order of their integer codes (``cfg[CFG_VARIANT]``).
VARIANTS: tuple[str, ...] = ("modified_darc", "original_darc", "direct_diff", "pid")
VARIANT_MODIFIED_DARC, VARIANT_ORIGINAL_DARC, VARIANT_DIRECT_DIFF, VARIANT_PID = 0, 1, 2, 3
#: Which position enters e1 (``cfg[CFG_POS_FB]``).
POSITION_FEEDBACK: tuple[str, ...] = ("measured", "filtered")
POS_FB_MEASURED, POS_FB_FILTERED = 0, 1
#: Which dx2/dt enters the calculable dF_pd/dt of original_darc (``cfg[CFG_ORIG_ACCEL]``).
ORIGINAL_DARC_ACCEL: tuple[str, ...] = ("filtered", "model")
ORIG_ACCEL_FILTERED, ORIG_ACCEL_MODEL = 0, 1
#: How a wanted opening inside the PWM curve's dead zone is commanded (``cfg[CFG_DZ_MODE]``).
DEAD_ZONE_MODES: tuple[str, ...] = ("up", "dither")
DZ_UP, DZ_DITHER = 0, 1
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


class PwmCurve(_Strict):
    """Effective open fraction (``ratio``) versus commanded duty (``duty``) of the valves.

    Piecewise linear between the points; both sequences non-decreasing, in [0, 1], starting at
    (0, 0). Two points with the same duty make a vertical step (the dead-zone jump). The
    controller inverts it (:func:`pneutune.control.law.duty.pwm_inverse`).
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

    @property
    def top_duty(self) -> float:
        """The smallest duty at which the curve reaches its largest ratio: any duty from here to
        1 is a full opening by the curve (Eq. 33's sat = 1 commands 1,
        :func:`pneutune.control.law.duty.pwm_inverse`)."""
        top = self.ratio[-1]
        return next(d for d, r in zip(self.duty, self.ratio, strict=True) if r >= top)


class ControllerValve(_Strict):
    """ISO 6358 constants of one valve (Eq. 7), for the fully-open flows of Eq. (32)."""

    C: float = Field(gt=0.0, le=1.0e-6, description="Sonic conductance [m^3/(s Pa)]")
    b: float = Field(ge=0.0, le=0.95, description="Critical pressure ratio [-]")
    pwm: PwmCurve | None = Field(
        None, description="Added by pneutune: this valve's own PWM curve (its delays and "
        "minimum pulse differ from the others'); absent: the top-level pwm, shared by the four")


class ControllerValves(_Strict):
    """The four valves, in the order a_in, a_out, b_in, b_out."""

    a_in: ControllerValve
    a_out: ControllerValve
    b_in: ControllerValve
    b_out: ControllerValve

    def ordered(self) -> tuple[ControllerValve, ...]:
        """The valves in the contract order (:data:`~pneutune.control.constants.VALVES`)."""
        return tuple(getattr(self, name) for name in VALVES)

    def curves(self, shared: PwmCurve) -> tuple[PwmCurve, ...]:
        """Each valve's PWM curve in the contract order: its own, else ``shared``."""
        return tuple(v.pwm if v.pwm is not None else shared for v in self.ordered())


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
        "filter's a posteriori estimate). The paper does not say (docs/controller.md).")
    original_darc_accel: Literal["filtered", "model"] = Field(
        "filtered", description="Added by pneutune: the dx2/dt in the calculable dF_pd/dt of "
        "original_darc (docs/original_darc.md): 'filtered' (the motion Kalman filter's "
        "acceleration) or 'model' ((F_p + θ̂2 - θ̂3 x2 - θ̂4 S_f(x2))/θ̂1). Unused by other "
        "variants.")
    dead_zone: Literal["up", "dither"] = Field(
        "up", description="Added by pneutune: how a wanted open fraction below the PWM curve's "
        "dead-zone knee (the top of its steep rise at the minimum pulse) is commanded: 'up' (the "
        "curve's inverse, at least the smallest pulse that opens the valve, every PWM period) or "
        "'dither' (whole smallest pulses in some PWM periods and none in the others, so that "
        "their mean over periods is the wanted fraction: a first-order sigma-delta, "
        "control/law/duty.py, docs/tuning.md)")
    rig: RigConfig
    valves: ControllerValves
    pwm: PwmCurve = Field(description="The valves' PWM curve; a valve with a curve of its own "
                          "(valves.<v>.pwm, added by pneutune) uses that instead")
    gains: GainsConfig
    adaptation: AdaptationConfig
    kalman: KalmanConfig
    pid: PidConfig = Field(PidConfig(), description="Added by pneutune: gains of the pid variant")
    limits: LimitsConfig
    provenance: ProvenanceConfig | None = None

    @model_validator(mode="after")
    def _check_limits(self) -> ControllerConfig:
        # a chamber at rest holds ambient pressure: a p_max at or below it trips the
        # supervisor's overpressure fault at the first sample, whatever the rig does
        if not self.limits.p_max > self.rig.p0:
            raise ValueError(f"limits.p_max > rig.p0 must hold (a chamber at rest is at ambient "
                             f"pressure), got p_max={self.limits.p_max}, p0={self.rig.p0}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form, as written to controller.yaml (tuples as lists; a valve without a
        curve of its own has no ``pwm`` key)."""
        out = self.model_dump(by_alias=True, mode="json")
        for name in VALVES:
            if out["valves"][name].get("pwm") is None:
                out["valves"][name].pop("pwm", None)
        return out

    @property
    def valve_curves(self) -> tuple[PwmCurve, ...]:
        """The PWM curve each valve's duty is inverted on, in the contract order
        (``valves.<v>.pwm``, else the top-level ``pwm``)."""
        return self.valves.curves(self.pwm)

    @property
    def top_duties(self) -> tuple[float, ...]:
        """Per valve, the smallest duty of a full opening by its curve
        (:attr:`PwmCurve.top_duty`)."""
        return tuple(c.top_duty for c in self.valve_curves)

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


#: The paper's Sec. 5.1 controller as a contract-4 file, shipped with the package (a checkout's
#: data/controller-paper.yaml links to it).
PAPER_CONTROLLER: Path = Path(__file__).resolve().parent / "data" / "controller-paper.yaml"
