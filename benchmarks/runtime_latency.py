"""Deploy runtime latency, and (``--realtime``) deadline overruns and jitter.

Prints, for the paper's config on sine-0.5hz (one 12 s scenario = 3000 samples, after a
warm-up run):

* the control step alone (:func:`pneutune.control.law.darc.step_into`), p50 and p99;
* the supervisor's sensor check, p50 and p99 (timed separately on the recorded samples);
* sensor to valve (read, supervisor, step, write) and the whole iteration (plus recording and
  advancing the simulated plant), p50 and p99, on the in-process rig and on the example
  driver across a pipe (``--rig pipe-sim``);
* with ``--realtime``: 10 s (``--seconds``) paced to wall time at Ts = 4 ms: overruns, start
  jitter p50/p99/max, schedule slips.

Figures, not assertions; they depend on the machine and its load.

    .venv/bin/python benchmarks/runtime_latency.py [--realtime] [--seconds 10] [--rig sim]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _run(rig_kind: str, seconds: float | None, realtime: bool):
    from pneutune.control.contracts.controller import load_controller
    from pneutune.control.rig.exec_rig import PipeRig
    from pneutune.control.rig.scenario_run import run_scenario, sim_rig_for
    from pneutune.control.sim.scenarios import SCENARIOS

    controller = load_controller(ROOT / "data" / "controller-paper.yaml")
    sc = SCENARIOS["sine-0.5hz"]
    if seconds is not None and seconds > sc.duration:
        sc = type(sc)(sc.name, sc.description, seconds, sc.period, sc.reference,
                      sc.plant_updates, sc.paper)
    if rig_kind == "sim":
        rig, _, _ = sim_rig_for(sc, seed=1)
    else:
        rig = PipeRig(scenario="sine-0.5hz", seed=1)
    try:
        return run_scenario(controller, sc, rig, realtime=realtime, duration=seconds)
    finally:
        rig.close()


def _supervisor_cost(sensors: np.ndarray) -> tuple[float, float]:
    from pneutune.control.contracts.controller import load_controller
    from pneutune.control.rig.supervisor import Supervisor, SupervisorSettings

    sup = Supervisor(SupervisorSettings.from_controller(
        load_controller(ROOT / "data" / "controller-paper.yaml")))
    stamps = np.zeros(4)
    ns = np.empty(sensors.shape[0], dtype=np.int64)
    for k, row in enumerate(sensors):
        t = k * 0.004
        stamps[:] = t
        t0 = time.perf_counter_ns()
        sup.check_sensors(t, row, stamps)
        ns[k] = time.perf_counter_ns() - t0
    return float(np.percentile(ns, 50)) / 1e3, float(np.percentile(ns, 99)) / 1e3


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realtime", action="store_true", help="also run paced to wall time")
    parser.add_argument("--seconds", type=float, default=10.0, help="paced run length [s]")
    parser.add_argument("--rig", choices=["sim", "pipe-sim"], default="sim",
                        help="rig of the paced run")
    args = parser.parse_args()

    for kind in ("sim", "pipe-sim"):
        _run(kind, 1.0, False)  # warm-up (compiled code, caches)
        res = _run(kind, None, False)
        t = res.loop.timing
        print(f"{kind:>8}, as fast as possible, {t.samples} samples: "
              f"step p50 {t.step_p50 * 1e6:.1f} µs, p99 {t.step_p99 * 1e6:.1f} µs; "
              f"sensor-to-valve p50 {t.loop_p50 * 1e6:.1f} µs, p99 {t.loop_p99 * 1e6:.1f} µs; "
              f"iteration p50 {t.iteration_p50 * 1e6:.1f} µs, "
              f"p99 {t.iteration_p99 * 1e6:.1f} µs")
        if kind == "sim":
            p50, p99 = _supervisor_cost(res.loop.recording.sensors_)
            print(f"{'':>8}  supervisor check_sensors: p50 {p50:.1f} µs, p99 {p99:.1f} µs")
    if args.realtime:
        res = _run(args.rig, args.seconds, True)
        t = res.loop.timing
        print(f"{args.rig:>8}, realtime {args.seconds:g} s at Ts = 4 ms ({t.samples} samples, "
              f"wall {t.wall_s:.2f} s): {t.overruns} overruns; jitter p50 "
              f"{t.jitter_p50 * 1e6:.0f} µs, p99 {t.jitter_p99 * 1e6:.0f} µs, max "
              f"{t.jitter_max * 1e6:.0f} µs; slipped {t.slipped_s * 1e3:.1f} ms; "
              f"sensor-to-valve p99 {t.loop_p99 * 1e6:.0f} µs")


if __name__ == "__main__":
    main()
