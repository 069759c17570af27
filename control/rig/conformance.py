"""The conformance check of a rig driver program: does it speak ``pneutune.rig/1``?

``python -m pneutune.control.driver check "CMD ARGS"`` starts the driver program several times
(one fresh process per session, as ``deploy --rig exec:`` does per scenario), talks the pipe
protocol of :mod:`pneutune.control.rig.wire` to it and reports each check, with exit status 0
when all pass and 1 otherwise. The checks, in :data:`CHECKS` order:

``hello``
    ``H`` gets ``K`` and a JSON hello with ``protocol`` ``pneutune.rig/1``, a positive ``Ts``
    and a complete, valid rig block whose ``Ts`` (the control period) the hello's ``Ts`` (the
    sample period) divides (:func:`~pneutune.control.rig.wire.check_rig_block`), within the
    startup timeout; with ``--sample-period S``, the hello's ``Ts`` is S.
``sequence``
    ``samples`` rounds of ``R``, ``W`` (all valves closed), ``A``, each answered ``K`` with
    its fixed-size body; no sample time lies after the sample's ``t``.
``clock``
    ``t`` is ``t0 + k Ts`` at the k-th ``R`` and ``t0 + (k+1) Ts`` after the k-th ``A``, to
    :data:`CLOCK_RTOL` of Ts, t0 the first ``R``'s t (0 on a simulated rig; a hardware clock
    may start anywhere): the clock advances by Ts, no sample skipped.
``bad_duty``
    A duty above 1, below 0 or NaN (each in a fresh session) gets ``E``, after which the
    server exits with a non-zero status.
``unknown_opcode``
    An unknown opcode (:data:`UNKNOWN_OPCODE`) gets ``E``, then the server exits non-zero.
``end_of_input``
    Closing the server's stdin makes it exit with status 0 within the timeout.
``close``
    ``C`` gets ``K``, then the server exits with status 0 within the timeout while its stdin
    is still open.
``latency``
    No reply of any session came later than the timeout (the hello: the startup timeout).
    A late reply is waited for up to :data:`PATIENCE` timeouts (the hello:
    :data:`HELLO_PATIENCE` startup timeouts), so that the report can say how late it was.

The first session runs ``hello``, ``sequence`` and ``clock``. When it gets no usable hello
(no reply, not JSON, another protocol, no ``Ts``), the checks that need a further session are
reported as not run (failed) rather than waiting for five more hellos that will not come.

What the pipe cannot show is not checked: that the valves really close after ``E``, ``C`` or
end of input is the driver's duty (and its watchdog's); check it on the rig with air on.
The check itself only ever writes closed-valve duties (0, 0, 0, 0), or duties the driver
must refuse.
"""

from __future__ import annotations

import argparse
import math
import shlex
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from pneutune.control.errors import ExperimentError
from pneutune.control.rig.driver_process import DriverProcess
from pneutune.control.rig.exec_rig import exec_command
from pneutune.control.rig.wire import (
    DEFAULT_STARTUP_TIMEOUT,
    DEFAULT_TIMEOUT,
    FRAME_DUTIES,
    FRAME_READ,
    FRAME_TIME,
    PROTOCOL,
    RigErrorReply,
    RigIOError,
    check_rig_block,
    parse_hello,
)

#: The checks, in report order.
CHECKS: tuple[str, ...] = ("hello", "sequence", "clock", "bad_duty", "unknown_opcode",
                           "end_of_input", "close", "latency")
#: R/W/A rounds of the sequence check (2 s of a 4 ms rig).
DEFAULT_SAMPLES = 500
#: Largest |t - k Ts| allowed, as a fraction of Ts: far above the rounding of t += Ts over
#: thousands of samples (~1e-12), far below a skipped sample or another Ts.
CLOCK_RTOL = 1.0e-6
#: Out-of-range duties, each sent to a fresh server: (what, duties).
BAD_DUTIES: tuple[tuple[str, tuple[float, float, float, float]], ...] = (
    ("above 1", (1.5, 0.0, 0.0, 0.0)),
    ("below 0", (0.0, -0.25, 0.0, 0.0)),
    ("NaN", (0.0, 0.0, math.nan, 0.0)),
)
#: An opcode the protocol does not have.
UNKNOWN_OPCODE = b"Z"
#: A late reply is waited for up to this many timeouts before the session is given up.
PATIENCE = 5.0
#: A late hello is waited for up to this many startup timeouts.
HELLO_PATIENCE = 2.0
_CLOSED = FRAME_DUTIES.pack(0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CheckResult:
    """The outcome of one check.

    Attributes
    ----------
    name : str
        One of :data:`CHECKS`.
    passed : bool
        Whether the driver passed it.
    detail : str
        What was seen (the first failure, or what passed).
    """

    name: str
    passed: bool
    detail: str


@dataclass(frozen=True)
class ConformanceReport:
    """Every check's result for one driver command.

    Attributes
    ----------
    command : tuple of str
        The driver program and its arguments.
    results : tuple of CheckResult
        In :data:`CHECKS` order.
    samples : int
        R/W/A rounds of the sequence check.
    timeout : float
        Longest allowed reply time after the hello [s].
    """

    command: tuple[str, ...]
    results: tuple[CheckResult, ...]
    samples: int
    timeout: float

    @property
    def passed(self) -> bool:
        """Whether every check passed."""
        return all(r.passed for r in self.results)

    def failed(self) -> list[str]:
        """Names of the failed checks."""
        return [r.name for r in self.results if not r.passed]

    def format(self) -> str:
        """The report as text: one line per check, then the verdict."""
        width = max(len(name) for name in CHECKS)
        lines = [f"driver check: {shlex.join(self.command)}",
                 f"  ({PROTOCOL}, {self.samples} samples, reply timeout {self.timeout:g} s)"]
        lines += [f"{'PASS' if r.passed else 'FAIL'}  {r.name:<{width}}  {r.detail}"
                  for r in self.results]
        n_ok = sum(r.passed for r in self.results)
        verdict = "conforms" if self.passed else f"fails {', '.join(self.failed())}"
        lines.append(f"{n_ok} of {len(self.results)} checks passed: the driver {verdict}")
        return "\n".join(lines)


@dataclass
class _Latency:
    """The slowest reply of every session, and the late ones."""

    timeout: float
    startup_timeout: float
    replies: int = 0
    slowest: float = 0.0
    slowest_where: str = ""
    late: list[str] = field(default_factory=list)

    def record(self, seconds: float, where: str, hello: bool) -> None:
        limit = self.startup_timeout if hello else self.timeout
        if seconds > limit:
            self.late.append(f"{where} took {seconds:.3g} s (limit {limit:g} s)")
        if not hello:
            self.replies += 1
            if seconds > self.slowest:
                self.slowest, self.slowest_where = seconds, where


class _Session:
    """One fresh driver process: every reply timed, a late one waited for up to PATIENCE
    timeouts (the hello: HELLO_PATIENCE startup timeouts)."""

    def __init__(self, command: Sequence[str], name: str, latency: _Latency) -> None:
        self.name = name
        self.latency = latency
        self.driver = DriverProcess(command)

    def request(self, what: str, data: bytes, size: int | None, hello: bool = False) -> bytes:
        lat = self.latency
        limit = lat.startup_timeout if hello else lat.timeout
        self.driver.send(data)
        start = time.monotonic()
        try:
            return self.driver.reply(size, (HELLO_PATIENCE if hello else PATIENCE) * limit)
        finally:
            lat.record(time.monotonic() - start, f"{what} ({self.name} session)", hello)

    def hello(self) -> tuple[float, dict[str, Any]]:
        """``H``: the hello's Ts and raw rig block (RigIOError if it is unusable)."""
        Ts, rig = parse_hello(self.request("H", b"H", None, hello=True))
        return Ts, dict(rig)

    def round(self, k: int) -> tuple[tuple[float, ...], float]:
        """One R, W (closed), A: the R values and the A time."""
        vals = FRAME_READ.unpack(self.request(f"R at sample {k}", b"R", FRAME_READ.size))
        self.request(f"W at sample {k}", b"W" + _CLOSED, 0)
        (t_next,) = FRAME_TIME.unpack(self.request(f"A at sample {k}", b"A", FRAME_TIME.size))
        return vals, t_next

    def end(self) -> int:
        return self.driver.end(self.latency.timeout)


def _start(command: Sequence[str], name: str, latency: _Latency) -> tuple[_Session, float]:
    """A fresh session past a usable hello and one round; RigIOError otherwise."""
    s = _Session(command, name, latency)
    try:
        Ts, _ = s.hello()
        s.round(0)
    except RigIOError:
        s.end()
        raise
    return s, Ts


def _main_session(s: _Session, samples: int, sample_period: float | None = None
                  ) -> tuple[bool, CheckResult, CheckResult, CheckResult]:
    """hello, sequence and clock, in one session; first whether a usable hello came (one
    that gives Ts and a rig object, complete or not)."""
    try:
        try:
            Ts, rig = s.hello()
        except RigIOError as exc:
            return (False, CheckResult("hello", False, str(exc)),
                    _not_run("sequence", "no hello"), _not_run("clock", "no hello"))
        try:
            block = check_rig_block(rig, Ts)
            if sample_period is not None and not math.isclose(Ts, sample_period,
                                                              rel_tol=1e-9, abs_tol=0.0):
                raise RigIOError(f"hello: Ts = {Ts!r} s, but --sample-period asked for "
                                 f"{sample_period!r} s")
            per = "" if Ts == block["Ts"] else f" sampling {round(float(block['Ts']) / Ts)} " \
                                               f"times per rig.Ts = {block['Ts']:g} s,"
            hello = CheckResult("hello", True, f"{PROTOCOL}, Ts = {Ts:g} s,{per} a complete "
                                               f"rig block ({len(rig)} keys)")
        except RigIOError as exc:
            hello = CheckResult("hello", False, str(exc))
        tol = CLOCK_RTOL * Ts
        clock_fail = ""
        worst = 0.0
        seq_fail = ""
        k = 0
        t0 = None  # the driver's clock may start anywhere (a hardware clock's own origin)
        try:
            for k in range(samples):
                vals, t_next = s.round(k)
                t, stamps = vals[0], vals[5:9]
                if t0 is None:
                    t0 = t if math.isfinite(t) else 0.0
                for t_got, j, op in ((t, k, "R"), (t_next, k + 1, "A")):
                    err = abs(t_got - t0 - j * Ts)
                    worst = max(worst, err) if math.isfinite(err) else math.inf
                    # a clock far from 0 (1.7e9 s: a Unix time) resolves only 0.24 us in a double
                    slack = max(tol, 8.0 * math.ulp(t_got)) if math.isfinite(t_got) else tol
                    if not err <= slack and not clock_fail:
                        start = "" if t0 == 0.0 else "t0 + "
                        clock_fail = (f"{op} at sample {k} gave t = {t_got!r} s, expected "
                                      f"{start}{j} Ts = {t0 + j * Ts!r} s")
                late = [st for st in stamps if not (math.isnan(st) or st <= t + tol)]
                if late:
                    seq_fail = (f"R at sample {k}: sample time {late[0]!r} s is after the "
                                f"sample's t = {t!r} s")
                    break
        except RigIOError as exc:
            seq_fail = f"sample {k}: {exc}"
        done = k + 1 if not seq_fail else k
        sequence = (CheckResult("sequence", False, seq_fail) if seq_fail else
                    CheckResult("sequence", True, f"{samples} rounds of R, W, A answered K "
                                                  "with well-formed replies"))
        if clock_fail:
            clock = CheckResult("clock", False, clock_fail)
        elif done == 0:
            clock = _not_run("clock", "no complete R, W, A round")
        else:
            origin = "" if not t0 else f" from t0 = {t0!r} s"
            clock = CheckResult("clock", True, f"t = k Ts at every R and A of {done} "
                                               f"samples{origin} (largest |t - t0 - k Ts| = "
                                               f"{worst:.3g} s)")
        return True, hello, sequence, clock
    finally:
        s.end()


def _not_run(name: str, why: str) -> CheckResult:
    return CheckResult(name, False, f"not run: {why}")


def _refusal(command: Sequence[str], name: str, request: bytes, what: str,
             latency: _Latency) -> str:
    """Send a request the driver must refuse; '' if it answered E and exited non-zero,
    else what went wrong."""
    try:
        s, _ = _start(command, name, latency)
    except RigIOError as exc:
        return f"{what}: the session did not start: {exc}"
    try:
        try:
            s.request(what, request, 0)
        except RigErrorReply:
            rc = s.driver.wait(latency.timeout)
            if rc is None:
                return (f"{what}: E, but the server still ran {latency.timeout:g} s later "
                        f"(it must close its valves and exit)")
            if rc == 0:
                return f"{what}: E, but the server exited with status 0 (expected non-zero)"
            return ""
        except RigIOError as exc:
            return f"{what}: {exc}, expected an E reply"
        return f"{what}: replied K, expected E"
    finally:
        s.end()


def _refusals(command: Sequence[str], latency: _Latency) -> tuple[CheckResult, CheckResult]:
    errors = [_refusal(command, "bad_duty", b"W" + FRAME_DUTIES.pack(*d), f"duties {list(d)} "
                       f"({what})", latency) for what, d in BAD_DUTIES]
    errors = [e for e in errors if e]
    bad_duty = (CheckResult("bad_duty", False, "; ".join(errors)) if errors else
                CheckResult("bad_duty", True, "E, then exit (non-zero) for duties "
                                              f"{', '.join(w for w, _ in BAD_DUTIES)}"))
    error = _refusal(command, "unknown_opcode", UNKNOWN_OPCODE, f"opcode {UNKNOWN_OPCODE!r}",
                     latency)
    opcode = (CheckResult("unknown_opcode", False, error) if error else
              CheckResult("unknown_opcode", True,
                          f"E, then exit (non-zero) for opcode {UNKNOWN_OPCODE!r}"))
    return bad_duty, opcode


def _ending(command: Sequence[str], how: str, latency: _Latency) -> CheckResult:
    """end_of_input (close stdin) or close (``C``, stdin left open): exit 0 within timeout."""
    name = "close" if how == "C" else "end_of_input"
    try:
        s, _ = _start(command, name, latency)
    except RigIOError as exc:
        return CheckResult(name, False, f"the session did not start: {exc}")
    try:
        start = time.monotonic()
        if how == "C":
            try:
                s.request("C", b"C", 0)
            except RigIOError as exc:
                return CheckResult(name, False, f"C: {exc}")
            start = time.monotonic()
        else:
            s.driver.close_input()
        rc = s.driver.wait(latency.timeout)
        took = time.monotonic() - start
        what = "K to C, then" if how == "C" else "after end of input,"
        if rc is None:
            return CheckResult(name, False, f"{what} the server still ran "
                                            f"{latency.timeout:g} s later")
        if rc != 0:
            return CheckResult(name, False, f"{what} the server exited with status {rc} "
                                            "(expected 0)")
        return CheckResult(name, True, f"{what} exit with status 0 in {took * 1e3:.0f} ms")
    finally:
        s.end()


def check_driver(command: Sequence[str], samples: int = DEFAULT_SAMPLES,
                 timeout: float = DEFAULT_TIMEOUT,
                 startup_timeout: float = DEFAULT_STARTUP_TIMEOUT,
                 sample_period: float | None = None) -> ConformanceReport:
    """Run every conformance check (module docstring) on a driver program.

    Parameters
    ----------
    command : sequence of str
        The driver program and its arguments (started afresh for each session).
    samples : int
        R/W/A rounds of the sequence and clock checks.
    timeout : float
        Longest allowed reply time after the hello, and longest wait for the server to exit
        after ``E``, ``C`` or end of input [s].
    startup_timeout : float
        Longest allowed wait for the hello [s].
    sample_period : float, optional
        The sample period the driver was asked for [s]: the hello's ``Ts`` must equal it (it
        must divide ``rig.Ts`` in any case).

    Returns
    -------
    ConformanceReport
    """
    latency = _Latency(float(timeout), float(startup_timeout))
    try:
        main = _Session(command, "main", latency)
    except RigIOError as exc:  # not there, not executable: nothing else can run
        results = (CheckResult("hello", False, str(exc)),
                   *(_not_run(name, "the driver cannot be started") for name in CHECKS[1:]))
        return ConformanceReport(tuple(command), results, samples, float(timeout))
    greeted, hello, sequence, clock = _main_session(main, samples, sample_period)
    if greeted:
        bad_duty, opcode = _refusals(command, latency)
        end_of_input = _ending(command, "EOF", latency)
        close = _ending(command, "C", latency)
    else:  # every other session starts with a hello too: do not wait for it five more times
        bad_duty, opcode, end_of_input, close = (
            _not_run(name, "no usable hello in the first session")
            for name in ("bad_duty", "unknown_opcode", "end_of_input", "close"))
    if latency.late:
        lat = CheckResult("latency", False, "; ".join(latency.late[:3]) + (
            f" (and {len(latency.late) - 3} more)" if len(latency.late) > 3 else ""))
    elif latency.replies == 0:
        lat = _not_run("latency", "no reply after a hello to time")
    else:
        lat = CheckResult("latency", True,
                          f"every reply within {timeout:g} s ({latency.replies} replies, "
                          f"slowest {latency.slowest * 1e3:.2f} ms: {latency.slowest_where})")
    results = (hello, sequence, clock, bad_duty, opcode, end_of_input, close, lat)
    return ConformanceReport(tuple(command), results, samples, float(timeout))


def add_check_parser(sub: Any) -> None:
    """Add the ``check`` subcommand to the subparsers ``sub`` of ``python -m
    pneutune.control.driver``."""
    p = sub.add_parser(
        "check", help="check that a driver program speaks the pipe protocol",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=f"""\
Check that a driver program speaks {PROTOCOL} (docs/deploy.md): start it afresh for each
session and report each check:

  hello           H gets the protocol, Ts and a complete, valid rig block (Ts divides
                  rig.Ts; with --sample-period S, Ts = S)
  sequence        --samples rounds of R, W (valves closed), A, each answered K, well formed
  clock           t = t0 + k Ts at every R and A: the clock advances by Ts, no sample
                  skipped (t0, the first R's t, may be anything)
  bad_duty        a duty above 1, below 0 or NaN gets E, then the server exits non-zero
  unknown_opcode  an unknown opcode gets E, then the server exits non-zero
  end_of_input    closing its stdin makes the server exit 0 within --timeout
  close           C gets K, then the server exits 0 within --timeout
  latency         no reply later than --timeout (the hello: --startup-timeout)

Exit status: 0 every check passed; 1 a check failed; 2 bad arguments.""",
        epilog="""\
examples:
  python -m pneutune.control.driver check "python -m pneutune.control.driver serve"
  python -m pneutune.control.driver check "./rig_driver --port /dev/ttyUSB0" --timeout 0.1
  python -m pneutune.control.driver check "python my_driver.py --seed {seed}" --samples 2000
  python -m pneutune.control.driver check "./rig_driver --sample-period {sample_period}" \
         --sample-period 0.0005

The valves' real state after E, C or end of input cannot be seen over the pipe: check it on
the rig. The check writes only closed-valve duties, and out-of-range ones the driver must
refuse.""")
    p.add_argument("command", metavar="CMD",
                   help="the driver program and its arguments, in one quoted string (split "
                        "like a shell would; {scenario}, {seed} and {sample_period} are replaced)")
    p.add_argument("--samples", type=int, default=DEFAULT_SAMPLES, metavar="N",
                   help=f"R/W/A rounds of the sequence check (default {DEFAULT_SAMPLES})")
    p.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, metavar="S",
                   help=f"longest reply time after the hello [s] (default {DEFAULT_TIMEOUT:g})")
    p.add_argument("--startup-timeout", type=float, default=DEFAULT_STARTUP_TIMEOUT,
                   metavar="S", help="longest wait for the hello [s] "
                                     f"(default {DEFAULT_STARTUP_TIMEOUT:g})")
    p.add_argument("--scenario", default="sine-0.5hz", metavar="S",
                   help="the value of {scenario} in CMD (default sine-0.5hz)")
    p.add_argument("--seed", type=int, default=1, metavar="N",
                   help="the value of {seed} in CMD (default 1)")
    p.add_argument("--sample-period", type=float, metavar="S",
                   help="the value of {sample_period} in CMD [s]; the hello's Ts must then be "
                        "S (and S must divide rig.Ts), as `record --sample-period S` requires")
    p.set_defaults(run=check_main)


def check_main(args: argparse.Namespace) -> int:
    """``check``: print the report on stdout; 0 if the driver conforms, else 1."""
    for name in ("timeout", "startup_timeout"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0.0):
            raise ExperimentError(f"--{name.replace('_', '-')} must be > 0 s, got {value}")
    if args.samples < 1:
        raise ExperimentError(f"--samples must be >= 1, got {args.samples}")
    if args.sample_period is not None and not (math.isfinite(args.sample_period)
                                               and args.sample_period > 0.0):
        raise ExperimentError(f"--sample-period must be > 0 s, got {args.sample_period}")
    command = exec_command(args.command, args.scenario, args.seed, args.sample_period)
    report = check_driver(command, samples=args.samples, timeout=args.timeout,
                          startup_timeout=args.startup_timeout,
                          sample_period=args.sample_period)
    print(report.format())
    return 0 if report.passed else 1


__all__ = ["BAD_DUTIES", "CHECKS", "CLOCK_RTOL", "DEFAULT_SAMPLES", "HELLO_PATIENCE", "PATIENCE",
           "UNKNOWN_OPCODE",
           "CheckResult", "ConformanceReport", "add_check_parser", "check_driver", "check_main"]
