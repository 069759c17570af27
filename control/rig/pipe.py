"""The pipe protocol ``pneutune.rig/1``: a rig driver as a program of its own, in any language.

The deploy runtime talks to a rig through :class:`pneutune.control.rig.protocol.Rig`. A rig
driver can implement that protocol as a Python class, or run as a program of its own that
answers the pipe protocol below on its stdin/stdout: a C program on a DAQ card, a Rust driver
on a fieldbus, a Python script on a serial port. This module holds both ends:

* the client: :class:`DriverProcess` (one driver program on two pipes: bounded, timed replies,
  its stderr tail), :class:`ExecRig` (the :class:`~pneutune.control.rig.protocol.Rig` over it,
  ``deploy --rig exec:CMD``) and :class:`PipeRig` (the example simulated rig in a child
  process, with ``truth()``: ``deploy --rig pipe-sim``);
* the example server: :func:`serve` answers the protocol for :class:`DeploySimRig`, the
  simulated rig in process (``python -m pneutune.control.driver serve``).

:mod:`pneutune.control.rig.conformance` checks that a driver program speaks the protocol
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

import argparse
import json
import math
import os
import re
import select
import shlex
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any, BinaryIO

import numpy as np
from pydantic import ValidationError

from pneutune.control.constants import RIG_HINT_KEYS, RIG_KEYS
from pneutune.control.contracts.plant import PlantConfig, RigConfig
from pneutune.control.contracts.yamlio import validation_error
from pneutune.control.errors import ExperimentError, PneutuneError
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import PlantParams
from pneutune.control.rig.simrig import SimRig

PROTOCOL = "pneutune.rig/1"
#: Default longest wait for a reply after the hello [s].
DEFAULT_TIMEOUT = 2.0
#: Default longest wait for the hello [s]: a driver program starts (a Python one imports its
#: libraries, about 1 s for the example server on a busy 2-core machine) and opens its hardware.
DEFAULT_STARTUP_TIMEOUT = 10.0
#: Placeholders a driver command may contain, replaced for each run: the scenario's name
#: (``deploy``) or the experiment's (``record``), the noise seed of a simulated rig, and the
#: sample period the client asks for [s].
COMMAND_PLACEHOLDERS: tuple[str, ...] = ("scenario", "seed", "sample_period")
#: Experiment names ``record`` puts in ``{scenario}``: the example server runs the plant as it is.
EXPERIMENTS: tuple[str, ...] = ("identification", "commissioning")
#: Largest hello and error message [bytes].
MAX_HELLO = 64 * 1024
MAX_ERROR = 4096
#: Frames of the protocol: the reply to R, the payload of W, the replies to A and T, a length.
FRAME_READ = struct.Struct("<9d")
FRAME_DUTIES = struct.Struct("<4d")
FRAME_TIME = struct.Struct("<d")
FRAME_TRUTH = struct.Struct("<6d")
FRAME_LENGTH = struct.Struct("<I")
_TAIL_LINES = 20
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")


class RigIOError(PneutuneError, OSError):
    """The rig did not answer, answered garbage, or reported an error."""


class RigErrorReply(RigIOError):
    """The driver answered a request with ``E``; :attr:`message` is its text."""

    def __init__(self, message: str) -> None:
        self.message = message
        super().__init__(f"the driver replied with an error: {message}")


class DeploySimRig(SimRig):
    """The in-process simulated rig as deploy and the example server use it.

    A :class:`~pneutune.control.rig.simrig.SimRig` whose compiled calls are loaded before the
    first sample (so a paced run's first sample is on time) and which keeps the duties last
    written (:attr:`last_duties`). Every :meth:`read` is a new sample on every channel. The
    sensor noise is drawn four standard normals per read from ``default_rng(seed)``, the same
    sequence as :func:`pneutune.control.sim.closed_loop.simulate_scenario` draws as one
    ``(n, 4)`` block, so a deploy run and a ``simulate`` run with the same seed see the same
    noise.

    Parameters
    ----------
    plant_cfg : PlantConfig or PlantParams
        The plant (with any scenario changes already merged).
    x0 : float, optional
        Initial position [m]; default mid-stroke. At rest, pressures in force balance.
    pressures0 : (float, float), optional
        Initial (p_a, p_b) [Pa abs].
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.
    sample_period : float, optional
        Sample period [s], dividing the plant's ``rig.Ts`` (:class:`SimRig`).
    """

    def __init__(self, plant_cfg: PlantConfig | PlantParams, x0: float | None = None,
                 pressures0: tuple[float, float] | None = None, seed: int | None = None,
                 sample_period: float | None = None) -> None:
        super().__init__(plant_cfg, x0=x0, pressures0=pressures0, seed=seed,
                         sample_period=sample_period)
        self.last_duties = np.zeros(4)
        self._warm_up()

    def _warm_up(self) -> None:
        """Run every compiled plant call once on a copy of the state (no noise drawn, no
        change to the rig), so that loading the compiled code does not delay the first
        sample of a paced run."""
        p = self.params
        s = self.state.copy()
        out = np.zeros(4)
        plant.measure(p.vec, s, self.supply, np.zeros(4), out)
        plant.truth(p.vec, s, self.supply, p.force_steps, np.zeros(6))
        plant.set_duties(p.vec, s, 0.0, np.zeros(4))
        plant.advance(p.vec, s, self.Ts, self.supply, p.force_steps)

    def write(self, duties: np.ndarray) -> None:
        """Command the four duties from now on (kept in :attr:`last_duties`)."""
        d = np.ascontiguousarray(duties, dtype=np.float64)
        self.last_duties = d.copy()
        super().write(d)


# ---------------------------------------------------------------------------------------------
# The hello and the driver command
# ---------------------------------------------------------------------------------------------


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
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (
                    math.isfinite(v) and v > 0.0):
                raise RigIOError(f"hello: rig.{k} must be a positive number, got {v!r}")
            out[k] = float(v)
    return out


def divides(sample_period: float, Ts: float) -> bool:
    """Whether ``sample_period`` divides ``Ts`` into a whole number of samples (to 1e-9)."""
    if not (math.isfinite(sample_period) and 0.0 < sample_period <= Ts * (1.0 + 1e-9)):
        return False
    k = round(Ts / sample_period)
    return abs(k * sample_period - Ts) <= 1e-9 * Ts


def exec_command(template: str, scenario: str, seed: int,
                 sample_period: float | None = None) -> list[str]:
    """The argument list of a driver command for one run.

    ``{scenario}``, ``{seed}`` and ``{sample_period}`` in ``template`` are replaced by the
    scenario's (or the experiment's) name, the seed and the sample period in seconds, then the
    text is split like a POSIX shell would (:func:`shlex.split`; no shell runs). A simulated or
    test rig needs them; a hardware driver may ignore them.

    Parameters
    ----------
    template : str
        E.g. ``"python -m pneutune.control.driver serve --scenario {scenario} --seed {seed}"``.
    scenario : str
        Scenario name (``deploy``) or experiment name (``record``).
    seed : int
        Sensor-noise seed of a simulated rig.
    sample_period : float, optional
        The period the driver is asked to sample at [s]; required when ``template`` contains
        ``{sample_period}``.

    Returns
    -------
    list of str

    Raises
    ------
    ExperimentError
        An empty command, unbalanced quotes, a placeholder other than those of
        :data:`COMMAND_PLACEHOLDERS`, or ``{sample_period}`` without a sample period.
    """
    found = _PLACEHOLDER.findall(template)
    unknown = [m for m in found if m not in COMMAND_PLACEHOLDERS]
    if unknown:
        raise ExperimentError(f"driver command {template!r}: unknown placeholder "
                              f"{{{unknown[0]}}}; it may contain "
                              + ", ".join(f"{{{p}}}" for p in COMMAND_PLACEHOLDERS))
    text = template.replace("{scenario}", scenario).replace("{seed}", str(int(seed)))
    if "sample_period" in found:
        if sample_period is None:
            raise ExperimentError(f"driver command {template!r}: {{sample_period}} needs a "
                                  f"sample period: give --sample-period S")
        text = text.replace("{sample_period}", repr(float(sample_period)))
    try:
        argv = shlex.split(text)
    except ValueError as exc:
        raise ExperimentError(f"driver command {template!r}: {exc}") from None
    if not argv:
        raise ExperimentError("driver command is empty: give the program to start, e.g. "
                              "exec:\"./rig_driver --port /dev/ttyUSB0\"")
    return argv


def sim_server_command(plant: str | os.PathLike[str] | None = None, scenario: str | None = None,
                       seed: int | None = None, sample_period: float | None = None) -> list[str]:
    """The command that starts the example rig server (this interpreter, this package)."""
    cmd = [sys.executable, "-m", "pneutune.control.driver", "serve"]
    if plant is not None:
        cmd += ["--plant", os.fspath(plant)]
    if scenario is not None:
        cmd += ["--scenario", scenario]
    if seed is not None:
        cmd += ["--seed", str(int(seed))]
    if sample_period is not None:
        cmd += ["--sample-period", repr(float(sample_period))]
    return cmd


# ---------------------------------------------------------------------------------------------
# Client
# ---------------------------------------------------------------------------------------------


class DriverProcess:
    """One driver program on the other end of two pipes: requests, timed replies, stderr.

    A thread keeps the last lines of the program's stderr (so a chatty driver never blocks on
    a full pipe, and an error names what the driver said last).

    Parameters
    ----------
    command : sequence of str
        Program and arguments (no shell).

    Raises
    ------
    RigIOError
        The program cannot be started (not there, not executable).
    """

    def __init__(self, command: Sequence[str]) -> None:
        self.command = list(command)
        try:
            # a session of its own: a Ctrl-C at the terminal reaches the client alone, which
            # then commands the fail-safe duties and closes the driver in order
            self._proc = subprocess.Popen(self.command, stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          bufsize=0, start_new_session=True)
        except OSError as exc:
            raise RigIOError(f"cannot start the rig driver `{shlex.join(self.command)}`: "
                             f"{exc.strerror or exc}") from None
        if (self._proc.stdin is None or self._proc.stdout is None
                or self._proc.stderr is None):  # pragma: no cover - PIPE always gives them
            raise RigIOError(f"cannot open pipes to {self.command}")
        self._in: BinaryIO = self._proc.stdin
        self._out: BinaryIO = self._proc.stdout
        self._rbuf = bytearray()
        self._tail: deque[str] = deque(maxlen=_TAIL_LINES)
        self._tail_thread = threading.Thread(target=self._drain_stderr, args=(self._proc.stderr,),
                                             daemon=True)
        self._tail_thread.start()

    def _drain_stderr(self, err: BinaryIO) -> None:
        with err:
            for line in iter(err.readline, b""):
                text = line.decode("utf-8", "replace").strip()
                if text:
                    self._tail.append(text)

    @property
    def returncode(self) -> int | None:
        """Exit status, or None while the program runs."""
        return self._proc.poll()

    def stderr_tail(self, lines: int = 3) -> str:
        """The last ``lines`` non-empty lines the program wrote on stderr, joined by `` | ``."""
        return " | ".join(list(self._tail)[-lines:])

    def _ended(self) -> str:
        """`` (exit status N): <stderr tail>`` once the program has ended (waits up to 1 s)."""
        try:
            rc: int | None = self._proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            rc = None
        self._tail_thread.join(timeout=0.5)
        tail = self.stderr_tail()
        return (f" (exit status {rc})" if rc is not None else "") + (f": {tail}" if tail else "")

    def send(self, data: bytes) -> None:
        """Write one request.

        Raises
        ------
        RigIOError
            The program is gone (its stdin is closed).
        """
        try:
            self._in.write(data)
            self._in.flush()
        except (BrokenPipeError, OSError, ValueError) as exc:
            raise RigIOError(f"the driver is gone ({exc}){self._ended()}") from None

    def _recv(self, n: int, deadline: float, timeout: float) -> bytes:
        fd = self._out.fileno()
        while len(self._rbuf) < n:
            ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                raise RigIOError(f"no reply from the driver within {timeout:g} s")
            chunk = os.read(fd, 65536)
            if not chunk:
                raise RigIOError(f"the driver closed its output{self._ended()}")
            self._rbuf += chunk
        data = bytes(self._rbuf[:n])
        del self._rbuf[:n]
        return data

    def reply(self, size: int | None, timeout: float) -> bytes:
        """Read one reply and return its body.

        Parameters
        ----------
        size : int or None
            Body size after ``K`` [bytes]; None: a ``<I`` length, then that many bytes
            (at most 64 KiB).
        timeout : float
            Longest wait for the whole reply [s].

        Raises
        ------
        RigErrorReply
            The reply was ``E``.
        RigIOError
            No (complete) reply within ``timeout``, end of output, a bad status byte or an
            oversized body.
        """
        deadline = time.monotonic() + timeout
        status = self._recv(1, deadline, timeout)
        if status == b"E":
            (length,) = FRAME_LENGTH.unpack(self._recv(FRAME_LENGTH.size, deadline, timeout))
            if length > MAX_ERROR:
                raise RigIOError(f"the driver's error message of {length} bytes exceeds "
                                 f"{MAX_ERROR}")
            raise RigErrorReply(self._recv(length, deadline, timeout).decode("utf-8", "replace"))
        if status != b"K":
            raise RigIOError(f"the driver replied with status {status!r}, expected b'K' or b'E'")
        if size is None:
            (length,) = FRAME_LENGTH.unpack(self._recv(FRAME_LENGTH.size, deadline, timeout))
            if length > MAX_HELLO:
                raise RigIOError(f"the driver's reply of {length} bytes exceeds {MAX_HELLO}")
            return self._recv(length, deadline, timeout)
        return self._recv(size, deadline, timeout) if size else b""

    def close_input(self) -> None:
        """Close the program's stdin (end of input: it must close its valves and exit)."""
        try:
            self._in.close()
        except OSError:
            pass

    def wait(self, timeout: float) -> int | None:
        """The exit status once the program has ended, or None if it runs after ``timeout`` s."""
        try:
            return self._proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def end(self, timeout: float) -> int:
        """End the session: end of input, ``timeout`` s to exit by itself, else kill.

        Returns
        -------
        int
            The exit status (negative: killed by that signal).
        """
        self.close_input()
        rc = self.wait(timeout)
        if rc is None:
            self._proc.kill()
            rc = self._proc.wait(timeout=5.0)
        self._out.close()
        self._tail_thread.join(timeout=0.5)
        return rc


class ExecRig:
    """A :class:`~pneutune.control.rig.protocol.Rig` whose driver is a program of its own.

    The program speaks the pipe protocol (module docstring) on its stdin/stdout; it is started
    here, greeted (``H``) and its hello checked (:func:`check_rig_block`).

    Parameters
    ----------
    command : sequence of str
        Program and arguments (:func:`exec_command` makes them from a ``--rig exec:`` text).
    timeout : float
        Longest wait for a reply after the hello [s].
    startup_timeout : float
        Longest wait for the hello [s].

    Raises
    ------
    RigIOError
        The program is not there, dies before it answers, answers late or with a bad hello;
        the message names the command and ends with the program's stderr tail.

    Notes
    -----
    Use as a context manager (or call :meth:`close`): closing sends ``C`` (fail-safe duties)
    and waits for the program to exit. After an error reply or a timeout the client closes
    the program's stdin, gives it ``timeout`` to close its valves and exit, then kills it.
    """

    def __init__(self, command: Sequence[str], timeout: float = DEFAULT_TIMEOUT,
                 startup_timeout: float = DEFAULT_STARTUP_TIMEOUT) -> None:
        self.command = list(command)
        self.timeout = float(timeout)
        self.closed = False
        self.t = 0.0
        self._stamps = np.zeros(4)
        self._duties_buf = bytearray(1 + FRAME_DUTIES.size)
        self._duties_buf[0:1] = b"W"
        self._driver = DriverProcess(self.command)
        try:
            body = self._request(b"H", None, startup_timeout)
            Ts, rig = parse_hello(body)
            self._rig_meta = check_rig_block(rig, Ts)
        except RigIOError as exc:
            self._end()
            raise RigIOError(f"rig driver `{shlex.join(self.command)}` failed at its hello: "
                             f"{exc}") from None
        self.Ts = Ts

    def _end(self) -> None:
        if not self.closed:
            self.closed = True
            self._driver.end(self.timeout)

    def _request(self, request: bytes, size: int | None, timeout: float | None = None) -> bytes:
        """Send ``request`` (opcode and payload); return the reply body (see
        :meth:`DriverProcess.reply`). Any failure ends the driver."""
        if self.closed:
            raise RigIOError("the rig is closed")
        try:
            self._driver.send(request)
            return self._driver.reply(size, self.timeout if timeout is None else timeout)
        except RigIOError:
            self._end()
            raise

    def read(self) -> np.ndarray:
        """Sensors at the current sample [x, p_a, p_b, p_s]."""
        vals = FRAME_READ.unpack(self._request(b"R", FRAME_READ.size))
        self.t = vals[0]
        self._stamps = np.array(vals[5:9])
        return np.array(vals[1:5])

    def sample_times(self) -> np.ndarray | None:
        """Sample times reported with the last :meth:`read`."""
        return self._stamps.copy()

    def write(self, duties: np.ndarray) -> None:
        """Command the four duties."""
        d = np.asarray(duties, dtype=np.float64)
        FRAME_DUTIES.pack_into(self._duties_buf, 1, d[0], d[1], d[2], d[3])
        self._request(bytes(self._duties_buf), 0)

    def advance(self) -> None:
        """Move to the next sample."""
        (self.t,) = FRAME_TIME.unpack(self._request(b"A", FRAME_TIME.size))

    def rig_metadata(self) -> dict[str, float | str]:
        """The driver's ``rig`` block, from its hello."""
        return dict(self._rig_meta)

    def close(self) -> None:
        """Fail-safe duties (``C``), then let the driver exit; idempotent."""
        if self.closed:
            return
        try:
            self._request(b"C", 0)
        except RigIOError:
            return  # _request has ended the driver
        self._end()

    def __enter__(self) -> ExecRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PipeRig(ExecRig):
    """The example simulated rig in a child process: an :class:`ExecRig` with ``truth()``.

    A :class:`~pneutune.control.rig.protocol.SimulatedRig` (``deploy --rig pipe-sim``).

    Parameters
    ----------
    command : sequence of str, optional
        The server command; default :func:`sim_server_command` of the other arguments.
    plant : path-like, optional
        plant.yaml of the simulated rig (default: the paper's rig).
    scenario : str, optional
        Scenario whose plant changes (payload, force steps) the simulated rig applies; the
        piston then starts at rest where the scenario's reference starts.
    seed : int, optional
        Sensor-noise seed.
    timeout, startup_timeout : float
        As :class:`ExecRig` [s].
    sample_period : float, optional
        The server's sample period [s], dividing the plant's ``rig.Ts``; default ``rig.Ts``.
    """

    def __init__(self, command: Sequence[str] | None = None,
                 plant: str | os.PathLike[str] | None = None, scenario: str | None = None,
                 seed: int | None = None, timeout: float = DEFAULT_TIMEOUT,
                 startup_timeout: float = DEFAULT_STARTUP_TIMEOUT,
                 sample_period: float | None = None) -> None:
        super().__init__(command if command is not None
                         else sim_server_command(plant, scenario, seed, sample_period),
                         timeout=timeout, startup_timeout=startup_timeout)

    def truth(self) -> np.ndarray:
        """The simulated rig's ``/sim/truth`` fields at the current sample."""
        return np.array(FRAME_TRUTH.unpack(self._request(b"T", FRAME_TRUTH.size)))

    def __enter__(self) -> PipeRig:
        return self


# ---------------------------------------------------------------------------------------------
# Server
# ---------------------------------------------------------------------------------------------


def _reply_error(out: BinaryIO, message: str) -> None:
    body = message.encode("utf-8")[:MAX_ERROR]
    out.write(b"E" + FRAME_LENGTH.pack(len(body)) + body)
    out.flush()


def _read_exact(inp: BinaryIO, n: int) -> bytes | None:
    data = b""
    while len(data) < n:
        chunk = inp.read(n - len(data))
        if not chunk:
            return None
        data += chunk
    return data


def serve(rig: DeploySimRig, inp: BinaryIO, out: BinaryIO) -> int:
    """Answer pipe-protocol requests for ``rig`` until ``C`` or end of input.

    Whatever ends the session (``C``, end of input, a bad request), the rig's fail-safe duties
    are written last.

    Parameters
    ----------
    rig : DeploySimRig
        The rig served.
    inp, out : binary file objects
        Requests in, replies out.

    Returns
    -------
    int
        0 after ``C`` or end of input, 1 after a protocol error.
    """
    hello = json.dumps({"protocol": PROTOCOL, "Ts": rig.Ts,
                        "rig": rig.rig_metadata()}).encode("utf-8")
    try:
        while True:
            op = inp.read(1)
            if not op:
                return 0
            if op == b"R":
                vals = rig.read()
                st = rig.sample_times()
                out.write(b"K" + FRAME_READ.pack(rig.t, *vals.tolist(), *st.tolist()))
            elif op == b"W":
                raw = _read_exact(inp, FRAME_DUTIES.size)
                if raw is None:
                    return 0
                d = np.array(FRAME_DUTIES.unpack(raw))
                if not np.all((d >= 0.0) & (d <= 1.0)):
                    _reply_error(out, f"duties must be in [0, 1], got {d.tolist()}")
                    return 1
                rig.write(d)
                out.write(b"K")
            elif op == b"A":
                rig.advance()
                out.write(b"K" + FRAME_TIME.pack(rig.t))
            elif op == b"T":
                out.write(b"K" + FRAME_TRUTH.pack(*rig.truth().tolist()))
            elif op == b"H":
                out.write(b"K" + FRAME_LENGTH.pack(len(hello)) + hello)
            elif op == b"C":
                rig.close()
                out.write(b"K")
                out.flush()
                return 0
            else:
                _reply_error(out, f"unknown request {op!r}")
                return 1
            out.flush()
    except BrokenPipeError:
        return 0
    finally:
        rig.close()


def add_serve_parser(sub: Any) -> None:
    """Add the ``serve`` subcommand to the subparsers ``sub`` of ``python -m
    pneutune.control.driver``."""
    p = sub.add_parser(
        "serve", help="serve the simulated rig on stdin/stdout (the example driver)",
        description=f"Serve the simulated rig on stdin/stdout ({PROTOCOL}; "
                    "pneutune/control/rig/pipe.py). Started by `deploy --rig pipe-sim`, or by "
                    "`deploy --rig exec:\"python -m pneutune.control.driver serve --scenario "
                    "{scenario} --seed {seed}\"`.")
    p.add_argument("--plant", help="plant.yaml (default: the paper's rig)")
    p.add_argument("--scenario", help="apply this scenario's plant changes, start at its x_r(0)")
    p.add_argument("--seed", type=int, help="sensor-noise seed (default: sim.seed)")
    p.add_argument("--sample-period", type=float, metavar="S",
                   help="sample (and tick) every S seconds, dividing the plant's rig.Ts "
                        "(default rig.Ts); the hello's Ts is S, its rig block keeps rig.Ts")
    p.set_defaults(run=serve_main)


def serve_main(args: argparse.Namespace) -> int:
    """``serve``: the simulated rig on this process's stdin/stdout until ``C`` or end of input.

    ``--scenario`` takes a scenario's name (its plant changes, the piston at rest at its
    x_r(0)) or an experiment's name (:data:`EXPERIMENTS`: the plant as it is, the piston at
    rest mid-stroke), so that one driver command line serves ``deploy`` and ``record``.

    A bad plant or scenario is answered with ``E`` (the client waits for the hello) and one
    ``error:`` line on stderr; exit status 2.
    """
    from pneutune.control.contracts.plant import load_plant
    from pneutune.control.sim.closed_loop import scenario_plant
    from pneutune.control.sim.scenarios import resolve_scenarios

    try:
        plant_cfg = load_plant(args.plant)
        x0 = None
        if args.scenario is not None and args.scenario not in EXPERIMENTS:
            found = resolve_scenarios(args.scenario)
            if len(found) != 1:
                raise ExperimentError(f"--scenario takes one scenario name, got "
                                      f"{args.scenario!r} ({len(found)} scenarios)")
            sc = found[0]
            plant_cfg = scenario_plant(plant_cfg, sc)
            x0 = float(sc.reference_array(plant_cfg.rig.Ts,
                                          0.5 * (plant_cfg.rig.x_min + plant_cfg.rig.x_max))[0, 0])
        rig = DeploySimRig(plant_cfg, x0=x0, seed=args.seed, sample_period=args.sample_period)
    except PneutuneError as exc:
        sys.stderr.write(f"error: {exc}\n")
        try:
            _reply_error(sys.stdout.buffer, str(exc))
        except OSError:
            pass
        return 2
    return serve(rig, sys.stdin.buffer, sys.stdout.buffer)


__all__ = ["COMMAND_PLACEHOLDERS", "DEFAULT_STARTUP_TIMEOUT", "DEFAULT_TIMEOUT", "EXPERIMENTS",
           "FRAME_DUTIES",
           "FRAME_LENGTH", "FRAME_READ", "FRAME_TIME", "FRAME_TRUTH", "MAX_ERROR", "MAX_HELLO",
           "PROTOCOL",
           "DeploySimRig", "DriverProcess", "ExecRig", "PipeRig", "RigErrorReply", "RigIOError",
           "add_serve_parser", "check_rig_block", "divides", "exec_command", "parse_hello", "serve",
           "serve_main", "sim_server_command"]
