"""plant.yaml (contract 2, ``pneutune.plant/1``): the simulated rig's configuration.

Defaults are the paper's rig (Sec. 5.1) plus the choices the paper leaves open, each marked
"not in the paper" with its reason. A partial file is merged over the defaults; an unknown key,
a wrong type or an out-of-range value is a :class:`ConfigError` naming the key.
"""

from __future__ import annotations

import itertools
import os
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from pneutune.control.constants import PLANT_SCHEMA, RIG_KEYS, VALVES
from pneutune.control.contracts.yamlio import deep_merge, load_config, validate_model


class _Strict(BaseModel):
    """Frozen, strict, no unknown keys: a misspelt key never falls back to a default."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class RigConfig(_Strict):
    """Cylinder geometry, gas and timing (the ``rig`` block shared by all four contracts)."""

    A_a: float = Field(7.854e-3, gt=0.0, le=1.0, description="Piston area, chamber A [m^2]")
    A_b: float = Field(7.54e-3, gt=0.0, le=1.0, description="Annulus area, chamber B [m^2]")
    x_min: float = Field(-0.0015, ge=-1.0, le=1.0, description="Stroke end, A side [m]")
    x_max: float = Field(0.0485, ge=-1.0, le=2.0, description="Stroke end, B side [m]")
    V0a: float = Field(5.036e-5, gt=0.0, le=0.1, description="Dead volume of A at x_min [m^3]")
    V0b: float = Field(2.916e-5, gt=0.0, le=0.1, description="Dead volume of B at x_max [m^3]")
    p0: float = Field(101325.0, ge=5.0e4, le=1.2e5, description="Ambient pressure [Pa abs]")
    p_s: float = Field(6.0e5, ge=1.2e5, le=1.6e6, description="Supply pressure [Pa abs]")
    T0: float = Field(283.15, ge=200.0, le=400.0, description="Gas temperature [K]")
    n: float = Field(1.2, ge=1.0, le=1.4, description="Polytropic exponent [-]")
    R: float = Field(287.0, gt=0.0, le=1.0e4, description="Gas constant of air [J/(kg K)]")
    Ts: float = Field(0.004, ge=1.0e-4, le=0.1, description="Sampling/control period [s]")
    pwm_hz: float = Field(60.0, ge=1.0, le=2000.0, description="PWM frequency [Hz]")
    pwm_update: Literal["immediate", "latched"] = Field(
        "immediate",
        description="immediate: a new duty acts at once (comparator against the PWM carrier); "
        "latched: it acts from the next PWM period start.",
    )

    @field_validator("x_max")
    @classmethod
    def _x_max_above_x_min(cls, value: float, info: ValidationInfo) -> float:
        x_min = info.data.get("x_min")
        if x_min is not None and not value > x_min:
            raise ValueError(f"x_max > x_min must hold, got x_min={x_min}, x_max={value}")
        return value

    @field_validator("A_b")
    @classmethod
    def _A_b_below_A_a(cls, value: float, info: ValidationInfo) -> float:
        A_a = info.data.get("A_a")
        if A_a is not None and value > A_a:
            raise ValueError(f"A_b <= A_a must hold (rod area A_a - A_b >= 0), "
                             f"got A_a={A_a}, A_b={value}")
        return value

    @field_validator("p_s")
    @classmethod
    def _p_s_above_p0(cls, value: float, info: ValidationInfo) -> float:
        p0 = info.data.get("p0")
        if p0 is not None and not value > p0:
            raise ValueError(f"p_s > p0 must hold, got p0={p0}, p_s={value}")
        return value

    @property
    def A_r(self) -> float:
        """Rod cross-section A_a - A_b [m^2]."""
        return self.A_a - self.A_b

    @property
    def pwm_period(self) -> float:
        """PWM period 1/pwm_hz [s]."""
        return 1.0 / self.pwm_hz


class FrictionConfig(_Strict):
    """Stribeck friction of Eq. (2).

    With ``sigma0`` > 0 the friction is the LuGre model instead (a real-rig effect): a bristle
    deflection z with ``dz/dt = v - sigma0 |v| z / g(v)``, ``g(v) = F_C + (F_S - F_C)
    exp(-(|v|/v_s)^alpha)`` and ``F_f = sigma0 z + sigma1 dz/dt + b_v v``. In steady sliding it
    is Eq. (2)'s Stribeck curve, so F_S, F_C, v_s, alpha and b_v keep their meaning; below
    break-away the piston creeps micrometres on the bristles' stiffness instead of sticking.

    Only b_v = 3500 N s/m is in the paper. Not in the paper: F_S, F_C, v_s and alpha; the
    defaults are plausible for a 100 mm bore cylinder (F_C tens of newtons, F_S above
    F_C, Stribeck velocity a few mm/s) and consistent with the paper's nominal A_f = 100 N of the
    smooth model, which must cover F_C plus part of the Stribeck excess.
    """

    F_S: float = Field(75.0, ge=0.0, le=1.0e4, description="Stiction force [N]")
    F_C: float = Field(50.0, ge=0.0, le=1.0e4, description="Coulomb friction level [N]")
    v_s: float = Field(0.005, gt=0.0, le=1.0, description="Stribeck velocity [m/s]")
    alpha: float = Field(2.0, gt=0.0, le=10.0, description="Stribeck exponent [-]")
    b_v: float = Field(3500.0, ge=0.0, le=1.0e5, description="Viscous coefficient [N s/m]")
    sigma0: float = Field(
        0.0, ge=0.0, le=1.0e8,
        description="LuGre bristle stiffness [N/m] (pre-sliding, a real-rig effect; 1e5-1e7 "
        "typical of pneumatic seals); 0: the stick-slip law of Eq. (2)")
    sigma1: float = Field(
        0.0, ge=0.0, le=1.0e5,
        description="LuGre bristle damping [N s/m] (used only with sigma0 > 0)")

    @field_validator("F_C")
    @classmethod
    def _F_C_below_F_S(cls, value: float, info: ValidationInfo) -> float:
        F_S = info.data.get("F_S")
        if F_S is not None and value > F_S:
            raise ValueError(f"F_C <= F_S must hold, got F_S={F_S}, F_C={value}")
        return value

    @model_validator(mode="after")
    def _lugre_needs_coulomb(self) -> FrictionConfig:
        if self.sigma0 > 0.0 and not self.F_C > 0.0:
            raise ValueError(f"sigma0 > 0 (LuGre) needs F_C > 0: the bristles relax at the rate "
                             f"sigma0 |v| / g(v) and g(v) >= F_C; got F_C={self.F_C}")
        return self


class ValveConfig(_Strict):
    """One on/off valve: ISO 6358 flow (Eq. 7) and its switching behaviour.

    Not in the paper: the delays and the minimum pulse. Defaults are typical of fast 3/2
    solenoid valves (a few ms). ``min_pulse`` is the shortest command pulse that moves the
    armature at all (the time for the coil current to reach pull-in); it cannot exceed
    ``delay_on``, the time from command to fully open, which includes it.
    """

    C: float = Field(8.373e-9, gt=0.0, le=1.0e-6, description="Sonic conductance [m^3/(s Pa)]")
    b: float = Field(0.18561, ge=0.0, le=0.95, description="Critical pressure ratio [-]")
    delay_on: float = Field(2.0e-3, ge=0.0, le=0.05, description="Command-on to open [s]")
    delay_off: float = Field(3.0e-3, ge=0.0, le=0.05, description="Command-off to closed [s]")
    min_pulse: float = Field(1.5e-3, ge=0.0, le=0.05, description="Shortest pulse that opens [s]")
    tau_open: float = Field(
        0.0, ge=0.0, le=0.02,
        description="Armature/spool opening time constant [s]: from the opening delay on, the "
        "open fraction rises as 1 - exp(-t/tau_open) instead of at once (a real-rig effect, "
        "not in the paper; fast solenoid valves 0.2-1 ms; 0: off)")
    tau_close: float = Field(
        0.0, ge=0.0, le=0.02,
        description="Armature/spool closing time constant [s]: from the closing delay on, the "
        "open fraction falls as exp(-t/tau_close) (0.2-1.5 ms typical; 0: off)")

    @field_validator("min_pulse")
    @classmethod
    def _min_pulse_within_delay_on(cls, value: float, info: ValidationInfo) -> float:
        delay_on = info.data.get("delay_on")
        if delay_on is not None and value > delay_on:
            raise ValueError(f"min_pulse <= delay_on must hold (the minimum pulse is part of the "
                             f"opening delay), got min_pulse={value}, delay_on={delay_on}")
        return value


class ValvesConfig(_Strict):
    """The four valves, in the order a_in, a_out, b_in, b_out."""

    a_in: ValveConfig = ValveConfig()
    a_out: ValveConfig = ValveConfig()
    b_in: ValveConfig = ValveConfig()
    b_out: ValveConfig = ValveConfig()

    def ordered(self) -> tuple[ValveConfig, ValveConfig, ValveConfig, ValveConfig]:
        """The valves in the contract order (:data:`~pneutune.control.constants.VALVES`)."""
        return tuple(getattr(self, name) for name in VALVES)  # type: ignore[return-value]


class LeakConfig(_Strict):
    """Piston-seal leak between A and B: ISO 6358 form with b = 0 (not in the paper)."""

    C: float = Field(0.0, ge=0.0, le=1.0e-7, description="Leak conductance [m^3/(s Pa)]")


class LineConfig(_Strict):
    """The pneumatic line between one chamber's two valves and the chamber (a real-rig effect,
    not in the paper; every term off by default).

    Quasi-static: the pressure wave needs ``delay`` to travel the line, so a valve's switching
    reaches the chamber that much later; the line's ``volume`` adds to the chamber's dead volume;
    its conductance ``C`` (ISO 6358 form with critical ratio ``b``) is in series with whichever
    of the chamber's valves is open, meeting them at a junction of negligible volume.
    """

    delay: float = Field(
        0.0, ge=0.0, le=0.01,
        description="Transport delay valve -> chamber [s]: length over the speed of sound "
        "(about 3 ms per metre of tube)")
    volume: float = Field(
        0.0, ge=0.0, le=0.01,
        description="Volume of the line, added to the chamber's dead volume [m^3] (0.5 m of "
        "6 mm bore tube: 1.4e-5 m^3)")
    C: float | None = Field(
        None, gt=0.0, le=1.0e-6,
        description="Sonic conductance of the line [m^3/(s Pa)]; null: no restriction")
    b: float = Field(0.3, ge=0.0, le=0.95, description="Critical pressure ratio of the line [-]")


class LinesConfig(_Strict):
    """The two lines: ``a`` feeds chamber A (valves a_in, a_out), ``b`` chamber B."""

    a: LineConfig = LineConfig()
    b: LineConfig = LineConfig()


class HeatConfig(_Strict):
    """Chamber thermodynamics (a real-rig effect, not in the paper; off by default).

    With ``h`` null the chambers follow the paper's Eqs. (5)-(6): a fixed polytropic exponent
    ``rig.n`` at the constant temperature ``rig.T0``. With ``h`` set, each chamber's gas
    temperature is a state: the energy equation with the ratio of specific heats ``gamma``,
    inflow at the supply temperature ``rig.T0``, outflow at the chamber's temperature, and
    convection ``h`` to the walls, which stay at ``rig.T0``. The wall area is the two end
    faces plus the bore's perimeter times the chamber's length (its volume over its area).
    """

    h: float | None = Field(
        None, ge=0.0, le=1.0e3,
        description="Wall heat-transfer coefficient [W/(m^2 K)] (5-50 typical of cylinder "
        "chambers; 0: adiabatic); null: the fixed polytropic exponent rig.n")
    gamma: float = Field(1.4, ge=1.0, le=1.67, description="Ratio of specific heats [-]")


class IOConfig(_Strict):
    """The data acquisition between the controller and the valves (not in the paper)."""

    delay: float = Field(
        0.0, ge=0.0, le=0.01,
        description="IO delay [s]: a duty written at a sample takes effect this much later "
        "(computation and output latency; 0: at once)")


class SupplyConfig(_Strict):
    """The supply line from the regulator to the inlet valves (a real-rig effect, not in the
    paper; off by default).

    With ``C`` set, the regulator holds ``rig.p_s`` (or the scenario's supply) upstream of a
    line of conductance ``C`` that fills a manifold of ``volume``, from which both inlet valves
    draw: at high flow the valves see the manifold's pressure droop, which the supply
    transmitter reads.
    """

    C: float | None = Field(
        None, gt=0.0, le=1.0e-6,
        description="Sonic conductance of the supply line and regulator [m^3/(s Pa)]; "
        "null: a stiff supply at rig.p_s")
    b: float = Field(0.3, ge=0.0, le=0.95, description="Critical pressure ratio of the line [-]")
    volume: float = Field(2.0e-4, gt=0.0, le=0.1,
                          description="Volume of the manifold and hose at the valves [m^3]")


class DisturbanceConfig(_Strict):
    """Constant disturbance terms of Eqs. (1), (5) and external force steps."""

    F_n: float = Field(0.0, ge=-1.0e4, le=1.0e4, description="Constant force on the piston [N]")
    D_a: float = Field(0.0, ge=-1.0e7, le=1.0e7, description="Constant dp_a/dt term [Pa/s]")
    D_b: float = Field(0.0, ge=-1.0e7, le=1.0e7, description="Constant dp_b/dt term [Pa/s]")
    force_steps: tuple[tuple[float, float], ...] = Field(
        (), description="[[t, F], ...]: from time t [s] the external force is F [N] (a level, "
        "not an increment); before the first step it is 0."
    )

    @field_validator("force_steps", mode="before")
    @classmethod
    def _lists_to_tuples(cls, value: Any) -> Any:
        if isinstance(value, list):
            return tuple(tuple(v) if isinstance(v, list) else v for v in value)
        return value

    @field_validator("force_steps")
    @classmethod
    def _check_steps(cls, value: tuple[tuple[float, float], ...]
                     ) -> tuple[tuple[float, float], ...]:
        times = [t for t, _ in value]
        if any(t < 0.0 for t in times):
            raise ValueError(f"force_steps times must be >= 0 s, got {times}")
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"force_steps times must increase strictly, got {times}")
        return value


class SensorsConfig(_Strict):
    """Sensor noise and quantisation (not in the paper; typical of the Sec. 5.1 sensors).

    Position: a resistive 75 mm sensor read by a 16-bit card (1.2 um steps) with 5 um noise.
    Pressures (chambers and supply): 300 Pa noise (0.03 % of a 10 bar span).
    Lags, the pressure quantum and transmitters at the valves (``p_at``) are real-rig effects,
    off by default: each reading is the first-order-lagged true value (of the chamber, or of
    the valves' junction), then noise is added, then it is quantised.
    """

    x_noise: float = Field(5.0e-6, ge=0.0, le=1.0e-3, description="Position noise std [m]")
    x_step: float = Field(1.2e-6, ge=0.0, le=1.0e-3, description="Position quantum [m]")
    p_noise: float = Field(300.0, ge=0.0, le=1.0e5, description="Pressure noise std [Pa]")
    p_step: float = Field(0.0, ge=0.0, le=1.0e5,
                          description="Pressure quantum [Pa] (12-bit on 10 bar: 244 Pa; 0: off)")
    x_lag: float = Field(0.0, ge=0.0, le=0.05,
                         description="Position sensor first-order lag [s] (0: off)")
    p_lag: float = Field(
        0.0, ge=0.0, le=0.05,
        description="Pressure transmitter first-order lag [s], chambers and supply "
        "(0.5-2 ms typical of industrial transmitters; 0: off)")
    p_at: Literal["chamber", "valves"] = Field(
        "chamber",
        description="Where the chamber pressure transmitters are plumbed: chamber (at the "
        "cylinder port, reading the chamber's pressure) or valves (at the valves' side of "
        "the line: with a line conductance they read the junction where the chamber's two "
        "valves meet the line, which leads the chamber while air flows; shut valves: the "
        "chamber's pressure)")


class SimConfig(_Strict):
    """Integration settings. ``dt`` is the largest RK4 step; see docs/integration.md.

    The default 0.4 ms comes from the convergence study of docs/integration.md: halving it
    moves the closed-loop tracking metrics E_p and E_rms by less than 0.005 mm. The integrator
    further limits the step while sliding to ``2 M / b_v`` (and less on a steep Stribeck branch
    near v = 0) so that RK4 stays stable and accurate on the stiff viscous mode of light,
    heavily damped plants.
    """

    dt: float = Field(4.0e-4, ge=1.0e-6, le=2.0e-3, description="Largest integration step [s]")
    seed: int = Field(1, ge=0, le=2**63 - 1, description="Seed of the sensor noise")


class PlantConfig(_Strict):
    """The whole plant.yaml document."""

    schema_: Literal["pneutune.plant/1"] = Field(PLANT_SCHEMA, alias="schema")
    rig: RigConfig = RigConfig()
    mass: float = Field(1.05, gt=0.0, le=1.0e3, description="Moving parts [kg]")
    payload: float = Field(0.0, ge=0.0, le=1.0e3, description="Extra load [kg]")
    friction: FrictionConfig = FrictionConfig()
    valves: ValvesConfig = ValvesConfig()
    leak: LeakConfig = LeakConfig()
    lines: LinesConfig = LinesConfig()
    heat: HeatConfig = HeatConfig()
    supply: SupplyConfig = SupplyConfig()
    io: IOConfig = IOConfig()
    disturbance: DisturbanceConfig = DisturbanceConfig()
    sensors: SensorsConfig = SensorsConfig()
    sim: SimConfig = SimConfig()

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False,
                              populate_by_name=True)

    @model_validator(mode="after")
    def _check(self) -> PlantConfig:
        period = self.rig.pwm_period
        for name, valve in zip(VALVES, self.valves.ordered(), strict=True):
            line = self.lines.a if name.startswith("a_") else self.lines.b
            slowest = max(valve.delay_on, valve.delay_off) + line.delay
            if slowest > 4.0 * period:
                side = "a" if name.startswith("a_") else "b"
                raise ValueError(
                    f"valves.{name}: delays plus lines.{side}.delay must not exceed 4 PWM "
                    f"periods ({4.0 * period:.6g} s at rig.pwm_hz={self.rig.pwm_hz}), "
                    f"got {slowest}")
        return self

    @property
    def effects(self) -> tuple[str, ...]:
        """The real-rig effects switched on (empty: the paper's model of Sec. 2)."""
        on = []
        if any(v.tau_open > 0.0 or v.tau_close > 0.0 for v in self.valves.ordered()):
            on.append("valve lag")
        if any(ln.delay > 0.0 or ln.volume > 0.0 or ln.C is not None
               for ln in (self.lines.a, self.lines.b)):
            on.append("lines")
        if self.heat.h is not None:
            on.append("heat transfer")
        if self.friction.sigma0 > 0.0:
            on.append("pre-sliding")
        if self.sensors.x_lag > 0.0 or self.sensors.p_lag > 0.0 or self.sensors.p_step > 0.0:
            on.append("sensor lag")
        if self.sensors.p_at == "valves":
            on.append("transmitters at the valves")
        if self.io.delay > 0.0:
            on.append("IO delay")
        if self.supply.C is not None:
            on.append("supply droop")
        return tuple(on)

    @property
    def total_mass(self) -> float:
        """Moving mass including payload [kg]."""
        return self.mass + self.payload

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (as written to plant.yaml)."""
        data = self.model_dump(by_alias=True, mode="python")
        data["disturbance"]["force_steps"] = [list(s) for s in self.disturbance.force_steps]
        return data

    def with_updates(self, updates: dict[str, Any], source: str = "<override>") -> PlantConfig:
        """A copy with ``updates`` deep-merged in and validated again."""
        return validate_model(PlantConfig, deep_merge(self.to_dict(), updates), source)

    def rig_metadata(self) -> dict[str, float | str]:
        """The ``rig`` block as the MCAP ``rig`` metadata record expects it (all RIG_KEYS)."""
        rig = self.rig.model_dump()
        return {k: rig[k] for k in RIG_KEYS}


def load_plant(path: str | os.PathLike[str] | None = None) -> PlantConfig:
    """Load plant.yaml merged over the paper defaults.

    Parameters
    ----------
    path : path-like or None
        The file; ``None`` gives the defaults.

    Returns
    -------
    PlantConfig

    Raises
    ------
    ConfigError
        Unknown key, wrong type, out-of-range value or bad YAML, naming the file and key.
    """
    if path is None:
        return PlantConfig()
    return load_config(path, PlantConfig, PLANT_SCHEMA, defaults=PlantConfig().to_dict())
