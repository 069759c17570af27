"""The wire format of the pipe protocol ``pneutune.rig/1``: frames, limits, the hello, errors.

The deploy runtime talks to a rig through :class:`pneutune.control.rig.protocol.Rig`. A rig
driver can implement that protocol as a Python class, or run as a program of its own that
answers the pipe protocol below on its stdin/stdout: a C program on a DAQ card, a Rust driver
on a fieldbus, a Python script on a serial port. The modules speaking it:

* the client: :class:`~pneutune.control.rig.driver_process.DriverProcess` (one driver program
  on two pipes: bounded, timed replies, its stderr tail), and in
  :mod:`pneutune.control.rig.exec_rig` the :class:`~pneutune.control.rig.protocol.Rig` over it,
  :class:`~pneutune.control.rig.exec_rig.ExecRig` (``deploy --rig exec:CMD``), and
  :class:`~pneutune.control.rig.exec_rig.PipeRig` (the example simulated rig in a child
  process, with ``truth()``: ``deploy --rig pipe-sim``);
* the example server: :func:`pneutune.control.rig.pipe_server.serve` answers the protocol for
  :class:`~pneutune.control.rig.deploy_simrig.DeploySimRig`, the simulated rig in process
  (``python -m pneutune.control.driver serve``);
* :mod:`pneutune.control.rig.conformance` checks that a driver program speaks the protocol
  (``python -m pneutune.control.driver check CMD``).

Pipe protocol (``pneutune.rig/1``)
----------------------------------
Binary, little-endian, over the server's stdin (requests) and stdout (replies); stderr is
prose. Every request is one opcode byte and a fixed-size payload; every reply starts with
``K`` (ok) or ``E`` (error, then ``<I`` length and at most 4096 bytes of UTF-8 message; the
server then writes the fail-safe duties, all valves closed, and exits with status 1).

==========  ======================  ===========================================================
request     payload                 reply after ``K``
==========  ======================  ===========================================================
``H``       (none)                  ``<I`` length, JSON (< 64 KiB): ``protocol``, ``Ts``, ``rig``
``R``       (none)                  ``<9d``: t, x, p_a, p_b, p_s, 4 sample times
``W``       ``<4d`` duties          (nothing); a duty outside [0, 1] (or NaN) gets ``E``
``A``       (none)                  ``<d``: the new t
``T``       (none)                  ``<6d``: /sim/truth fields (simulated rigs only)
``C``       (none)                  (nothing); the server writes the fail-safe duties, exits 0
==========  ======================  ===========================================================

An unknown opcode gets ``E``. End of input (the client is gone) makes the server write the
fail-safe duties and exit 0. The hello's ``Ts`` is the period the driver samples and
ticks at (``A``); its ``rig`` is the rig block: every key of
:data:`~pneutune.control.constants.RIG_KEYS` (optionally the hints of
:data:`~pneutune.control.constants.RIG_HINT_KEYS`), whose ``rig.Ts`` is the control period the
rig is built for. ``Ts`` must divide ``rig.Ts`` into whole samples: a data-acquisition card may
sample faster than the valves are updated (``record --sample-period``), while ``deploy`` runs
the controller at every sample and requires ``Ts == rig.Ts``. Sample
times are NaN for a channel that never delivered. Doubles travel as IEEE 754 bits, so a run
across the pipe gives bit-identical numbers to the same run in process. The client waits at
most ``startup_timeout`` for the hello and ``timeout`` for every later reply
(:class:`RigIOError`). Only pipes to a child process: nothing listens on a network.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from typing import Any

from pydantic import ValidationError

from pneutune.control.constants import RIG_HINT_KEYS, RIG_HINT_RANGES, RIG_KEYS
from pneutune.control.contracts.plant import RigConfig
from pneutune.control.contracts.yamlio import validation_error
from pneutune.control.errors import PneutuneError

PROTOCOL = "pneutune.rig/1"
#: Default longest wait for a reply after the hello [s].
DEFAULT_TIMEOUT = 2.0
#: Default longest wait for the hello [s]: a driver program starts (a Python one imports its
#: libraries, about 1 s for the example server on a busy 2-core machine) and opens its hardware.
#: The example server also builds its simulated plant before it answers, which compiles the
#: plant's code when numba's cache does not hold it yet (after an install or an upgrade): up to
#: half a minute on a loaded 2-core machine, measured at over 10 s.
DEFAULT_STARTUP_TIMEOUT = 60.0
#: Largest hello and error message [bytes].
MAX_HELLO = 64 * 1024
MAX_ERROR = 4096
#: Frames of the protocol: the reply to R, the payload of W, the replies to A and T, a length.
FRAME_READ = struct.Struct("<9d")
FRAME_DUTIES = struct.Struct("<4d")
FRAME_TIME = struct.Struct("<d")
FRAME_TRUTH = struct.Struct("<6d")
FRAME_LENGTH = struct.Struct("<I")


class RigIOError(PneutuneError, OSError):
    """The rig did not answer, answered garbage, or reported an error."""


class RigErrorReply(RigIOError):
    """The driver answered a request with ``E``; :attr:`message` is its text."""

    def __init__(self, message: str) -> None:
        self.message = message
        super().__init__(f"the driver replied with an error: {message}")


def parse_hello(body: bytes) -> tuple[float, Mapping[str, Any]]:
    """The sampling period and the (unchecked) rig block of a hello reply.

    Parameters
    ----------
    body : bytes
        The JSON after ``K`` and the length.

    Returns
    -------
    (Ts, rig)
        ``Ts`` [s], finite and positive; ``rig`` the JSON object (see :func:`check_rig_block`).

    Raises
    ------
    RigIOError
        Not a JSON object, another protocol, no usable ``Ts`` or no ``rig`` object.
    """
    try:
        meta = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RigIOError(f"hello: not UTF-8 JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise RigIOError(f"hello: expected a JSON object, got {type(meta).__name__}")
    if meta.get("protocol") != PROTOCOL:
        raise RigIOError(f"hello: protocol must be {PROTOCOL!r}, got {meta.get('protocol')!r}")
    Ts = meta.get("Ts")
    if isinstance(Ts, bool) or not isinstance(Ts, (int, float)) or not (
            math.isfinite(Ts) and Ts > 0.0):
        raise RigIOError(f"hello: Ts must be a positive number of seconds, got {Ts!r}")
    rig = meta.get("rig")
    if not isinstance(rig, dict):
        raise RigIOError(f"hello: rig must be a JSON object (the rig block), got {rig!r}")
    return float(Ts), rig


def check_rig_block(rig: Mapping[str, Any], Ts: float) -> dict[str, float | str]:
    """The hello's rig block, complete and valid, as the run log stores it.

    Parameters
    ----------
    rig : mapping
        The hello's ``rig`` object.
    Ts : float
        The hello's ``Ts`` [s], the driver's sample period; it must divide ``rig.Ts`` (the
        control period) into whole samples.

    Returns
    -------
    dict
        Every key of ``RIG_KEYS`` (floats, and ``pwm_update``), then any hint of
        ``RIG_HINT_KEYS``.

    Raises
    ------
    RigIOError
        A missing or unknown key, a value of the wrong type or out of the contract's range
        (:class:`~pneutune.control.contracts.plant.RigConfig`), or a ``Ts`` that does not
        divide ``rig.Ts``.
    """
    missing = [k for k in RIG_KEYS if k not in rig]
    if missing:
        raise RigIOError(f"hello: the rig block lacks {', '.join(missing)} (it must have "
                         f"every key of {', '.join(RIG_KEYS)})")
    unknown = sorted(set(rig) - set(RIG_KEYS) - set(RIG_HINT_KEYS))
    if unknown:
        raise RigIOError(f"hello: the rig block has unknown key(s) {', '.join(unknown)}")
    try:
        block = RigConfig.model_validate({k: rig[k] for k in RIG_KEYS})
    except ValidationError as exc:
        raise RigIOError(str(validation_error("hello", exc, prefix="rig"))) from None
    if block.Ts != Ts and not divides(Ts, block.Ts):
        raise RigIOError(f"hello: Ts = {Ts!r} s (the sample period) must divide rig.Ts = "
                         f"{block.Ts!r} s (the control period) into whole samples")
    out: dict[str, float | str] = {k: getattr(block, k) for k in RIG_KEYS}
    for k in RIG_HINT_KEYS:
        if k in rig:
            v = rig[k]
            lo, hi, unit = RIG_HINT_RANGES[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (
                    math.isfinite(v) and lo <= v <= hi):
                raise RigIOError(f"hello: rig.{k} must be a number of {unit} within "
                                 f"[{lo:g}, {hi:g}], got {v!r}")
            out[k] = float(v)
    return out


def divides(sample_period: float, Ts: float) -> bool:
    """Whether ``sample_period`` divides ``Ts`` into a whole number of samples (to 1e-9).

    Parameters
    ----------
    sample_period : float
        The candidate sample period [s].
    Ts : float
        The period it must divide [s].

    Returns
    -------
    bool
        True when ``sample_period`` is finite, positive, at most ``Ts`` and a whole fraction of
        it, to a relative 1e-9.
    """
    if not (math.isfinite(sample_period) and 0.0 < sample_period <= Ts * (1.0 + 1e-9)):
        return False
    k = round(Ts / sample_period)
    return abs(k * sample_period - Ts) <= 1e-9 * Ts


__all__ = ["DEFAULT_STARTUP_TIMEOUT", "DEFAULT_TIMEOUT", "FRAME_DUTIES", "FRAME_LENGTH",
           "FRAME_READ", "FRAME_TIME", "FRAME_TRUTH", "MAX_ERROR", "MAX_HELLO", "PROTOCOL",
           "RigErrorReply", "RigIOError", "check_rig_block", "divides", "parse_hello"]
