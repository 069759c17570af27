"""The client rigs of the pipe protocol: a rig driver as a program of its own.

:class:`ExecRig` is the :class:`~pneutune.control.rig.protocol.Rig` over a driver program that
speaks the pipe protocol ``pneutune.rig/1`` (:mod:`pneutune.control.rig.wire`) on its
stdin/stdout (``deploy --rig exec:CMD``); :class:`PipeRig` is the example simulated rig
(:mod:`pneutune.control.rig.pipe_server`) in a child process, an :class:`ExecRig` with
``truth()`` (``deploy --rig pipe-sim``). :func:`exec_command` makes a driver's argument list
from a ``--rig exec:`` text and :func:`sim_server_command` the example server's.
"""

from __future__ import annotations

import math
import os
import re
import shlex
import sys
from collections.abc import Sequence

import numpy as np

from pneutune.control.errors import ExperimentError
from pneutune.control.rig.driver_process import DriverProcess
from pneutune.control.rig.wire import (
    DEFAULT_STARTUP_TIMEOUT,
    DEFAULT_TIMEOUT,
    FRAME_DUTIES,
    FRAME_READ,
    FRAME_TIME,
    FRAME_TRUTH,
    RigIOError,
    check_rig_block,
    parse_hello,
)

#: Placeholders a driver command may contain, replaced for each run: the scenario's name
#: (``deploy``) or the experiment's (``record``), the noise seed of a simulated rig, and the
#: sample period the client asks for [s].
COMMAND_PLACEHOLDERS: tuple[str, ...] = ("scenario", "seed", "sample_period")
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")


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
    """The command that starts the example rig server (this interpreter, this package).

    Parameters
    ----------
    plant : path-like, optional
        plant.yaml of the simulated rig (``--plant``).
    scenario : str, optional
        Scenario or experiment name (``--scenario``).
    seed : int, optional
        Sensor-noise seed (``--seed``).
    sample_period : float, optional
        The server's sample period [s] (``--sample-period``).

    Returns
    -------
    list of str
        ``python -m pneutune.control.driver serve`` and the options given.
    """
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


class ExecRig:
    """A :class:`~pneutune.control.rig.protocol.Rig` whose driver is a program of its own.

    The program speaks the pipe protocol (:mod:`pneutune.control.rig.wire`) on its
    stdin/stdout; it is started here, greeted (``H``) and its hello checked
    (:func:`~pneutune.control.rig.wire.check_rig_block`).

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
        self._t0: float | None = None  # the driver's first time: the rig's clock counts from it
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
        :meth:`~pneutune.control.rig.driver_process.DriverProcess.reply`). Any failure ends
        the driver."""
        if self.closed:
            raise RigIOError("the rig is closed")
        try:
            self._driver.send(request)
            return self._driver.reply(size, self.timeout if timeout is None else timeout)
        except RigIOError:
            self._end()
            raise

    def _clock(self, t_driver: float, request: str, advance: bool) -> float:
        """The rig's time from the ``t`` of an ``R`` or ``A`` reply, counted from the first
        one the driver sent (a hardware clock may start anywhere: a Unix time works), and
        checked: finite, never earlier than the last one, and later after an advance."""
        if self._t0 is None and math.isfinite(t_driver):
            self._t0 = t_driver  # the first time: the rig's 0
            return 0.0
        t = t_driver - self._t0 if self._t0 is not None else t_driver
        slack = 1.0e-6 * self.Ts
        ok = math.isfinite(t) and (t > self.t + slack if advance else t >= self.t - slack)
        if not ok:  # the driver still answers: the caller writes the fail-safe duties
            after = "later than" if advance else "at or after"
            last = self.t + (self._t0 or 0.0)
            raise RigIOError(f"the driver's {request} reply carries t = {t_driver:.9g} s, "
                             f"expected a finite time {after} the last one, {last:.9g} s (the "
                             "protocol's clock advances by Ts)")
        return t

    def read(self) -> np.ndarray:
        """Sensors at the current sample [x, p_a, p_b, p_s]."""
        vals = FRAME_READ.unpack(self._request(b"R", FRAME_READ.size))
        self.t = self._clock(vals[0], "R", advance=False)
        # the channels' sample times on the same clock (a NaN, never delivered, stays NaN)
        self._stamps = np.array(vals[5:9]) - (self._t0 or 0.0)
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
        (t,) = FRAME_TIME.unpack(self._request(b"A", FRAME_TIME.size))
        self.t = self._clock(t, "A", advance=True)

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


__all__ = ["COMMAND_PLACEHOLDERS", "ExecRig", "PipeRig", "exec_command", "sim_server_command"]
