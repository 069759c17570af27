"""A rig driver speaking ``pneutune.rig/1`` with one deliberate fault, chosen by ``--mode``.

The conformance check (``python -m pneutune.control.driver check``) must catch each fault and
name the check it breaks (tests/test_driver_exec.py). ``--mode ok`` is a conforming driver, so
that every other mode differs from a passing one by exactly its fault:

================  =====================  ==================================================
mode              breaks                 what it does
================  =====================  ==================================================
``ok``            (nothing)              speaks the protocol
``bad_hello``     ``hello``              its rig block lacks ``pwm_update``
``stamp_future``  ``sequence``           from sample 20 on, its sample times lie after ``t``
``clock``         ``clock``              from sample 100 on, ``A`` advances ``t`` by 2 Ts
``accept_duty``   ``bad_duty``           accepts duties outside [0, 1] (and NaN)
``accept_opcode`` ``unknown_opcode``     answers ``K`` to an unknown opcode
``ignore_eof``    ``end_of_input``       keeps running after end of input
``ignore_close``  ``close``              answers ``C`` but keeps running until end of input
``late``          ``latency``            answers ``A`` at sample 50 after ``--delay`` seconds
``clock_nan``     ``clock``              answers ``A`` at sample 30 with t = NaN
``clock_back``    ``clock``              answers ``R`` at sample 30 with t = 0
``clock_unix``    (nothing)              a clock that starts at a Unix time, 1.7e9 s
``stale_unix``    (the supervisor)       that clock, and x's sample time frozen from sample 30
================  =====================  ==================================================

Standard library only (it starts in a few tens of ms); no hardware, a piston at rest.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time

MODES = ("ok", "bad_hello", "stamp_future", "clock", "accept_duty", "accept_opcode",
         "ignore_eof", "ignore_close", "late", "clock_nan", "clock_back", "clock_unix",
         "stale_unix")
#: Where the Unix-time modes' clock starts [s].
UNIX_T0 = 1.7e9
TS = 0.004
RIG = {"A_a": 7.854e-3, "A_b": 7.54e-3, "x_min": -0.0015, "x_max": 0.0485, "V0a": 5.036e-5,
       "V0b": 2.916e-5, "p0": 101325.0, "p_s": 6.0e5, "T0": 283.15, "n": 1.2, "R": 287.0,
       "Ts": TS, "pwm_hz": 60.0, "pwm_update": "immediate"}
#: How long ignore_eof keeps running after end of input [s] (the check kills it long before).
LINGER = 30.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=MODES, default="ok")
    parser.add_argument("--delay", type=float, default=1.0, help="the late reply's delay [s]")
    args = parser.parse_args()
    mode = args.mode
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    rig = {k: v for k, v in RIG.items() if not (mode == "bad_hello" and k == "pwm_update")}
    hello = json.dumps({"protocol": "pneutune.rig/1", "Ts": TS, "rig": rig}).encode()

    def reply(body: bytes) -> None:
        out.write(b"K" + body)
        out.flush()

    def error(message: str) -> int:
        body = message.encode()
        out.write(b"E" + struct.pack("<I", len(body)) + body)
        out.flush()
        return 1

    k = 0
    t = 0.0
    while True:
        op = inp.read(1)
        if not op:  # end of input
            if mode == "ignore_eof":
                time.sleep(LINGER)
            return 0
        if op == b"H":
            reply(struct.pack("<I", len(hello)) + hello)
        elif op == b"R":
            stamp = t + TS if mode == "stamp_future" and k >= 20 else t
            t_read = 0.0 if mode == "clock_back" and k == 30 else t
            stamps = [stamp] * 4
            if mode == "stale_unix" and k >= 30:
                stamps[0] = 30 * TS
            if mode in ("clock_unix", "stale_unix"):
                t_read, stamps = UNIX_T0 + t_read, [UNIX_T0 + st for st in stamps]
            reply(struct.pack("<9d", t_read, 0.0235, 2.0e5, 2.0e5, 6.0e5, *stamps))
        elif op == b"W":
            raw = inp.read(32)
            if len(raw) < 32:
                return 0
            duties = struct.unpack("<4d", raw)
            if mode != "accept_duty" and not all(0.0 <= d <= 1.0 for d in duties):  # NaN too
                return error(f"duties must be in [0, 1], got {list(duties)}")
            reply(b"")
        elif op == b"A":
            if mode == "late" and k == 50:
                time.sleep(args.delay)
            k += 1
            t = (2 * k - 100) * TS if mode == "clock" and k > 100 else k * TS
            t_sent = UNIX_T0 + t if mode in ("clock_unix", "stale_unix") else t
            reply(struct.pack("<d", float("nan") if mode == "clock_nan" and k == 30 else t_sent))
        elif op == b"C":
            reply(b"")
            if mode != "ignore_close":
                return 0
        elif mode == "accept_opcode":
            reply(b"")
        else:
            return error(f"unknown request {op!r}")


if __name__ == "__main__":
    raise SystemExit(main())
