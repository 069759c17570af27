"""A rig driver speaking ``pneutune.rig/1`` whose piston rests mid-stroke, and which can spy,
lie about its period, die or press Ctrl-C.

For the ``record`` tests: ``--log F`` appends every opcode it receives to F (so a test sees
that ``--plan`` sent no ``R``, ``W`` or ``A``); ``--sample-period S`` is the period its hello
gives (default the rig block's 4 ms, whatever a client asked for); ``--die-at N`` exits with
status 1 at the N-th ``A`` without a reply (a driver that crashes mid-run); ``--interrupt-at
N`` sends SIGINT to its parent at the N-th ``A`` (a Ctrl-C at the terminal, which reaches the
client alone: the driver runs in a session of its own), and with ``--interrupt-again`` once
more at each later ``W`` and at ``C`` (an impatient user while the valves close and the log is
written).

Standard library only; the chambers sit at ambient, the supply at 6 bar, every channel fresh.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import struct
import sys

RIG = {"A_a": 7.854e-3, "A_b": 7.54e-3, "x_min": -0.0015, "x_max": 0.0485, "V0a": 5.036e-5,
       "V0b": 2.916e-5, "p0": 101325.0, "p_s": 6.0e5, "T0": 283.15, "n": 1.2, "R": 287.0,
       "Ts": 0.004, "pwm_hz": 60.0, "pwm_update": "immediate"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log")
    parser.add_argument("--sample-period", type=float, default=RIG["Ts"])
    parser.add_argument("--die-at", type=int, default=-1)
    parser.add_argument("--interrupt-at", type=int, default=-1)
    parser.add_argument("--interrupt-again", action="store_true")
    args = parser.parse_args()
    ts = args.sample_period
    hello = json.dumps({"protocol": "pneutune.rig/1", "Ts": ts, "rig": RIG}).encode()
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    spy = open(args.log, "a", encoding="ascii") if args.log else None
    k = 0
    x = 0.5 * (RIG["x_min"] + RIG["x_max"])
    while True:
        op = inp.read(1)
        if not op:
            return 0
        if spy is not None:
            spy.write(op.decode("ascii", "replace"))
            spy.flush()
        if op == b"H":
            out.write(b"K" + struct.pack("<I", len(hello)) + hello)
        elif op == b"R":
            t = k * ts
            out.write(b"K" + struct.pack("<9d", t, x, RIG["p0"], RIG["p0"], RIG["p_s"],
                                         t, t, t, t))
        elif op == b"W":
            if len(inp.read(32)) < 32:
                return 0
            if args.interrupt_again and 0 < args.interrupt_at <= k:
                os.kill(os.getppid(), signal.SIGINT)
            out.write(b"K")
        elif op == b"A":
            k += 1
            if k == args.die_at:
                return 1
            if k == args.interrupt_at:
                os.kill(os.getppid(), signal.SIGINT)
            out.write(b"K" + struct.pack("<d", k * ts))
        elif op == b"C":
            if args.interrupt_again and 0 < args.interrupt_at <= k:
                os.kill(os.getppid(), signal.SIGINT)
            out.write(b"K")
            out.flush()
            return 0
        else:
            msg = b"unknown request"
            out.write(b"E" + struct.pack("<I", len(msg)) + msg)
            out.flush()
            return 1
        out.flush()


if __name__ == "__main__":
    raise SystemExit(main())
