"""model.yaml (contract 3, ``pneutune.model/1``): what ``identify`` writes and ``tune`` reads.

The contract's keys keep their names and meanings; pneutune adds (documented in the schema):

* per valve: ``C_min``/``C_max``, ``b_min``/``b_max`` (the range ``tune`` samples plants from)
  and the switching behaviour ``delay_on``, ``delay_off``, ``min_pulse`` it can simulate;
* ``friction.ranges``: [lo, hi] per Stribeck parameter;
* ``mass_range``, ``leak``, ``sensors`` (noise levels seen in the log), ``notes`` (what was not
  identifiable and why);
* ``effects``: real-rig effects (IO delay, sensor lags, valve armature lags) by their plant.yaml
  key, each a nominal value and the range tune's plant draws sample;
* ``source`` is the contract's mapping (log, sha256, duration_s) for a model identified from one
  log, and a list of such mappings, one per log, for a model fitted to several logs of one rig
  (``identify A.mcap B.mcap``); :attr:`ModelConfig.sources` reads either as a tuple;
* ``source.run`` (each log's): what the log's run record says of the run (:class:`LoggedRun`):
  whether it is a closed loop, its scenario, the controller that ran with its contract-4 content
  when identify found that file unchanged, and the log's measured tracking indices, so that tune
  compares the model's closed loop with the rig's from model.yaml alone.

θ = [M, F_n, b_v, A_f, D_an, D_bn] (the paper's order) in kg, N, N s/m, N, Pa/s, Pa/s.
"""

from __future__ import annotations

import os
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, WithJsonSchema, model_validator

from pneutune.control.constants import MODEL_SCHEMA, THETA_NAMES, VALVES
from pneutune.control.contracts.controller import ControllerConfig, PwmCurve
from pneutune.control.contracts.plant import RigConfig
from pneutune.control.contracts.yamlio import load_config, write_yaml


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _to_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def _vec6(value: Any) -> Any:
    value = _to_tuple(value)
    if isinstance(value, tuple) and len(value) != 6:
        raise ValueError(f"expected 6 values, one per θ = [{', '.join(THETA_NAMES)}], "
                         f"got {len(value)}")
    return value


Vec6 = Annotated[tuple[float, float, float, float, float, float], BeforeValidator(_vec6)]
Range = Annotated[tuple[float, float], BeforeValidator(_to_tuple)]


def _check_range(name: str, lo: float, value: float, hi: float) -> None:
    if not lo <= value <= hi:
        raise ValueError(f"{name}_min <= {name} <= {name}_max must hold, "
                         f"got {lo} <= {value} <= {hi}")


#: A controller.yaml document inside model.yaml: validated as contract 4, and in the exported
#: JSON Schema an object (controller.schema.json is its schema; its keys are not repeated).
LoggedController = Annotated[ControllerConfig, WithJsonSchema(
    {"type": "object", "description": "A controller.yaml document (pneutune.controller/1)"})]


class LoggedRun(_Strict):
    """Added: what a log's run record says of the run, as identify read it.

    ``controller_config`` holds the controller that ran when identify found its file unchanged
    since the run; otherwise ``controller_missing`` says why not (exactly one of the two is
    set). ``E_p_mm`` and ``E_rms_mm`` are the log's own tracking indices over its last three
    reference periods.
    """

    closed_loop: bool = Field(description="The log holds /control/state and "
                              "/control/reference (a closed loop that deploy or simulate "
                              "logged)")
    scenario: str | None = Field(None, description="The scenario the run record names")
    controller: str | None = Field(None, description="The controller file the run record "
                                   "names, as named there")
    controller_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$",
                                          description="The controller file's sha256 at the "
                                          "run, as the run record gives it")
    controller_config: LoggedController | None = Field(
        None, description="The contract-4 content of the controller that ran (a whole "
        "controller.yaml document, validated as one), when identify found its file (as named, "
        "from the working directory, else beside the log) unchanged since the run")
    controller_missing: str | None = Field(
        None, description="Why controller_config is absent (no controller named, file "
        "not found, changed since the run (sha256), does not load)")
    homing_fault: bool = Field(False, description="A fault stopped the homing move "
                               "before the scenario (run record homing: fault)")
    samples: int | None = Field(None, ge=0, description="Closed-loop samples at the "
                                "control rate (absent for an open-loop log)")
    E_p_mm: float | None = Field(None, ge=0.0, description="The log's max |x - x_r| over "
                                 "its last three reference periods [mm]; absent when the "
                                 "scenario is unknown, the homing move faulted or the log is "
                                 "shorter than that")
    E_rms_mm: float | None = Field(None, ge=0.0, description="The log's rms of x - x_r "
                                   "over the same window [mm]")

    @model_validator(mode="after")
    def _check(self) -> LoggedRun:
        if (self.controller_config is None) == (self.controller_missing is None):
            raise ValueError("exactly one of controller_config and controller_missing must be "
                             "given")
        if (self.E_p_mm is None) != (self.E_rms_mm is None):
            raise ValueError("E_p_mm and E_rms_mm must be given together")
        return self


class SourceInfo(_Strict):
    """A log the model came from."""

    log: str = Field(description="Path of the run log as given to identify")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="sha256 of the log file")
    duration_s: float = Field(ge=0.0, description="Duration of the log [s]")
    run: LoggedRun | None = Field(None, description="Added: what the log's run record says of "
                                  "the run (closed loop or not, scenario, the controller that "
                                  "ran, the measured tracking indices); absent: not recorded, "
                                  "and tune's log check asks for identify to be run again")


#: Added: the logs of a model fitted to several logs of one rig, one mapping per log (a model
#: of one log keeps the single mapping, so a list has two or more).
Sources = Annotated[tuple[SourceInfo, ...], Field(min_length=2), BeforeValidator(_to_tuple)]


class ModelValve(_Strict):
    """One valve: ISO 6358 (Eq. 7) with its range, and its switching behaviour."""

    C: float = Field(gt=0.0, le=1.0e-6, description="Sonic conductance [m^3/(s Pa)]")
    b: float = Field(ge=0.0, le=0.95, description="Critical pressure ratio [-]")
    C_min: float = Field(gt=0.0, le=1.0e-6, description="Added: lower end of C's range")
    C_max: float = Field(gt=0.0, le=1.0e-6, description="Added: upper end of C's range")
    b_min: float = Field(ge=0.0, le=0.95, description="Added: lower end of b's range")
    b_max: float = Field(ge=0.0, le=0.95, description="Added: upper end of b's range")
    delay_on: float = Field(0.0, ge=0.0, le=0.05, description="Added: command-on to open [s]")
    delay_off: float = Field(0.0, ge=0.0, le=0.05, description="Added: command-off to closed [s]")
    min_pulse: float = Field(0.0, ge=0.0, le=0.05,
                             description="Added: shortest command pulse that opens [s]")
    min_pulse_min: float | None = Field(
        None, ge=0.0, le=0.05, description="Added: lower end of the minimum pulses the log "
        "cannot tell from min_pulse [s], which tune draws from where it is wider than 0.1 ms; "
        "absent: not identified from the exact opening per sample")
    min_pulse_max: float | None = Field(
        None, ge=0.0, le=0.05, description="Added: upper end of that range [s]")
    pwm: PwmCurve | None = Field(None, description="Added: this valve's own PWM curve "
                                 "(absent: the top-level pwm, shared by the four)")

    @model_validator(mode="after")
    def _check(self) -> ModelValve:
        _check_range("C", self.C_min, self.C, self.C_max)
        _check_range("b", self.b_min, self.b, self.b_max)
        if self.min_pulse > self.delay_on:
            raise ValueError(f"min_pulse <= delay_on must hold, got min_pulse={self.min_pulse}, "
                             f"delay_on={self.delay_on}")
        if (self.min_pulse_min is None) != (self.min_pulse_max is None):
            raise ValueError("min_pulse_min and min_pulse_max must be given together")
        if self.min_pulse_min is not None and self.min_pulse_max is not None:
            _check_range("min_pulse", self.min_pulse_min, self.min_pulse, self.min_pulse_max)
        return self


class ModelValves(_Strict):
    """The four valves, in the order a_in, a_out, b_in, b_out."""

    a_in: ModelValve
    a_out: ModelValve
    b_in: ModelValve
    b_out: ModelValve

    def ordered(self) -> tuple[ModelValve, ...]:
        """The valves in the contract order."""
        return tuple(getattr(self, name) for name in VALVES)


class FrictionRanges(_Strict):
    """Added: [lo, hi] of each Stribeck parameter, for sampling plants."""

    F_S: Range
    F_C: Range
    v_s: Range
    alpha: Range
    b_v: Range


class ModelFriction(_Strict):
    """Stribeck friction of Eq. (2) and the smooth model of Eqs. (3)-(4)."""

    F_S: float = Field(ge=0.0, le=1.0e4, description="Stiction force [N]")
    F_C: float = Field(ge=0.0, le=1.0e4, description="Coulomb level [N]")
    v_s: float = Field(gt=0.0, le=1.0, description="Stribeck velocity [m/s]")
    alpha: float = Field(gt=0.0, le=10.0, description="Stribeck exponent [-]")
    b_v: float = Field(ge=0.0, le=1.0e5, description="Viscous coefficient [N s/m]")
    A_f: float = Field(ge=-1.0e4, le=1.0e4, description="Smooth-model amplitude, Eq. (3) [N]")
    ranges: FrictionRanges | None = Field(None, description="Added: ranges for sampling plants")

    @model_validator(mode="after")
    def _check(self) -> ModelFriction:
        if self.F_C > self.F_S:
            raise ValueError(f"F_C <= F_S must hold, got F_S={self.F_S}, F_C={self.F_C}")
        if self.ranges is not None:
            for name in ("F_S", "F_C", "v_s", "alpha", "b_v"):
                lo, hi = getattr(self.ranges, name)
                _check_range(f"ranges.{name}", lo, getattr(self, name), hi)
        return self


class ThetaBlock(_Strict):
    """θ nominal and its box [θ_min, θ_max], Assumption 1."""

    nominal: Vec6
    min: Vec6
    max: Vec6

    @model_validator(mode="after")
    def _check(self) -> ThetaBlock:
        for i, name in enumerate(THETA_NAMES):
            if not self.min[i] <= self.nominal[i] <= self.max[i]:
                raise ValueError(f"min <= nominal <= max must hold for {name} (θ{i + 1}), got "
                                 f"{self.min[i]} <= {self.nominal[i]} <= {self.max[i]}")
            if not self.min[i] < self.max[i]:
                raise ValueError(f"min < max must hold for {name} (θ{i + 1}), got "
                                 f"{self.min[i]} and {self.max[i]}")
        return self


class Uncertainty(_Strict):
    """Bounds of the fast-changing uncertain nonlinearities (Assumption 1)."""

    F_max: float = Field(ge=0.0, description="|F̃0| <= F_max [N]")
    D_a_max: float = Field(ge=0.0, description="|D̃a0| <= D_a_max [Pa/s]")
    D_b_max: float = Field(ge=0.0, description="|D̃b0| <= D_b_max [Pa/s]")


class FitBlock(_Strict):
    """Validation: the identified model simulated on a held-out part of the log."""

    nrmse_x: float = Field(ge=0.0, description="NRMSE of x (rms error / range) [-]")
    nrmse_p_a: float = Field(ge=0.0, description="NRMSE of p_a [-]")
    nrmse_p_b: float = Field(ge=0.0, description="NRMSE of p_b [-]")


class LeakBlock(_Strict):
    """Added: seal leak A<->B (ISO 6358 form, b = 0)."""

    C: float = Field(0.0, ge=0.0, le=1.0e-7, description="Leak conductance [m^3/(s Pa)]")


class SensorsBlock(_Strict):
    """Added: sensor noise seen in the log (rest segments or residuals)."""

    x_noise: float = Field(ge=0.0, le=1.0e-3, description="Position noise std [m]")
    p_noise: float = Field(ge=0.0, le=1.0e5, description="Pressure noise std [Pa]")


#: plant.yaml keys of the real-rig effects a model may carry (``effects``), and their upper
#: limits [s] (as plant.yaml allows them).
EFFECT_KEYS: dict[str, float] = {
    "io.delay": 0.01,
    "sensors.p_lag": 0.05,
    "sensors.x_lag": 0.05,
    **{f"valves.{v}.{k}": 0.02 for v in VALVES for k in ("tau_open", "tau_close")},
}


class EffectRange(_Strict):
    """Added: one real-rig effect's value in the model and the range tune draws it from."""

    nominal: float = Field(ge=0.0, description="The value of the nominal plant (SI units)")
    range: Range = Field(description="[lo, hi] the plant draws sample (SI units)")


def _check_effects(effects: dict[str, EffectRange]) -> None:
    for key, eff in effects.items():
        if key not in EFFECT_KEYS:
            raise ValueError(f"effects: unknown key {key!r}; expected one of "
                             f"{', '.join(EFFECT_KEYS)}")
        lo, hi = eff.range
        if not 0.0 <= lo <= eff.nominal <= hi <= EFFECT_KEYS[key]:
            raise ValueError(f"effects.{key}: 0 <= lo <= nominal <= hi <= {EFFECT_KEYS[key]} "
                             f"must hold, got lo={lo}, nominal={eff.nominal}, hi={hi}")


class ModelConfig(_Strict):
    """The whole model.yaml document."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False,
                              populate_by_name=True)

    schema_: Literal["pneutune.model/1"] = Field(MODEL_SCHEMA, alias="schema")
    source: SourceInfo | Sources = Field(
        description="The log the model came from; for a model fitted to several logs of one "
        "rig, a list of two or more of them, one per log")
    rig: RigConfig
    valves: ModelValves
    pwm: PwmCurve
    friction: ModelFriction
    mass: float = Field(gt=0.0, le=1.0e3, description="Total moving mass identified [kg]")
    mass_range: Range | None = Field(None, description="Added: [lo, hi] of the mass [kg]")
    theta: ThetaBlock
    uncertainty: Uncertainty
    fit: FitBlock
    leak: LeakBlock = LeakBlock()
    sensors: SensorsBlock | None = None
    effects: dict[str, EffectRange] | None = Field(
        None, description="Added: real-rig effects (plant.yaml keys: io.delay, sensors.p_lag, "
        "sensors.x_lag, valves.<valve>.tau_open|tau_close), each with the value the nominal "
        "plant has and the range tune's plant draws sample; absent: none")
    loop_delay: EffectRange | None = Field(
        None, description="Added: the whole loop delay, from a written duty to the chamber "
        "flow's response (the valves' opening delays plus io.delay) [s]; informative, tune "
        "draws its parts")
    basis: dict[str, str] | None = Field(
        None, description="Added: where each range of the plant coordinates came from, keyed "
        "like tune's plant draws (mass, friction.F_S, valves.a_in.C, ...): 'statistics: ...', "
        "'data bound: ...', 'prior: ...', and what the cross-check against the log changed")
    notes: Annotated[tuple[str, ...], BeforeValidator(_to_tuple)] = Field(
        (), description="Added: what was not identifiable, and why")

    @model_validator(mode="after")
    def _check(self) -> ModelConfig:
        # the simulator handles a valve's switching within 4 PWM periods (plant.yaml's rule)
        period = 1.0 / self.rig.pwm_hz
        for name in VALVES:
            valve = getattr(self.valves, name)
            key, slowest = max((("delay_on", valve.delay_on), ("delay_off", valve.delay_off)),
                               key=lambda kv: kv[1])
            if slowest > 4.0 * period:
                raise ValueError(f"valves.{name}.{key}: must not exceed 4 PWM periods "
                                 f"({4.0 * period:.6g} s at rig.pwm_hz = {self.rig.pwm_hz:g} Hz), "
                                 f"got {slowest:g} s")
        if self.mass_range is not None:
            _check_range("mass", self.mass_range[0], self.mass, self.mass_range[1])
        if self.effects:
            _check_effects(self.effects)
        if self.loop_delay is not None:
            _check_range("loop_delay", self.loop_delay.range[0], self.loop_delay.nominal,
                         self.loop_delay.range[1])
        return self

    @property
    def sources(self) -> tuple[SourceInfo, ...]:
        """Every log the model came from, in order (one for a single-log ``source``)."""
        return (self.source,) if isinstance(self.source, SourceInfo) else tuple(self.source)

    def to_dict(self) -> dict[str, Any]:
        """Plain data as written to model.yaml (lists, not tuples)."""
        return _listify(self.model_dump(by_alias=True, mode="python", exclude_none=True))


def _listify(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _listify(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_listify(v) for v in obj]
    return obj


def load_model(path: str | os.PathLike[str]) -> ModelConfig:
    """Load and validate a model.yaml; any failure is a ConfigError naming file and key."""
    return load_config(path, ModelConfig, MODEL_SCHEMA)


def save_model(model: ModelConfig, path: str | os.PathLike[str], header: str = "") -> None:
    """Write a model.yaml atomically."""
    write_yaml(path, model.to_dict(), header=header)


