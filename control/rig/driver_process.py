"""One rig driver program on the other end of two pipes (the client's process handling).

:class:`DriverProcess` starts the program (no shell, a session of its own), writes requests to
its stdin, reads replies of the pipe protocol (:mod:`pneutune.control.rig.wire`) from its
stdout with a deadline, and keeps the tail of its stderr for error messages.
:class:`~pneutune.control.rig.exec_rig.ExecRig` and the conformance check
(:mod:`pneutune.control.rig.conformance`) talk to a driver through it.
"""

from __future__ import annotations

import os
import select
import shlex
import subprocess
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import BinaryIO

from pneutune.control.rig.wire import FRAME_LENGTH, MAX_ERROR, MAX_HELLO, RigErrorReply, RigIOError

_TAIL_LINES = 20


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


__all__ = ["DriverProcess"]
