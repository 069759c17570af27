"""The interface a rig driver implements, and an example driver across a process boundary.

:class:`RigDriver` is what the deploy runtime (:mod:`pneutune.control.rig.runtime`) talks to. A
hardware driver implements it in Python, or runs as its own process and speaks the pipe
protocol below (then :class:`PipeRig` is its Python side, unchanged). Three rigs ship:

* :class:`DeploySimRig`: the simulated rig in process (the compiled plant,
  :class:`pneutune.control.rig.simrig.SimRig`) with the driver extras (sample times, metadata,
  close);
* :class:`PipeRig` + ``python -m pneutune.control.driver serve``: the same simulated rig in
  another process, over the pipe protocol (the example driver, ``deploy --rig pipe-sim``);
* :class:`pneutune.control.rig.faults.FaultySimRig`: the simulated rig with injected faults.

The driver contract (docs/deploy.md has the long form)
------------------------------------------------------
Units: SI. Positions in m, pressures in Pa *absolute*, duties 0..1 in the valve order
``a_in, a_out, b_in, b_out``, times in s on the rig's clock, which starts at 0.

``Ts``
    The sampling period [s]; it must equal the controller's ``rig.Ts`` (``deploy`` checks it).
``t``
    Time of the current sample, ``k Ts`` after ``k`` calls of :meth:`advance`.
``read()``
    The sensors at the current sample ``[x, p_a, p_b, p_s]``: the latest value of each
    channel, taken as close to the tick as the hardware allows; call once per sample. A channel
    that has never delivered reads NaN. Must not block longer than ~Ts/10.
``sample_times()`` (optional; returning None means "not known")
    Rig time at which each channel last delivered a *new* value. The supervisor's staleness
    rule uses it; without it a frozen position cannot be told from a piston at rest.
``write(duties)``
    Command the four duties from now on. Non-blocking. How a new duty takes effect within the
    running PWM period is the rig's ``pwm_update`` (``immediate``: at once, comparator;
    ``latched``: at the next period start). Duties outside [0, 1] are a programming error.
``advance()``
    Return when the next sample is due (hardware: block until the tick; simulation: integrate
    to it). **Missed deadline**: if it is called after the next tick has passed, it returns at
    once and the sample is *late*, never skipped (skipping would break the controller's fixed
    Ts); the driver counts it. The runtime reports overruns and jitter; a rig that stops
    ticking is caught by ``limits.sensor_timeout_s``.
``rig_metadata()``
    The ``rig`` block of the rig (:data:`~pneutune.control.constants.RIG_KEYS`), written to
    the run log so that ``identify`` knows the geometry and timing.
``close()``
    Write the fail-safe duties (all valves closed,
    :data:`pneutune.control.rig.supervisor.FAIL_SAFE_DUTIES`) and release the hardware;
    idempotent. A driver must reach the same state by itself when its client disappears (end
    of file on its input, a crash) and, on hardware, through a watchdog that cuts the coil
    power when no ``write`` came for ``sensor_timeout_s``: normally-closed valves are then
    all closed.

Pipe protocol (``pneutune.rig/1``)
----------------------------------
Binary, little-endian, over the server's stdin (requests) and stdout (replies); stderr is
prose. Every request is one opcode byte and a fixed-size payload; every reply starts with
``K`` (ok) or ``E`` (error, then ``<I`` length and at most 4096 bytes of UTF-8 message; the
server then closes the valves and exits 1).

==========  ======================  ===========================================================
request     payload                 reply after ``K``
==========  ======================  ===========================================================
``H``       (none)                  ``<I`` length, JSON (< 64 KiB): ``protocol``, ``Ts``, ``rig``
``R``       (none)                  ``<9d``: t, x, p_a, p_b, p_s, 4 sample times
``W``       ``<4d`` duties          (nothing)
``A``       (none)                  ``<d``: the new t
``T``       (none)                  ``<6d``: /sim/truth fields (simulated rigs only)
``C``       (none)                  (nothing); the server writes the fail-safe duties and exits 0
==========  ======================  ===========================================================

Doubles travel as IEEE 754 bits, so a run across the pipe gives bit-identical numbers to the
same run in process. The client waits at most ``timeout`` seconds for a reply
(:class:`RigIOError`). Only pipes to a child process: nothing listens on a network.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import struct
import subprocess
import sys
from collections.abc import Sequence
from typing import BinaryIO, Protocol, runtime_checkable

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import PneutuneError
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import PlantParams
from pneutune.control.rig.simrig import SimRig
from pneutune.control.rig.supervisor import FAIL_SAFE_DUTIES

PROTOCOL = "pneutune.rig/1"
_MAX_HELLO = 64 * 1024
_MAX_ERROR = 4096
_READ = struct.Struct("<9d")
_DUTIES = struct.Struct("<4d")
_TIME = struct.Struct("<d")
_TRUTH = struct.Struct("<6d")
_LEN = struct.Struct("<I")


class RigIOError(PneutuneError, OSError):
    """The rig did not answer, answered garbage, or reported an error."""


@runtime_checkable
class RigDriver(Protocol):
    """What a hardware (or simulated) rig driver provides; see the module docstring.

    Attributes
    ----------
    Ts : float
        Sampling period [s].
    t : float
        Time of the current sample [s].
    """

    Ts: float
    t: float

    def read(self) -> np.ndarray:
        """Sensors at the current sample: [x [m], p_a, p_b, p_s [Pa abs]]."""
        ...

    def sample_times(self) -> np.ndarray | None:
        """Rig time each channel last delivered a new value [s], or None if unknown."""
        ...

    def write(self, duties: np.ndarray) -> None:
        """Command the duties [a_in, a_out, b_in, b_out] (0..1) from now on."""
        ...

    def advance(self) -> None:
        """Return when the next sample is due (late, never skipped, on a missed deadline)."""
        ...

    def rig_metadata(self) -> dict[str, float | str]:
        """The ``rig`` block of this rig (every key of RIG_KEYS)."""
        ...

    def close(self) -> None:
        """Write the fail-safe duties (all valves closed) and release the rig; idempotent."""
        ...


class DeploySimRig(SimRig):
    """The in-process simulated rig with the :class:`RigDriver` extras.

    Every :meth:`read` is a new sample on every channel (``sample_times()`` is ``t``). The
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
    """

    def __init__(self, plant_cfg: PlantConfig | PlantParams, x0: float | None = None,
                 pressures0: tuple[float, float] | None = None, seed: int | None = None) -> None:
        super().__init__(plant_cfg, x0=x0, pressures0=pressures0, seed=seed)
        self.closed = False
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

    def sample_times(self) -> np.ndarray | None:
        """Every channel is refreshed at every sample: ``[t, t, t, t]``."""
        return np.full(4, self.t)

    def write(self, duties: np.ndarray) -> None:
        """Command the four duties from now on (kept in :attr:`last_duties`)."""
        d = np.ascontiguousarray(duties, dtype=np.float64)
        self.last_duties = d.copy()
        super().write(d)

    def rig_metadata(self) -> dict[str, float | str]:
        """The plant's ``rig`` block."""
        return self.params.config.rig_metadata()

    def close(self) -> None:
        """Write the fail-safe duties (all closed); idempotent."""
        if not self.closed:
            self.write(np.asarray(FAIL_SAFE_DUTIES))
            self.closed = True


# ---------------------------------------------------------------------------------------------
# Client
# ---------------------------------------------------------------------------------------------


class PipeRig:
    """A :class:`RigDriver` whose rig runs in a child process, over the pipe protocol.

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
    timeout : float
        Longest wait for a reply [s].

    Notes
    -----
    Use as a context manager (or call :meth:`close`): closing sends ``C`` (fail-safe duties)
    and waits for the server to exit.
    """

    def __init__(self, command: Sequence[str] | None = None,
                 plant: str | os.PathLike[str] | None = None, scenario: str | None = None,
                 seed: int | None = None, timeout: float = 2.0) -> None:
        cmd = list(command) if command is not None else sim_server_command(plant, scenario, seed)
        self.timeout = float(timeout)
        self.closed = False
        self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, bufsize=0)
        if self._proc.stdin is None or self._proc.stdout is None:  # pragma: no cover
            raise RigIOError(f"cannot open pipes to {cmd}")
        self._in: BinaryIO = self._proc.stdin
        self._out: BinaryIO = self._proc.stdout
        self._rbuf = bytearray()
        hello = self._request(b"H", b"", None)
        meta = json.loads(hello.decode("utf-8"))
        if meta.get("protocol") != PROTOCOL:
            self._kill()
            raise RigIOError(f"rig server speaks {meta.get('protocol')!r}, expected {PROTOCOL!r}")
        self.Ts = float(meta["Ts"])
        self._rig_meta: dict[str, float | str] = dict(meta["rig"])
        self.t = 0.0
        self._stamps = np.zeros(4)
        self._duties_buf = bytearray(1 + _DUTIES.size)
        self._duties_buf[0:1] = b"W"

    # -- transport ------------------------------------------------------------------------------

    def _recv(self, n: int) -> bytes:
        fd = self._out.fileno()
        while len(self._rbuf) < n:
            ready, _, _ = select.select([fd], [], [], self.timeout)
            if not ready:
                self._kill()
                raise RigIOError(f"rig server: no reply within {self.timeout:g} s")
            chunk = os.read(fd, 65536)
            if not chunk:
                err = self._stderr_tail()
                raise RigIOError("rig server closed its output" + (f": {err}" if err else ""))
            self._rbuf += chunk
        data = bytes(self._rbuf[:n])
        del self._rbuf[:n]
        return data

    def _request(self, op: bytes, payload: bytes, size: int | None) -> bytes:
        """Send ``op + payload``; return the reply body (``size`` bytes, or length-prefixed)."""
        if self.closed:
            raise RigIOError("the rig is closed")
        try:
            self._in.write(op + payload)
            self._in.flush()
        except (BrokenPipeError, OSError) as exc:
            err = self._stderr_tail()
            raise RigIOError(f"rig server gone ({exc})" + (f": {err}" if err else "")) from None
        status = self._recv(1)
        if status == b"E":
            (length,) = _LEN.unpack(self._recv(_LEN.size))
            msg = self._recv(min(length, _MAX_ERROR)).decode("utf-8", "replace")
            self._kill()
            raise RigIOError(f"rig server: {msg}")
        if status != b"K":
            self._kill()
            raise RigIOError(f"rig server: bad reply status {status!r}")
        if size is None:
            (length,) = _LEN.unpack(self._recv(_LEN.size))
            if length > _MAX_HELLO:
                self._kill()
                raise RigIOError(f"rig server: reply of {length} bytes exceeds {_MAX_HELLO}")
            return self._recv(length)
        return self._recv(size) if size else b""

    def _stderr_tail(self) -> str:
        proc = self._proc
        if proc.poll() is None or proc.stderr is None:
            return ""
        try:
            text = proc.stderr.read(_MAX_ERROR).decode("utf-8", "replace")
        except OSError:  # pragma: no cover
            return ""
        lines = [ln for ln in text.strip().splitlines() if ln.strip()]
        return lines[-1] if lines else ""

    def _kill(self) -> None:
        self.closed = True
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait(timeout=5.0)
        for fh in (self._proc.stdin, self._proc.stdout, self._proc.stderr):
            if fh is not None:
                fh.close()

    # -- RigDriver ------------------------------------------------------------------------------

    def read(self) -> np.ndarray:
        """Sensors at the current sample [x, p_a, p_b, p_s]."""
        vals = _READ.unpack(self._request(b"R", b"", _READ.size))
        self.t = vals[0]
        self._stamps = np.array(vals[5:9])
        return np.array(vals[1:5])

    def sample_times(self) -> np.ndarray | None:
        """Sample times reported with the last :meth:`read`."""
        return self._stamps.copy()

    def write(self, duties: np.ndarray) -> None:
        """Command the four duties."""
        d = np.asarray(duties, dtype=np.float64)
        _DUTIES.pack_into(self._duties_buf, 1, d[0], d[1], d[2], d[3])
        self._request(bytes(self._duties_buf[:1]), bytes(self._duties_buf[1:]), 0)

    def advance(self) -> None:
        """Move to the next sample."""
        (self.t,) = _TIME.unpack(self._request(b"A", b"", _TIME.size))

    def truth(self) -> np.ndarray:
        """The simulated rig's ``/sim/truth`` fields at the current sample."""
        return np.array(_TRUTH.unpack(self._request(b"T", b"", _TRUTH.size)))

    def rig_metadata(self) -> dict[str, float | str]:
        """The server rig's ``rig`` block."""
        return dict(self._rig_meta)

    def close(self) -> None:
        """Fail-safe duties, then stop the server; idempotent."""
        if self.closed:
            return
        try:
            self._request(b"C", b"", 0)
        except RigIOError:
            pass
        self.closed = True
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:  # pragma: no cover
            self._proc.kill()
            self._proc.wait(timeout=5.0)
        for fh in (self._proc.stdin, self._proc.stdout, self._proc.stderr):
            if fh is not None:
                fh.close()

    def __enter__(self) -> PipeRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def sim_server_command(plant: str | os.PathLike[str] | None = None, scenario: str | None = None,
                       seed: int | None = None) -> list[str]:
    """The command that starts the example rig server (this interpreter, this package)."""
    cmd = [sys.executable, "-m", "pneutune.control.driver", "serve"]
    if plant is not None:
        cmd += ["--plant", os.fspath(plant)]
    if scenario is not None:
        cmd += ["--scenario", scenario]
    if seed is not None:
        cmd += ["--seed", str(int(seed))]
    return cmd


# ---------------------------------------------------------------------------------------------
# Server
# ---------------------------------------------------------------------------------------------


def _reply_error(out: BinaryIO, message: str) -> None:
    body = message.encode("utf-8")[:_MAX_ERROR]
    out.write(b"E" + _LEN.pack(len(body)) + body)
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
                out.write(b"K" + _READ.pack(rig.t, *vals.tolist(), *st.tolist()))
            elif op == b"W":
                raw = _read_exact(inp, _DUTIES.size)
                if raw is None:
                    return 0
                d = np.array(_DUTIES.unpack(raw))
                if not np.all((d >= 0.0) & (d <= 1.0)):
                    _reply_error(out, f"duties must be in [0, 1], got {d.tolist()}")
                    return 1
                rig.write(d)
                out.write(b"K")
            elif op == b"A":
                rig.advance()
                out.write(b"K" + _TIME.pack(rig.t))
            elif op == b"T":
                out.write(b"K" + _TRUTH.pack(*rig.truth().tolist()))
            elif op == b"H":
                out.write(b"K" + _LEN.pack(len(hello)) + hello)
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


def _serve_main(argv: Sequence[str] | None = None) -> int:
    from pneutune.control.contracts.plant import load_plant
    from pneutune.control.sim.closed_loop import scenario_plant
    from pneutune.control.sim.scenarios import resolve_scenarios

    parser = argparse.ArgumentParser(
        prog="python -m pneutune.control.driver",
        description="Example rig driver: the simulated rig served over stdin/stdout "
                    f"({PROTOCOL}, see pneutune/control/rig/pipe.py). Started by PipeRig.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("serve", help="serve the simulated rig on stdin/stdout")
    p.add_argument("--plant", help="plant.yaml (default: the paper's rig)")
    p.add_argument("--scenario", help="apply this scenario's plant changes, start at its x_r(0)")
    p.add_argument("--seed", type=int, help="sensor-noise seed (default: sim.seed)")
    args = parser.parse_args(argv)
    plant_cfg = load_plant(args.plant)
    x0 = None
    if args.scenario is not None:
        found = resolve_scenarios(args.scenario)
        if len(found) != 1:
            parser.error(f"--scenario takes one scenario name, got the group {args.scenario!r}")
        sc = found[0]
        plant_cfg = scenario_plant(plant_cfg, sc)
        x0 = float(sc.reference_array(plant_cfg.rig.Ts,
                                      0.5 * (plant_cfg.rig.x_min + plant_cfg.rig.x_max))[0, 0])
    rig = DeploySimRig(plant_cfg, x0=x0, seed=args.seed)
    return serve(rig, sys.stdin.buffer, sys.stdout.buffer)


def main() -> int:  # pragma: no cover - exercised through PipeRig in a subprocess
    try:
        return _serve_main()
    except PneutuneError as exc:
        sys.stderr.write(f"error: {exc}\n")
        # the client is waiting for the hello: answer it with the error
        try:
            _reply_error(sys.stdout.buffer, str(exc))
        except OSError:
            pass
        return 2


__all__ = ["PROTOCOL", "DeploySimRig", "PipeRig", "RigDriver", "RigIOError", "serve",
           "sim_server_command"]

if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
