"""Another simulator of the same physics: deploy -> identify -> tune -> deploy over the pipe.

What a commissioning engineer does on a rig nobody modelled for pneutune, with the rig played by
``tests/drivers/other_sim_driver.py``: a simulator of the paper's Sec. 2 written apart from
pneutune's (LuGre friction, valves that open along a ramp, fixed-step RK4), run as a program and
reached only through the driver protocol ``pneutune.rig/1`` (``deploy --rig exec:``); the truth
the identified model is compared with is the driver's own (``--print-plant``). For each plant of
``PLANTS``:

1. ``deploy data/controller-paper.yaml --scenario all`` on the driver: the paper's gains, scored,
   and the closed-loop logs (``--id-scenario``'s is the one identified with ``--id-log deploy``;
   12 s at 4 ms);
2. with ``--id-log record`` or ``both``: ``record --experiment identification`` on the driver
   (``--sample-period 0.0005``: the driver samples every 0.5 ms, the duties change every 4 ms;
   about 150 s of the protocol), whose ``--json`` summary gives the end-stop contact speeds;
3. ``identify`` on the log (``deploy``: the closed-loop log; ``record``: the identification
   run; ``both``: the two together, ``identify A.mcap B.mcap``); the model is compared with the
   driver's truth (C and b per valve, F_C, b_v, the mass): each value, and whether the
   identified range holds the truth;
4. ``tune --trials N --seed S`` on the model;
5. ``deploy`` of the tuned controller.yaml on the driver, every scenario, the same noise seed.

The table's "log check" column is tune's replay of the identified log's closed loop on the
model (tune/logcheck.py): ``warning`` when the rig and the model disagree, or when the tuned
controller does worse than the logged one there (``skipped`` for a log that is no closed loop).
Two more tables give every identified parameter and valve timing against the driver's truth
(the delays' truth is the driver's step equivalent, see `timing_errors`) and the end-stop
contacts that ``record`` measured.

A row passes when every command exits 0 and the tuned controller's E_p is below the paper's
gains' in every Table-1 scenario. Nothing of pneutune's own simulator is in the loop but the
closed loops inside ``tune``.

    .venv/bin/python benchmarks/other_sim.py [--plants rig,rough,latched] [--trials 200]
        [--seed 1] [--out reports/other_sim] [--id-scenario sine-0.5hz]
        [--id-log deploy|record|both]

Prints the table and writes ``OUT/other_sim.json`` and ``OUT/other_sim.md``. Exit status 0
when every row passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from pneutune.control.constants import VALVES
from pneutune.control.sim.scenarios import GROUPS

ROOT = Path(__file__).resolve().parents[1]
#: The other simulator, a program the tests run too (never imported here).
DRIVER = ROOT / "tests" / "drivers" / "other_sim_driver.py"
PAPER = ROOT / "data" / "controller-paper.yaml"
TABLE1: tuple[str, ...] = GROUPS["table1"]
#: What ``--id-log`` takes: the paper's closed-loop deploy log, the identification run that
#: ``record`` writes, or both identified together.
ID_LOGS: tuple[str, ...] = ("deploy", "record", "both")
#: The sample period the identification run asks the driver for [s] (the duties still change
#: every rig.Ts = 4 ms).
RECORD_SAMPLE_PERIOD = 0.0005
#: The scenario whose plant carries the payload (the driver adds it, and counts it in the moving
#: mass of its truth).
HEAVY_SCENARIO = "sine-0.5hz-heavy"


def _valves(C: tuple[float, ...], b: tuple[float, ...], on: tuple[float, ...],
            off: tuple[float, ...], pulse: tuple[float, ...]) -> dict[str, dict[str, float]]:
    return {n: {"C": c, "b": bb, "delay_on": d1, "delay_off": d2, "min_pulse": mp}
            for n, c, bb, d1, d2, mp in zip(VALVES, C, b, on, off, pulse, strict=True)}


#: The driver's plants (its own file format, tests/drivers/other_sim_driver.py): the paper's rig,
#: a rough one (more friction, unequal and slower valves, a seal leak) and a latched one.
PLANTS: dict[str, dict[str, Any]] = {
    "rig": {},
    "rough": {
        "mass": 1.4,
        "friction": {"F_C": 95.0, "F_S": 150.0, "v_s": 0.005, "alpha": 1.5, "b_v": 2500.0},
        "valves": _valves((9.6e-9, 7.1e-9, 8.0e-9, 9.9e-9), (0.26, 0.15, 0.22, 0.28),
                          (3.0e-3, 2.5e-3, 3.5e-3, 2.0e-3), (1.5e-3, 2.0e-3, 1.2e-3, 2.5e-3),
                          (2.5e-3, 2.0e-3, 2.8e-3, 1.8e-3)),
        "leak": {"C_ab": 1.0e-10},
    },
    "latched": {
        "mass": 1.8,
        "pwm_update": "latched",
        "friction": {"F_C": 45.0, "F_S": 70.0, "v_s": 0.003, "alpha": 2.0, "b_v": 4500.0},
        "valves": _valves((7.5e-9, 8.8e-9, 9.2e-9, 7.0e-9), (0.20, 0.30, 0.16, 0.24),
                          (1.5e-3, 1.8e-3, 2.2e-3, 1.2e-3), (1.0e-3, 1.4e-3, 1.6e-3, 1.1e-3),
                          (1.2e-3, 1.5e-3, 1.4e-3, 1.6e-3)),
    },
}


def _bin(name: str) -> str:
    exe = Path(sys.executable).with_name(name)
    return str(exe) if exe.is_file() else name


def _run(cmd: list[str]) -> tuple[int, dict[str, Any] | None, str]:
    """Run a command that prints JSON last (a pneutune command with ``--json``, the driver's
    ``--print-plant``): (exit status, that JSON, its last stderr line)."""
    proc = subprocess.run(cmd, capture_output=True, text=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    lines = proc.stdout.strip().splitlines()
    obj = json.loads(lines[-1]) if lines else None
    tail = proc.stderr.strip().splitlines()[-1:] if proc.stderr.strip() else [""]
    return proc.returncode, obj, tail[0]


def _driver_rig(plant: Path, sample_period: bool = False) -> str:
    """``--rig exec:...`` for the driver with ``plant``, its placeholders left to the client."""
    rig = (f"exec:{shlex.quote(sys.executable)} {shlex.quote(str(DRIVER))} --plant "
           f"{shlex.quote(str(plant))} --scenario {{scenario}} --seed {{seed}}")
    return rig + (" --sample-period {sample_period}" if sample_period else "")


def deploy(controller: Path, plant: Path, log: Path, seed: int) -> tuple[int, dict[str, Any] | None,
                                                                        str]:
    """Every scenario of ``controller`` on the driver with ``plant``; logs ``log``-<scenario>."""
    return _run([_bin("deploy"), str(controller), "--rig", _driver_rig(plant), "--scenario",
                 "all", "--seed", str(seed), "--log", str(log), "--json"])


def record(plant: Path, log: Path, seed: int,
           sample_period: float = RECORD_SAMPLE_PERIOD) -> tuple[int, dict[str, Any] | None, str]:
    """The identification run on the driver with ``plant``, sampled every ``sample_period``.

    Parameters
    ----------
    plant : Path
        The driver's plant file.
    log : Path
        The MCAP log to write.
    seed : int
        The driver's noise seed (``{seed}``).
    sample_period : float
        ``record --sample-period`` [s]; the driver's ``--sample-period``.

    Returns
    -------
    tuple
        ``record``'s exit status, its ``--json`` summary (None when it printed none) and its last
        stderr line.
    """
    return _run([_bin("record"), "--experiment", "identification", "--rig",
                 _driver_rig(plant, sample_period=True), "--sample-period", repr(sample_period),
                 "--seed", str(seed), "--out", str(log), "--json"])


def driver_truth(plant: Path, scenario: str) -> tuple[int, dict[str, Any] | None, str]:
    """The driver's truth for ``plant`` in ``scenario`` (``other_sim_driver.py --print-plant``).

    Parameters
    ----------
    plant : Path
        The driver's plant file.
    scenario : str
        The scenario (or experiment) of the identified log: the heavy sine adds its payload to
        the moving mass.

    Returns
    -------
    tuple
        The driver's exit status, its truth (None when it printed none): ``plant``, the complete
        plant in its own file format, and ``moving_mass`` [kg]; and its last stderr line.
    """
    return _run([sys.executable, str(DRIVER), "--plant", str(plant), "--scenario", scenario,
                 "--print-plant"])


def truth_errors(model_path: Path, truth: dict[str, Any]) -> dict[str, Any]:
    """Identified value against the driver's truth: relative error and whether in range.

    Parameters
    ----------
    model_path : Path
        The model.yaml that ``identify`` wrote.
    truth : dict
        The driver's truth for the identified log's scenario (`driver_truth`): its complete
        ``plant`` and the ``moving_mass`` (the plant's mass, plus the heavy sine's payload).

    Returns
    -------
    dict
        Per parameter (``a_in.C``, ..., ``F_C``, ``b_v``, ``mass``): ``identified``, ``truth``,
        ``rel`` (identified / truth - 1) and ``inside`` (whether the identified range holds the
        truth; None where the model gives no range).
    """
    plant = truth["plant"]
    m = yaml.safe_load(model_path.read_text())
    out: dict[str, Any] = {}

    def one(key: str, value: float, lo: float | None, hi: float | None, true: float) -> None:
        inside = None if lo is None or hi is None else bool(lo <= true <= hi)
        out[key] = {"identified": value, "truth": true, "rel": value / true - 1.0,
                    "inside": inside}

    for name in VALVES:
        v, t = m["valves"][name], plant["valves"][name]
        one(f"{name}.C", v["C"], v["C_min"], v["C_max"], t["C"])
        one(f"{name}.b", v["b"], v["b_min"], v["b_max"], t["b"])
    one("F_C", m["friction"]["F_C"], None, None, plant["friction"]["F_C"])
    th = m["theta"]
    one("b_v", m["friction"]["b_v"], th["min"][2], th["max"][2], plant["friction"]["b_v"])
    one("mass", m["mass"], *m["mass_range"], truth["moving_mass"])
    return out


def timing_errors(model_path: Path, truth: dict[str, Any]) -> dict[str, Any]:
    """Identified valve timings against the driver's: delays and minimum pulse per valve.

    The driver's armature starts moving ``max(delay, min_pulse)`` after a coil edge and moves
    along a ramp; pneutune's valve model switches in one step. The truth of a delay is
    therefore the step that passes the same air: the start of the movement plus half the ramp.

    Parameters
    ----------
    model_path : Path
        The model.yaml that ``identify`` wrote.
    truth : dict
        The driver's truth (`driver_truth`); its complete ``plant`` gives the valves.

    Returns
    -------
    dict
        Per ``<valve>.delay_on``, ``<valve>.delay_off``, ``<valve>.min_pulse``: ``identified``,
        ``truth``, ``rel`` and ``inside`` (None: the model gives no range for them).
    """
    plant = truth["plant"]
    m = yaml.safe_load(model_path.read_text())
    out: dict[str, Any] = {}
    for name in VALVES:
        v, t = m["valves"][name], plant["valves"][name]
        half = 0.5 * t["ramp"]
        true = {"delay_on": max(t["delay_on"], t["min_pulse"]) + half,
                "delay_off": max(t["delay_off"], t["min_pulse"]) + half,
                "min_pulse": t["min_pulse"]}
        for key, value in true.items():
            out[f"{name}.{key}"] = {"identified": v[key], "truth": value,
                                    "rel": v[key] / value - 1.0 if value > 0 else math.nan,
                                    "inside": None}
    return out


def _usage_error(code: int, err: str) -> bool:
    """Whether a command's exit status and last stderr line are argparse's usage error."""
    return code == 2 and ("unrecognized arguments" in err or "usage:" in err)


def run_plant(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """deploy (paper) -> [record] -> identify -> tune -> deploy (tuned) for one plant.

    Parameters
    ----------
    name : str
        A key of `PLANTS`.
    args : argparse.Namespace
        ``out``, ``seed``, ``trials``, ``id_scenario`` and ``id_log`` (one of `ID_LOGS`).

    Returns
    -------
    dict
        The row: ``stage`` reached, ``passed``, ``error`` when a command failed, the paper's
        and the tuned E_p per scenario, ``identified`` (`truth_errors`), ``record`` (the
        identification run's summary, with its contacts), the tune's objective and log check.
    """
    t0 = time.perf_counter()
    work = Path(args.out) / name
    work.mkdir(parents=True, exist_ok=True)
    plant_yaml = work / "plant.yaml"
    plant_yaml.write_text(yaml.safe_dump(PLANTS[name], sort_keys=False))
    id_log = args.id_log
    row: dict[str, Any] = {"plant": name, "id_log": id_log, "stage": "deploy paper",
                           "passed": False}
    code, paper, err = deploy(PAPER, plant_yaml, work / "paper.mcap", args.seed)
    if code != 0 or paper is None:
        row["error"] = f"exit {code}: {err}"
        return row
    row["paper"] = {s: r.get("E_p_mm") for s, r in paper["scenarios"].items()}
    logs: list[Path] = []
    if id_log in ("deploy", "both"):
        logs.append(work / f"paper-{args.id_scenario}.mcap")
    if id_log in ("record", "both"):
        row["stage"] = "record"
        t1 = time.perf_counter()
        code, summary, err = record(plant_yaml, work / "record.mcap", args.seed)
        if summary is not None:
            row["record"] = {k: summary.get(k) for k in (
                "status", "duration_s", "samples", "sample_period", "control_period",
                "contacts", "fault")}
            row["record"]["seconds"] = time.perf_counter() - t1
        if code != 0 or summary is None:
            row["error"] = f"exit {code}: {err}"
            return row
        logs.append(work / "record.mcap")
    row["stage"] = "identify"
    code, _, err = _run([_bin("identify"), *map(str, logs), "--out", str(work / "identify"),
                         "--json"])
    if code != 0:
        row["error"] = f"exit {code}: {err}"
        if len(logs) > 1 and _usage_error(code, err):
            row["error"] += (" -- this identify takes one log only; --id-log both needs "
                             "identify LOG.mcap LOG.mcap (several logs of one rig)")
        return row
    model = work / "identify" / "model.yaml"
    # the identified log's scenario: the deploy log's, else the identification run (no payload;
    # --id-log both with the heavy sine is refused)
    scenario = args.id_scenario if id_log == "deploy" else "identification"
    code, truth, err = driver_truth(plant_yaml, scenario)
    if code != 0 or truth is None:
        row["error"] = f"driver --print-plant: exit {code}: {err}"
        return row
    row["identified"] = truth_errors(model, truth)
    row["timing"] = timing_errors(model, truth)
    row["stage"] = "tune"
    t1 = time.perf_counter()
    code, tuned_json, err = _run([_bin("tune"), "--model", str(model), "--trials",
                                  str(args.trials), "--seed", str(args.seed), "--out",
                                  str(work / "tune"), "--json"])
    row["tune_s"] = time.perf_counter() - t1
    if code != 0 or tuned_json is None:
        row["error"] = f"exit {code}: {err}"
        return row
    row["objective"] = tuned_json["best"]["objective"]
    row["behind_paper"] = tuned_json.get("behind_paper")
    row["log_check"] = tuned_json.get("log_check")
    row["stage"] = "deploy tuned"
    code, tuned, err = deploy(work / "tune" / "controller.yaml", plant_yaml, work / "tuned.mcap",
                              args.seed)
    if code != 0 or tuned is None:
        row["error"] = f"exit {code}: {err}"
        return row
    row["tuned"] = {s: r.get("E_p_mm") for s, r in tuned["scenarios"].items()}
    row["stage"] = "done"
    row["passed"] = all(row["tuned"][s] < row["paper"][s] for s in TABLE1)
    row["seconds"] = time.perf_counter() - t0
    return row


def table(rows: list[dict[str, Any]], scenarios: tuple[str, ...]) -> str:
    """Markdown: per plant, the log identified, the identified parameters outside their range,
    the tune, whether tune's replay of the log's closed loop warned (tune/logcheck.py), E_p.

    Parameters
    ----------
    rows : list of dict
        `run_plant`'s rows.
    scenarios : tuple of str
        The E_p columns.

    Returns
    -------
    str
    """
    head = ("| plant | id log | stage | outside range | largest \\|rel. error\\| | objective | "
            "log check | " + " | ".join(scenarios) + " | pass |")
    out = [head, "|" + "---|" * (8 + len(scenarios))]
    for r in rows:
        ident = r.get("identified", {})
        outside = [k for k, v in ident.items() if v["inside"] is False] or ["none"]
        worst = max(ident.items(), key=lambda kv: abs(kv[1]["rel"]), default=None)
        worst_s = f"{worst[0]} {worst[1]['rel']:+.0%}" if worst else "-"
        eps = [f"{r['tuned'][s]:.2f} / {r['paper'][s]:.2f}" if "tuned" in r
               else (f"- / {r['paper'][s]:.2f}" if "paper" in r else "-") for s in scenarios]
        obj = f"{r['objective']:.3f}" if "objective" in r else "-"
        lc = r.get("log_check") or {}
        check = ("warning" if lc.get("warnings") else "skipped" if lc.get("skipped")
                 else "agrees" if lc else "-")
        stage = r["stage"] if "error" not in r else f"{r['stage']}: {r['error']}"
        out.append(f"| {r['plant']} | {r.get('id_log', 'deploy')} | {stage} | "
                   f"{', '.join(outside)} | {worst_s} | {obj} | {check} | "
                   + " | ".join(eps) + f" | {'yes' if r['passed'] else '**no**'} |")
    return "\n".join(out)


def _num(value: float) -> str:
    return f"{value:.4g}" if abs(value) >= 1e-3 else f"{value:.4e}"


def identified_table(rows: list[dict[str, Any]]) -> str:
    """Markdown: every identified parameter and valve timing against the driver's truth.

    Parameters
    ----------
    rows : list of dict
        `run_plant`'s rows.

    Returns
    -------
    str
        One line per plant and parameter: truth, identified value, relative error, whether the
        identified range holds the truth (``-``: the model gives no range). Delays are in ms,
        their truth the driver's step equivalent (`timing_errors`).
    """
    out = ["| plant | id log | parameter | truth | identified | rel. error | truth in range |",
           "|---|---|---|---:|---:|---:|---|"]
    for r in rows:
        for key, v in r.get("identified", {}).items():
            inside = "-" if v["inside"] is None else ("yes" if v["inside"] else "**no**")
            out.append(f"| {r['plant']} | {r.get('id_log', 'deploy')} | {key} | "
                       f"{_num(v['truth'])} | {_num(v['identified'])} | {v['rel']:+.1%} | "
                       f"{inside} |")
        for key, v in r.get("timing", {}).items():
            out.append(f"| {r['plant']} | {r.get('id_log', 'deploy')} | {key} [ms] | "
                       f"{v['truth'] * 1e3:.3f} | {v['identified'] * 1e3:.3f} | "
                       f"{v['rel']:+.1%} | - |")
    return "\n".join(out)


def contacts_table(rows: list[dict[str, Any]]) -> str:
    """Markdown: the end-stop contacts ``record`` measured, per plant (none without a record).

    Parameters
    ----------
    rows : list of dict
        `run_plant`'s rows.

    Returns
    -------
    str
        One line per contact: the stop, the approach segment, when, the measured and the
        planned approach speed.
    """
    out = ["| plant | stop | segment | t [s] | speed [mm/s] | planned [mm/s] |",
           "|---|---|---|---:|---:|---:|"]
    for r in rows:
        rec = r.get("record")
        if rec is None:
            continue
        for c in rec.get("contacts") or []:
            out.append(f"| {r['plant']} | {c['stop']} | {c['segment']} | {c['t']:.3f} | "
                       f"{c['speed'] * 1e3:.1f} | {c['planned'] * 1e3:.0f} |")
        if not rec.get("contacts"):
            out.append(f"| {r['plant']} | none | - | - | - | - |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Command line; see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--plants", default=",".join(PLANTS), help=f"of {list(PLANTS)}")
    ap.add_argument("--trials", type=int, default=200, help="tune --trials (default 200)")
    ap.add_argument("--seed", type=int, default=1, help="tune and sensor-noise seed")
    ap.add_argument("--out", default="reports/other_sim")
    ap.add_argument("--id-scenario", default="sine-0.5hz",
                    help="the paper's closed-loop log that is identified (default sine-0.5hz)")
    ap.add_argument("--id-log", choices=ID_LOGS, default="deploy",
                    help="the log identified: deploy (the paper's closed-loop log of "
                         "--id-scenario, default), record (the identification run on the "
                         f"driver, sampled every {RECORD_SAMPLE_PERIOD * 1e3:g} ms) or both "
                         "(identified together)")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.plants.split(",") if n.strip()]
    unknown = [n for n in names if n not in PLANTS]
    if unknown:
        ap.error(f"unknown plants {unknown}; choose from {list(PLANTS)}")
    if args.id_log == "both" and args.id_scenario == HEAVY_SCENARIO:
        ap.error(f"--id-log both with --id-scenario {HEAVY_SCENARIO}: the two logs would have "
                 "different moving masses (the payload), which one model cannot fit")
    rows = []
    for name in names:
        row = run_plant(name, args)
        rows.append(row)
        print(f"{name}: {row['stage']}{' ' + row['error'] if 'error' in row else ''}, "
              f"{'pass' if row['passed'] else 'FAIL'}", file=sys.stderr, flush=True)
    scenarios = tuple(next((r["paper"] for r in rows if "paper" in r), {s: 0 for s in TABLE1}))
    source = {"deploy": f"the paper's {args.id_scenario} log",
              "record": "the identification run (record)",
              "both": f"the paper's {args.id_scenario} log and the identification run"}
    md = (f"{table(rows, scenarios)}\n\n"
          f"Identified against the driver's truth:\n\n{identified_table(rows)}\n")
    if args.id_log != "deploy":
        md += f"\nEnd-stop contacts of the identification run:\n\n{contacts_table(rows)}\n"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "other_sim.json").write_text(json.dumps(rows, indent=1))
    (out / "other_sim.md").write_text(
        f"# Another simulator: tuned / paper's gains, E_p [mm], tune --trials {args.trials}, "
        f"seed {args.seed}, identified from {source[args.id_log]}\n\n{md}")
    print(md)
    return 0 if all(r["passed"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
