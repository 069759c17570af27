"""The supervisor's settings as a flat vector for the C targets, and ``pt_sup_layout.h``.

A PLC or a microcontroller runs the control law in C (``control/law/c/ptlaw.c``) and, around it,
the same safety supervisor as the deploy runtime
(:class:`~pneutune.control.rig.supervisor.Supervisor`) in ``control/law/c/pt_supervisor.c``,
wrapped with the law by ``pt_controller.c``. The C reads the supervisor's thresholds from a flat
``pt_real sup[PT_SUP_SIZE]`` vector that :func:`pack_supervisor` fills, keeps its memory in a
flat ``pt_real state[PT_SUP_STATE_SIZE]`` vector, and reports a ``uint32_t`` status word.

All three are declared here once: the slots of the settings vector in :data:`SUP_SLOTS` (name,
width, meaning; the ``SUP_*`` offsets follow from the order), those of the state vector in
:data:`SUP_STATE_SLOTS` (``SUP_S_*``), the bits of the status word in :data:`STATUS_BITS`
(the fault bits in the order of :data:`~pneutune.control.rig.supervisor.FAULT_CODES`, the order
the supervisor checks them in). :func:`sup_layout_header` generates the C header from them;
``python -m pneutune.control.rig.supervisor_pack`` rewrites the committed
``control/law/c/pt_sup_layout.h``, and ``--check`` exits 1 when it differs.

The settings vector holds the thresholds as the module docstring of
:mod:`~pneutune.control.rig.supervisor` states them, computed here once in float64
(``x_min - x_span_margin``, ``timeout + 1 ns``, ``theta_min + theta_band (theta_max -
theta_min)``, ...): the deploy runtime's :class:`~pneutune.control.rig.supervisor.Supervisor`
and a target hand the C the same doubles, so they take the same decisions.

Status word (``uint32_t``)
    bits 0-6: the faults of :data:`~pneutune.control.rig.supervisor.FAULT_CODES` in their order
    (``sensor_nan`` ... ``supply_loss``, then ``rig_io``, which only the target's own I/O code
    raises); bit 7: ``start_position`` (the runtime's check of the first sample); bit 8:
    ``reference_nan`` (C only: a non-finite time or reference, which the Python runtime never
    receives). At most one fault bit is ever set: the first fault found, the one Python
    reports. Bit 12: the config vectors have another layout; bit 13: the fail-safe duties are
    not all in [0, 1]. Bits 16-18: the warnings of
    :data:`~pneutune.control.rig.supervisor.WARNING_CODES` (``deadline_overrun`` is the target
    scheduler's); bits 24-29: which θ̂ and bound a ``reidentify_theta`` warning is about (M, b_v,
    A_f; lower, upper), one bit per Python event.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pneutune.control.constants import THETA_NAMES
from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.law.c_header import ascii_comment, c_double, define, header_main
from pneutune.control.rig.runtime import START_TOLERANCE
from pneutune.control.rig.supervisor import (  # _TIME_EPS: the Python's own 1 ns margin
    _TIME_EPS,
    CHANNELS,
    FAIL_SAFE_MODES,
    FAULT_CODES,
    WARNING_CODES,
    WATCHED_THETA,
    SupervisorSettings,
)

#: The committed header, next to the C sources of the law and the supervisor.
HEADER_PATH: Path = Path(__file__).resolve().parents[1] / "law" / "c" / "pt_sup_layout.h"

#: The settings vector's slots in order: (name, width, meaning). SI units. The thresholds are
#: those :class:`~pneutune.control.rig.supervisor.Supervisor` compares with.
SUP_SLOTS: tuple[tuple[str, int, str], ...] = (
    ("SUP_LAYOUT", 1, "layout id written by pack_supervisor, checked by the C"),
    ("SUP_X_SPAN_LO", 1, "x_min - x_span_margin: lowest reading of a working position sensor [m]"),
    ("SUP_X_SPAN_HI", 1, "x_max + x_span_margin: highest one [m]"),
    ("SUP_P_SENSOR_LO", 1, "p_sensor_min: lowest reading of a working pressure sensor [Pa abs]"),
    ("SUP_P_SENSOR_HI", 1, "p_sensor_max: highest one [Pa abs]"),
    ("SUP_STALE_AGE", 1, "sensor_timeout_s + 1 ns: a channel not new for longer is stale [s]"),
    ("SUP_FREEZE", 1, "freeze_detection: 1 judges repeated pressure values stale, 0 does not"),
    ("SUP_X_LIM_LO", 1, "x_min - x_tolerance: lowest allowed position [m]"),
    ("SUP_X_LIM_HI", 1, "x_max + x_tolerance: highest allowed position [m]"),
    ("SUP_P_MAX", 1, "limits.p_max: highest allowed chamber pressure [Pa abs]"),
    ("SUP_SUPPLY_MIN", 1, "p0 + supply_loss_fraction (p_s_model - p0): supply lost below [Pa abs]"),
    ("SUP_P_S_MODEL", 1, "rig.p_s, the supply pressure of the model [Pa abs]"),
    ("SUP_SUPPLY_WARN_DELTA", 1, "supply_warn_delta [Pa]"),
    ("SUP_SUPPLY_HOLD", 1, "supply_warn_hold_s - 1 ns [s]"),
    ("SUP_THETA_NEAR_LO", 3,
     "theta_min + theta_band (theta_max - theta_min) of the watched theta (M, b_v, A_f)"),
    ("SUP_THETA_NEAR_HI", 3, "theta_max - theta_band (theta_max - theta_min), same order"),
    ("SUP_THETA_HOLD", 1, "theta_hold_s - 1 ns [s]"),
    ("SUP_START_TOL", 1, "largest |x - x_r| at the first sample (the runtime's start_tolerance; "
                         "inf: no check) [m]"),
)

SUP_LAYOUT, SUP_X_SPAN_LO, SUP_X_SPAN_HI, SUP_P_SENSOR_LO, SUP_P_SENSOR_HI = 0, 1, 2, 3, 4
SUP_STALE_AGE, SUP_FREEZE, SUP_X_LIM_LO, SUP_X_LIM_HI, SUP_P_MAX = 5, 6, 7, 8, 9
SUP_SUPPLY_MIN, SUP_P_S_MODEL, SUP_SUPPLY_WARN_DELTA, SUP_SUPPLY_HOLD = 10, 11, 12, 13
SUP_THETA_NEAR_LO, SUP_THETA_NEAR_HI, SUP_THETA_HOLD, SUP_START_TOL = 14, 17, 20, 21

#: The state vector's slots in order: (name, width, meaning). Owned by the caller, written by
#: ``pt_sup_reset`` and the checks; the last two belong to ``pt_controller.c``.
SUP_STATE_SLOTS: tuple[tuple[str, int, str], ...] = (
    ("SUP_S_LAST", 4, "last value of each channel (x, p_a, p_b, p_s), the value rule"),
    ("SUP_S_CHANGED_AT", 4, "time each channel's value last changed [s]"),
    ("SUP_S_STARTED", 1, "1 once the value rule has seen a sample"),
    ("SUP_S_SUPPLY_OFF", 1, "1 while p_s differs from the model's by more than the delta"),
    ("SUP_S_SUPPLY_SINCE", 1, "since when [s]"),
    ("SUP_S_THETA_NEAR", 6, "1 while watched theta j is near bound s (index 2 j + s, s = 0 lower)"),
    ("SUP_S_THETA_SINCE", 6, "since when [s], same index"),
    ("SUP_S_WARNED_SUPPLY", 1, "1 once reidentify_supply was given"),
    ("SUP_S_WARNED_THETA", 6, "1 once reidentify_theta was given for (j, s)"),
    ("SUP_S_FAULT_CHANNEL", 1,
     "channel of the last fault found (CHANNELS), -1: none or not a channel's"),
    ("SUP_S_FIRST_DONE", 1, "pt_controller: 1 once the first sample passed the checks"),
    ("SUP_S_LAW_READY", 1, "pt_controller: 1 once the law state is initialised"),
)

SUP_S_LAST, SUP_S_CHANGED_AT, SUP_S_STARTED, SUP_S_SUPPLY_OFF, SUP_S_SUPPLY_SINCE = 0, 4, 8, 9, 10
SUP_S_THETA_NEAR, SUP_S_THETA_SINCE, SUP_S_WARNED_SUPPLY, SUP_S_WARNED_THETA = 11, 17, 23, 24
SUP_S_FAULT_CHANNEL, SUP_S_FIRST_DONE, SUP_S_LAW_READY = 30, 31, 32


def _offsets(slots: tuple[tuple[str, int, str], ...]) -> int:
    """Check every offset name against its place in ``slots``; the vector's size."""
    index = 0
    names = globals()
    for name, width, _ in slots:
        if names[name] != index:
            raise RuntimeError(f"supervisor_pack: {name} = {names[name]}, but its table puts "
                               f"it at {index}")
        index += width
    return index


#: Length of the settings vector.
SUP_SIZE: int = _offsets(SUP_SLOTS)
#: The same, under its C name.
PT_SUP_SIZE: int = SUP_SIZE
#: Length of the state vector.
SUP_STATE_SIZE: int = _offsets(SUP_STATE_SLOTS)
#: Identifies this layout (of both vectors); changes whenever a slot is added, moved or renamed.
#: Below 2^24, so that a float build (``PT_REAL_FLOAT``) holds it exactly.
SUP_LAYOUT_ID: float = float(2_000_000 + zlib.crc32(
    repr((SUP_SLOTS, SUP_STATE_SLOTS)).encode()) % 1_000_000)

#: Fault codes of the status word, bit i for code i: the supervisor's in their order, then the
#: runtime's start check, then the C-only check of the time and reference.
STATUS_FAULT_CODES: tuple[str, ...] = (*FAULT_CODES, "start_position", "reference_nan")
#: Bit of the first warning; warning i of WARNING_CODES is bit WARN_BIT0 + i.
WARN_BIT0 = 16
#: Bit of the first θ̂ detail: watched θ j (WATCHED_THETA) at bound s (0 lower, 1 upper) is bit
#: THETA_BIT0 + 2 j + s.
THETA_BIT0 = 24
#: Config bits.
BAD_LAYOUT_BIT, BAD_FAIL_SAFE_BIT = 12, 13


def _status_bits() -> dict[str, int]:
    bits = {f"FAULT_{code.upper()}": i for i, code in enumerate(STATUS_FAULT_CODES)}
    bits["STATUS_BAD_LAYOUT"] = BAD_LAYOUT_BIT
    bits["STATUS_BAD_FAIL_SAFE"] = BAD_FAIL_SAFE_BIT
    bits.update({f"WARN_{code.upper()}": WARN_BIT0 + i for i, code in enumerate(WARNING_CODES)})
    for j, i in enumerate(WATCHED_THETA):
        for side, tag in enumerate(("LOW", "HIGH")):
            bits[f"WARN_THETA_{THETA_NAMES[i].upper()}_{tag}"] = THETA_BIT0 + 2 * j + side
    if BAD_LAYOUT_BIT < len(STATUS_FAULT_CODES) or WARN_BIT0 + len(WARNING_CODES) > THETA_BIT0:
        raise RuntimeError("supervisor_pack: the status bits overlap")
    return bits


#: Bit index of every flag of the status word, by its C name without ``PT_``.
STATUS_BITS: dict[str, int] = _status_bits()
#: The fault bits.
FAULT_MASK: int = (1 << len(STATUS_FAULT_CODES)) - 1
#: The warning bits (codes and θ̂ details).
WARN_MASK: int = (((1 << len(WARNING_CODES)) - 1) << WARN_BIT0) | (
    ((1 << 2 * len(WATCHED_THETA)) - 1) << THETA_BIT0)
#: The config bits.
CONFIG_MASK: int = (1 << BAD_LAYOUT_BIT) | (1 << BAD_FAIL_SAFE_BIT)


def pack_supervisor(settings: SupervisorSettings | ControllerConfig, *,
                    start_tolerance: float = START_TOLERANCE) -> np.ndarray:
    """The settings vector the C supervisor reads.

    Parameters
    ----------
    settings : SupervisorSettings or ControllerConfig
        The thresholds; a controller config gives the default ones
        (:meth:`SupervisorSettings.from_controller`).
    start_tolerance : float
        Largest |x(0) - x_r(0)| of the first sample, checked by ``pt_controller_step`` as the
        runtime does (:data:`~pneutune.control.rig.runtime.START_TOLERANCE`; ``math.inf``
        disables the check, as a homing move does) [m].

    Returns
    -------
    (SUP_SIZE,) float64
        The vector, :data:`SUP_LAYOUT_ID` in its first slot.

    Raises
    ------
    ValueError
        ``start_tolerance`` is NaN or negative.
    """
    s = (SupervisorSettings.from_controller(settings) if isinstance(settings, ControllerConfig)
         else settings)
    if not start_tolerance >= 0.0:
        raise ValueError(f"start_tolerance must be >= 0, got {start_tolerance}")
    v = np.zeros(SUP_SIZE)
    v[SUP_LAYOUT] = SUP_LAYOUT_ID
    v[SUP_X_SPAN_LO] = s.x_min - s.x_span_margin
    v[SUP_X_SPAN_HI] = s.x_max + s.x_span_margin
    v[SUP_P_SENSOR_LO], v[SUP_P_SENSOR_HI] = s.p_sensor_range
    v[SUP_STALE_AGE] = s.sensor_timeout_s + _TIME_EPS
    v[SUP_FREEZE] = 1.0 if s.freeze_detection else 0.0
    v[SUP_X_LIM_LO] = s.x_min - s.x_tolerance
    v[SUP_X_LIM_HI] = s.x_max + s.x_tolerance
    v[SUP_P_MAX] = s.p_max
    v[SUP_SUPPLY_MIN] = s.supply_min
    v[SUP_P_S_MODEL] = s.p_s_model
    v[SUP_SUPPLY_WARN_DELTA] = s.supply_warn_delta
    v[SUP_SUPPLY_HOLD] = s.supply_warn_hold_s - _TIME_EPS
    for j, i in enumerate(WATCHED_THETA):
        lo, hi = s.theta_min[i], s.theta_max[i]
        band = s.theta_band * (hi - lo)
        v[SUP_THETA_NEAR_LO + j] = lo + band
        v[SUP_THETA_NEAR_HI + j] = hi - band
    v[SUP_THETA_HOLD] = s.theta_hold_s - _TIME_EPS
    v[SUP_START_TOL] = start_tolerance
    return v


def pack_fail_safe(mode: str | Sequence[float] = "hold") -> np.ndarray:
    """The fail-safe duties of ``pt_config_t``: a mode of
    :data:`~pneutune.control.rig.supervisor.FAIL_SAFE_MODES` or four duties.

    Parameters
    ----------
    mode : str or sequence of 4 float
        ``hold`` (all valves closed), ``exhaust``, or ``[a_in, a_out, b_in, b_out]``.

    Returns
    -------
    (4,) float64

    Raises
    ------
    ValueError
        An unknown mode, or duties that are not four values in [0, 1].
    """
    if isinstance(mode, str):
        if mode not in FAIL_SAFE_MODES:
            raise ValueError(f"fail-safe mode must be one of {tuple(FAIL_SAFE_MODES)}, "
                             f"got {mode!r}")
        return np.array(FAIL_SAFE_MODES[mode], dtype=np.float64)
    duties = np.asarray(mode, dtype=np.float64)
    if duties.shape != (4,) or not np.all((duties >= 0.0) & (duties <= 1.0)):
        raise ValueError(f"fail-safe duties must be 4 values in [0, 1], got {mode!r}")
    return duties


def status_codes(status: int) -> tuple[str, ...]:
    """The names of the flags set in a status word (faults, config, warnings, θ̂ details).

    Parameters
    ----------
    status : int
        What ``pt_sup_check_*`` or ``pt_controller_step`` returned.

    Returns
    -------
    tuple of str
        Fault and warning codes as in Python (``sensor_nan``, ``reidentify_theta``, ...),
        ``bad_layout``, ``bad_fail_safe``, and ``theta_<name>_<low|high>`` for the details, in
        bit order.
    """
    out = []
    for name, bit in sorted(STATUS_BITS.items(), key=lambda item: item[1]):
        if status >> bit & 1:
            out.append(name.split("_", 1)[1].lower())
    return tuple(out)


def first_fault(status: int) -> str | None:
    """The fault code of a status word (its lowest fault bit), None without a fault."""
    faults = status & FAULT_MASK
    if not faults:
        return None
    return STATUS_FAULT_CODES[(faults & -faults).bit_length() - 1]


def _slot_lines(slots: tuple[tuple[str, int, str], ...]) -> list[str]:
    names = globals()
    return [define(name, str(names[name]), f"[{width}] {meaning}")
            for name, width, meaning in slots]


def _names_init(names: Sequence[str]) -> str:
    return "{" + ", ".join(f'"{n}"' for n in names) + "}"


def sup_layout_header() -> str:
    """The text of ``pt_sup_layout.h``, generated from the Python tables.

    Returns
    -------
    str
        The header: the ``SUP_*`` offsets of the settings vector with ``SUP_SIZE`` and
        ``SUP_LAYOUT_ID``, the ``SUP_S_*`` offsets of the state vector with
        ``SUP_STATE_SIZE``, the channel indices, the watched θ̂ indices, and every bit of the
        status word with its masks and the fault names, each as a ``#define PT_<name>`` line.
    """
    lines = [
        "/* pt_sup_layout.h: slots of the supervisor's flat vectors and bits of its status word.",
        " *",
        " * Generated by `python -m pneutune.control.rig.supervisor_pack` from",
        " * control/rig/supervisor_pack.py and control/rig/supervisor.py; do not edit (`--check`",
        " * compares).",
        " */",
        "#ifndef PT_SUP_LAYOUT_H",
        "#define PT_SUP_LAYOUT_H",
        "",
        "/* settings vector (supervisor_pack.SUP_SLOTS): offset, then width and meaning */",
        *_slot_lines(SUP_SLOTS),
        define("SUP_SIZE", str(SUP_SIZE), "length of the settings vector"),
        define("SUP_LAYOUT_ID", c_double(SUP_LAYOUT_ID), "sup[PT_SUP_LAYOUT] of this layout"),
        "",
        "/* state vector (supervisor_pack.SUP_STATE_SLOTS): offset, then width and meaning */",
        *_slot_lines(SUP_STATE_SLOTS),
        define("SUP_STATE_SIZE", str(SUP_STATE_SIZE), "length of the state vector"),
        "",
        "/* sensor channels (supervisor.CHANNELS), the order of the sensors array */",
        *[define(f"CH_{name.upper()}", str(i)) for i, name in enumerate(CHANNELS)],
        "",
        "/* theta indices watched for a bound (supervisor.WATCHED_THETA): "
        + ", ".join(ascii_comment(THETA_NAMES[i]) for i in WATCHED_THETA) + " */",
        define("SUP_N_WATCHED", str(len(WATCHED_THETA))),
        define("SUP_WATCHED_THETA_INIT", "{" + ", ".join(str(i) for i in WATCHED_THETA) + "}"),
        "",
        "/* status word: one bit per flag; the fault bits in the order they are checked",
        " * (supervisor.FAULT_CODES, then start_position, then reference_nan) */",
    ]
    for name, bit in sorted(STATUS_BITS.items(), key=lambda item: item[1]):
        lines.append(define(name, f"0x{1 << bit:08X}UL", f"bit {bit}"))
    lines += [
        define("FAULT_MASK", f"0x{FAULT_MASK:08X}UL", "every fault bit"),
        define("WARN_MASK", f"0x{WARN_MASK:08X}UL", "every warning bit, details included"),
        define("STATUS_CONFIG_MASK", f"0x{CONFIG_MASK:08X}UL", "the config bits"),
        define("WARN_THETA_BIT0", str(THETA_BIT0), "bit of watched theta j at bound s: + 2 j + s"),
        define("FAULT_COUNT", str(len(STATUS_FAULT_CODES)), "fault bits 0 .. FAULT_COUNT - 1"),
        define("FAULT_NAMES_INIT", _names_init(STATUS_FAULT_CODES), "by fault bit"),
        "",
        "#endif /* PT_SUP_LAYOUT_H */",
        "",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Write ``pt_sup_layout.h``, or with ``--check`` compare it with the tables
    (:func:`~pneutune.control.law.c_header.header_main`)."""
    return header_main(argv, "python -m pneutune.control.rig.supervisor_pack",
                       "Generate pt_sup_layout.h, the C slots and status bits of the supervisor, "
                       "from the Python tables.", sup_layout_header, HEADER_PATH)


__all__ = [
    "CONFIG_MASK", "FAULT_MASK", "HEADER_PATH", "PT_SUP_SIZE", "STATUS_BITS", "STATUS_FAULT_CODES",
    "SUP_LAYOUT_ID", "SUP_SIZE", "SUP_SLOTS", "SUP_STATE_SIZE", "SUP_STATE_SLOTS", "WARN_MASK",
    "first_fault", "main", "pack_fail_safe", "pack_supervisor", "status_codes",
    "sup_layout_header",
]

if __name__ == "__main__":
    raise SystemExit(main())
