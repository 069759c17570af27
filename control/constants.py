"""Physical constants and naming conventions shared by every module (SI units)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    #: The installed pneutune's version (``pneutune.control.__version__``).
    VERSION: str = version("pneutune")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    VERSION = "0.0.0+unknown"

#: ISO 6358 reference temperature [K].
T_REF: float = 293.15
#: Air density at the ISO 6358 reference conditions [kg/m^3].
RHO0: float = 1.185

#: Valve order everywhere (arrays of four are in this order): charge A, exhaust A, charge B,
#: exhaust B.
VALVES: tuple[str, str, str, str] = ("a_in", "a_out", "b_in", "b_out")
A_IN, A_OUT, B_IN, B_OUT = 0, 1, 2, 3

#: Keys of the ``rig`` block (plant.yaml, model.yaml, controller.yaml and the MCAP ``rig``
#: metadata record). All are floats in SI units except ``pwm_update``.
RIG_KEYS: tuple[str, ...] = (
    "A_a", "A_b", "x_min", "x_max", "V0a", "V0b", "p0", "p_s", "T0", "n", "R", "Ts",
    "pwm_hz", "pwm_update",
)
#: Optional keys of the ``rig`` metadata record of a run log: hints a commissioning engineer
#: may give that no log can measure well. ``mass``: the total moving mass [kg] (datasheet plus
#: payload), from which ``identify`` takes its prior range when the log cannot resolve it.
RIG_HINT_KEYS: tuple[str, ...] = ("mass",)
#: The range each hint of :data:`RIG_HINT_KEYS` must lie in, and its unit. The moving mass:
#: from 1 g (the piston and rod of the smallest cylinders weigh a few grams; the simulator's
#: step shrinks with the mass, so a mass far below any cylinder's would never finish) to
#: 1000 kg (the plant contract's bound).
RIG_HINT_RANGES: dict[str, tuple[float, float, str]] = {"mass": (1.0e-3, 1.0e3, "kg")}
#: Allowed values of ``rig.pwm_update``.
PWM_UPDATE_MODES: tuple[str, str] = ("immediate", "latched")

#: The paper's θ = [M, F_n, b_v, A_f, D_an, D_bn] (Sec. 2.3); this order is kept everywhere.
THETA_NAMES: tuple[str, ...] = ("M", "F_n", "b_v", "A_f", "D_an", "D_bn")
#: Units of θ's components, in the same order.
THETA_UNITS: tuple[str, ...] = ("kg", "N", "N s/m", "N", "Pa/s", "Pa/s")

#: A valve whose b range (``b_max - b_min`` in model.yaml) is wider than this is weakly
#: identified: ``identify`` says so, and ``tune`` then searches θ̂3(0) (docs/tuning.md) [-].
WEAK_B_SPAN: float = 0.2

#: ``deploy --home`` (``run_scenario(home=...)``): move the piston to the scenario's start only
#: when it rests more than 1 mm away, before every scenario, or never.
HOME_MODES: tuple[str, ...] = ("auto", "always", "off")

#: Schema identifiers of the file contracts.
LOG_SCHEMA = "pneutune.log/1"
PLANT_SCHEMA = "pneutune.plant/1"
MODEL_SCHEMA = "pneutune.model/1"
CONTROLLER_SCHEMA = "pneutune.controller/1"
