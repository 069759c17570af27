"""Contract 1 (``pneutune.log/1``), the MCAP run log: its topics, their fields and schemas.

One run per file. Every topic of the contract is one MCAP channel with message encoding ``json``
and a JSON Schema (schema encoding ``jsonschema``, :data:`TOPIC_SCHEMAS`), so that Foxglove and
any other MCAP reader can open the file. Two metadata records (string maps) describe the run:
``rig`` holds every key of :data:`~pneutune.control.constants.RIG_KEYS` (numbers as decimal
strings) and optionally the hints of :data:`~pneutune.control.constants.RIG_HINT_KEYS`
(``mass``); ``run`` holds ``schema`` (``pneutune.log/1``), ``created_by``, ``version`` and, for a
simulated run, ``seed``.

Times
    A message's log time is integer nanoseconds since the start of the run,
    ``round(t * 1e9)`` of the time ``t`` [s] given to the writer; publish time equals log time.
    The reader's index is ``log_time / 1e9`` [s] (float64). Within one topic, times never
    decrease in file order.

Non-finite numbers
    JSON has no NaN or infinity. A NaN, ``+inf`` or ``-inf`` is stored as ``null``; the JSON
    Schemas say so in their descriptions.

Compact layout
    The writer formats a message of a numeric topic as :attr:`TopicSpec.template`: fields in
    schema order, no whitespace, numbers as ``repr(float)``. The reader decodes that layout in
    bulk and any other JSON layout message by message.

The writer is :mod:`pneutune.control.logs.writer`, the reader :mod:`pneutune.control.logs.reader`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

from pneutune.control.constants import LOG_SCHEMA, RIG_KEYS

__all__ = [
    "AGE_RESOLUTION",
    "EVENT_LEVELS",
    "REQUIRED_TOPICS",
    "RIG_NUMBER_KEYS",
    "TOPICS",
    "TOPIC_SCHEMAS",
    "TOPIC_SPECS",
    "FieldSpec",
    "TopicSpec",
    "format_ns",
    "topic_fields",
    "topic_spec",
]

#: Topics that every run log must contain (contract 1).
REQUIRED_TOPICS: tuple[str, ...] = ("/rig/sensors", "/rig/valves")
#: Reading ages (``/rig/sensor_age``) up to this are a clock's rounding, not a sampling skew
#: [s]: a driver clocked in Unix time resolves 0.24 us. A run whose ages all stay within it
#: writes no ``/rig/sensor_age``.
AGE_RESOLUTION = 1.0e-6
#: Values of ``/rig/events`` field ``level``.
EVENT_LEVELS: tuple[str, ...] = ("info", "warning", "error")
#: The keys of the ``rig`` metadata record that hold decimal numbers (all but ``pwm_update``).
RIG_NUMBER_KEYS: tuple[str, ...] = tuple(k for k in RIG_KEYS if k != "pwm_update")

#: Field kinds: a number, a vector of 6 numbers (``theta_hat``), a string, an event level
#: (a string of :data:`EVENT_LEVELS`), a JSON object (segment ``params``).
NUMBER, VECTOR6, STRING, LEVEL, OBJECT = "number", "vector6", "string", "level", "object"
_NULL_NOTE = " JSON has no NaN or infinity: a non-finite value is written as null."
_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class FieldSpec:
    """One field of a topic: its name, kind (:data:`NUMBER`, :data:`VECTOR6`, ...) and the
    description (with its unit) that goes into the JSON Schema."""

    name: str
    kind: str
    description: str


@dataclass(frozen=True)
class TopicSpec:
    """One topic of contract 1: its fields, schema and JSON row template."""

    topic: str
    schema_name: str
    description: str
    fields: tuple[FieldSpec, ...]

    @cached_property
    def numeric(self) -> bool:
        """True if every field is a number or a vector of numbers (``write_many`` applies)."""
        return all(f.kind in (NUMBER, VECTOR6) for f in self.fields)

    @cached_property
    def names(self) -> tuple[str, ...]:
        """The field names, in schema order (a vector field is one name)."""
        return tuple(f.name for f in self.fields)

    @cached_property
    def width(self) -> int:
        """Numbers per message of a numeric topic."""
        return sum(6 if f.kind == VECTOR6 else 1 for f in self.fields)

    @cached_property
    def columns(self) -> tuple[str, ...]:
        """DataFrame columns: fields, with a vector expanded to ``name_0`` .. ``name_5``."""
        out: list[str] = []
        for f in self.fields:
            out.extend([f"{f.name}_{k}" for k in range(6)] if f.kind == VECTOR6 else [f.name])
        return tuple(out)

    @cached_property
    def template(self) -> str:
        """%-format template of one compact JSON message; one ``%r`` per number."""
        parts = []
        for f in self.fields:
            value = "[" + ",".join(["%r"] * 6) + "]" if f.kind == VECTOR6 else "%r"
            parts.append(f'"{f.name}":{value}')
        return "{" + ",".join(parts) + "}"

    def json_schema(self) -> dict[str, Any]:
        """The topic's JSON Schema (draft 2020-12): every field required, no other field."""
        props: dict[str, Any] = {}
        for f in self.fields:
            if f.kind == NUMBER:
                props[f.name] = {"type": "number", "description": f.description + _NULL_NOTE}
            elif f.kind == VECTOR6:
                props[f.name] = {
                    "type": "array",
                    "items": {"type": "number"},
                    "minItems": 6,
                    "maxItems": 6,
                    "description": f.description + _NULL_NOTE,
                }
            elif f.kind == LEVEL:
                props[f.name] = {
                    "type": "string",
                    "enum": list(EVENT_LEVELS),
                    "description": f.description,
                }
            elif f.kind == OBJECT:
                props[f.name] = {"type": "object", "description": f.description}
            else:
                props[f.name] = {"type": "string", "description": f.description}
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": f"{LOG_SCHEMA} {self.topic}",
            "description": self.description,
            "type": "object",
            "properties": props,
            "required": list(self.names),
            "additionalProperties": False,
        }


def _number(name: str, description: str) -> FieldSpec:
    return FieldSpec(name, NUMBER, description)


_SPEC_LIST: tuple[TopicSpec, ...] = (
    TopicSpec(
        "/rig/sensors",
        "pneutune.log.RigSensors",
        "Measured signals, one message per sample.",
        (
            _number("x", "Piston position [m]; x = 0 lies 1.5 mm from the rodless end."),
            _number("p_a", "Pressure in chamber A (rodless side) [Pa, absolute]."),
            _number("p_b", "Pressure in chamber B (rod side) [Pa, absolute]."),
            _number("p_s", "Supply pressure [Pa, absolute]."),
        ),
    ),
    TopicSpec(
        "/rig/sensor_age",
        "pneutune.log.RigSensorAge",
        "Age of each /rig/sensors value at its message's time: the message time minus the "
        "time the channel was sampled, one message per /rig/sensors message at the same log "
        "time. Written when the rig reports per-channel sample times (a multiplexed ADC, a "
        "fieldbus that polls the transmitters in turn) and some channel was not sampled at "
        "its message's time; identify then interpolates each channel to the message times. "
        "Absent, every reading counts as sampled at its message's time.",
        (
            _number("x", "Age of the position reading [s]."),
            _number("p_a", "Age of the chamber-A pressure reading [s]."),
            _number("p_b", "Age of the chamber-B pressure reading [s]."),
            _number("p_s", "Age of the supply pressure reading [s]."),
        ),
    ),
    TopicSpec(
        "/rig/valves",
        "pneutune.log.RigValves",
        "Commanded PWM duty of the four on/off valves, one message per sample.",
        (
            _number("u_a_in", "Commanded duty of valve a_in (charge A), 0..1 [1]."),
            _number("u_a_out", "Commanded duty of valve a_out (exhaust A), 0..1 [1]."),
            _number("u_b_in", "Commanded duty of valve b_in (charge B), 0..1 [1]."),
            _number("u_b_out", "Commanded duty of valve b_out (exhaust B), 0..1 [1]."),
        ),
    ),
    TopicSpec(
        "/control/reference",
        "pneutune.log.ControlReference",
        "Reference trajectory of a closed-loop run, one message per control step.",
        (
            _number("x_r", "Reference position [m]."),
            _number("v_r", "Reference velocity [m/s]."),
            _number("a_r", "Reference acceleration [m/s^2]."),
        ),
    ),
    TopicSpec(
        "/control/state",
        "pneutune.log.ControlState",
        "Internal state of the controller (DARC notation of Qian et al. 2014), one message "
        "per control step.",
        (
            _number("e1", "Position tracking error e1 = x - x_r [m]."),
            _number("e2", "Sliding error e2 = de1/dt + k1 e1 [m/s]."),
            _number("e3", "Force error e3 = F_p - F_pd [N]."),
            _number("x_hat", "Estimated position [m]."),
            _number("v_hat", "Estimated velocity [m/s]."),
            _number("a_hat", "Estimated acceleration [m/s^2]."),
            _number("F_pd", "Desired pneumatic force F_pd (Eq. 17) [N]."),
            _number("dF_pd", "Estimated time derivative of F_pd [N/s]."),
            _number("Q_Ld", "Desired load flow Q_Ld (Eq. 26) [N/s]."),
            FieldSpec(
                "theta_hat",
                VECTOR6,
                "Parameter estimate theta_hat = [M kg, F_n N, b_v N s/m, A_f N, D_an Pa/s, "
                "D_bn Pa/s] (paper Sec. 2.3 order).",
            ),
        ),
    ),
    TopicSpec(
        "/experiment/segment",
        "pneutune.log.ExperimentSegment",
        "Start of a segment of an experiment protocol, one message per segment.",
        (
            FieldSpec("label", STRING, "Segment name, unique within the run."),
            FieldSpec("kind", STRING, "Segment type (e.g. chirp, step, hold)."),
            FieldSpec("params", OBJECT, "Segment parameters, SI units."),
        ),
    ),
    TopicSpec(
        "/rig/events",
        "pneutune.log.RigEvents",
        "Something happened (limit hit, sensor timeout, supervisor action).",
        (
            FieldSpec("level", LEVEL, "Severity."),
            FieldSpec("code", STRING, "Machine-readable event code."),
            FieldSpec("message", STRING, "Human-readable description."),
        ),
    ),
    TopicSpec(
        "/sim/truth",
        "pneutune.log.SimTruth",
        "True plant signals of a simulated run, one message per sample.",
        (
            _number("v", "Piston velocity [m/s]."),
            _number("a", "Piston acceleration [m/s^2]."),
            _number("F_friction", "Friction force F_f of Eq. (1) [N]."),
            _number("F_ext", "External force on the piston [N]."),
            _number("mdot_a", "Net mass flow into chamber A [kg/s]."),
            _number("mdot_b", "Net mass flow into chamber B [kg/s]."),
        ),
    ),
)
#: The spec of every topic of contract 1 (fields, schema, compact JSON layout).
TOPIC_SPECS: dict[str, TopicSpec] = {s.topic: s for s in _SPEC_LIST}
#: The topics of contract 1, in the order of the contract.
TOPICS: tuple[str, ...] = tuple(TOPIC_SPECS)
#: JSON Schema (draft 2020-12) of every topic of contract 1; stored in the file's schema records.
TOPIC_SCHEMAS: dict[str, dict[str, Any]] = {s.topic: s.json_schema() for s in _SPEC_LIST}


def topic_spec(topic: str) -> TopicSpec:
    """The spec of a contract-1 topic.

    Raises
    ------
    ValueError
        A topic outside contract 1.
    """
    try:
        return TOPIC_SPECS[topic]
    except KeyError:
        raise ValueError(f"unknown topic {topic!r}; contract 1 has {', '.join(TOPICS)}") from None


def topic_fields(topic: str) -> tuple[str, ...]:
    """The field names of a contract-1 topic, in order (a vector field is one name).

    Raises
    ------
    ValueError
        A topic outside contract 1.
    """
    return topic_spec(topic).names


def format_ns(ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond time, e.g. ``1.004000000 s``."""
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    q, r = divmod(abs(ns), _NS_PER_S)
    return f"{sign}{q}.{r:09d} s"
