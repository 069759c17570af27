"""Another simulator of the same physics: deploy -> identify -> tune -> deploy over the pipe.

What a commissioning engineer does on a rig nobody modelled for pneutune, with the rig played by
``benchmarks/other_sim_driver.py``: a simulator of the paper's Sec. 2 written apart from
pneutune's (LuGre friction, valves that open along a ramp, fixed-step RK4), reached only through
the driver protocol ``pneutune.rig/1`` (``deploy --rig exec:``). For each plant of ``PLANTS``:

1. ``deploy data/controller-paper.yaml --scenario all`` on the driver: the paper's gains, scored,
   and the closed-loop logs (``--id-scenario``'s is the one identified; 12 s at 4 ms);
2. ``identify`` on that log; the model is compared with the driver's truth (C and b per valve,
   F_C, b_v, the mass): each value, and whether the identified range holds the truth;
3. ``tune --trials N --seed S`` on the model;
4. ``deploy`` of the tuned controller.yaml on the driver, every scenario, the same noise seed.

The table's "log check" column is tune's replay of the identified log's closed loop on the
model (tune/logcheck.py): ``warning`` when the rig and the model disagree, or when the tuned
controller does worse than the logged one there.

A row passes when every command exits 0 and the tuned controller's E_p is below the paper's
gains' in every Table-1 scenario. Nothing of pneutune's own simulator is in the loop but the
closed loops inside ``tune``.

    .venv/bin/python benchmarks/other_sim.py [--plants rig,rough,latched] [--trials 200]
        [--seed 1] [--out reports/other_sim] [--id-scenario sine-0.5hz]

Prints the table and writes ``OUT/other_sim.json`` and ``OUT/other_sim.md``. Exit status 0
when every row passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml
from other_sim_driver import load_plant_dict  # beside this script (sys.path[0])

from pneutune.control.constants import VALVES
from pneutune.control.sim.scenarios import GROUPS

ROOT = Path(__file__).resolve().parents[1]
DRIVER = ROOT / "benchmarks" / "other_sim_driver.py"
PAPER = ROOT / "data" / "controller-paper.yaml"
TABLE1: tuple[str, ...] = GROUPS["table1"]


def _valves(C: tuple[float, ...], b: tuple[float, ...], on: tuple[float, ...],
            off: tuple[float, ...], pulse: tuple[float, ...]) -> dict[str, dict[str, float]]:
    return {n: {"C": c, "b": bb, "delay_on": d1, "delay_off": d2, "min_pulse": mp}
            for n, c, bb, d1, d2, mp in zip(VALVES, C, b, on, off, pulse, strict=True)}


#: The driver's plants (its own file format, benchmarks/other_sim_driver.py): the paper's rig,
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
    """Run a pneutune command with ``--json``: (exit status, its JSON, its last stderr line)."""
    proc = subprocess.run(cmd, capture_output=True, text=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    lines = proc.stdout.strip().splitlines()
    obj = json.loads(lines[-1]) if lines else None
    tail = proc.stderr.strip().splitlines()[-1:] if proc.stderr.strip() else [""]
    return proc.returncode, obj, tail[0]


def deploy(controller: Path, plant: Path, log: Path, seed: int) -> tuple[int, dict[str, Any] | None,
                                                                        str]:
    """Every scenario of ``controller`` on the driver with ``plant``; logs ``log``-<scenario>."""
    rig = (f"exec:{shlex.quote(sys.executable)} {shlex.quote(str(DRIVER))} --plant "
           f"{shlex.quote(str(plant))} --scenario {{scenario}} --seed {{seed}}")
    return _run([_bin("deploy"), str(controller), "--rig", rig, "--scenario", "all", "--seed",
                 str(seed), "--log", str(log), "--json"])


def truth_errors(model_path: Path, plant: dict[str, Any]) -> dict[str, Any]:
    """Identified value against the driver's truth: relative error and whether in range."""
    truth = load_plant_dict(plant)
    m = yaml.safe_load(model_path.read_text())
    out: dict[str, Any] = {}

    def one(key: str, value: float, lo: float | None, hi: float | None, true: float) -> None:
        inside = None if lo is None or hi is None else bool(lo <= true <= hi)
        out[key] = {"identified": value, "truth": true, "rel": value / true - 1.0,
                    "inside": inside}

    for name in VALVES:
        v, t = m["valves"][name], truth["valves"][name]
        one(f"{name}.C", v["C"], v["C_min"], v["C_max"], t["C"])
        one(f"{name}.b", v["b"], v["b_min"], v["b_max"], t["b"])
    one("F_C", m["friction"]["F_C"], None, None, truth["friction"]["F_C"])
    th = m["theta"]
    one("b_v", m["friction"]["b_v"], th["min"][2], th["max"][2], truth["friction"]["b_v"])
    one("mass", m["mass"], *m["mass_range"], truth["mass"])
    return out


def run_plant(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """deploy (paper) -> identify -> tune -> deploy (tuned) for one plant."""
    t0 = time.perf_counter()
    work = Path(args.out) / name
    work.mkdir(parents=True, exist_ok=True)
    plant_yaml = work / "plant.yaml"
    plant_yaml.write_text(yaml.safe_dump(PLANTS[name], sort_keys=False))
    row: dict[str, Any] = {"plant": name, "stage": "deploy paper", "passed": False}
    code, paper, err = deploy(PAPER, plant_yaml, work / "paper.mcap", args.seed)
    if code != 0 or paper is None:
        row["error"] = f"exit {code}: {err}"
        return row
    row["paper"] = {s: r.get("E_p_mm") for s, r in paper["scenarios"].items()}
    log = work / f"paper-{args.id_scenario}.mcap"
    row["stage"] = "identify"
    code, _, err = _run([_bin("identify"), str(log), "--out", str(work / "identify"), "--json"])
    if code != 0:
        row["error"] = f"exit {code}: {err}"
        return row
    model = work / "identify" / "model.yaml"
    row["identified"] = truth_errors(model, PLANTS[name])
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
    """Markdown: per plant, the identified parameters outside their range, the tune, whether
    tune's replay of the log's closed loop warned (tune/logcheck.py), E_p."""
    head = ("| plant | stage | outside range | largest \\|rel. error\\| | objective | "
            "log check | " + " | ".join(scenarios) + " | pass |")
    out = [head, "|" + "---|" * (7 + len(scenarios))]
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
        out.append(f"| {r['plant']} | {stage} | {', '.join(outside)} | {worst_s} | {obj} | "
                   f"{check} | "
                   + " | ".join(eps) + f" | {'yes' if r['passed'] else '**no**'} |")
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
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.plants.split(",") if n.strip()]
    unknown = [n for n in names if n not in PLANTS]
    if unknown:
        ap.error(f"unknown plants {unknown}; choose from {list(PLANTS)}")
    rows = []
    for name in names:
        row = run_plant(name, args)
        rows.append(row)
        print(f"{name}: {row['stage']}{' ' + row['error'] if 'error' in row else ''}, "
              f"{'pass' if row['passed'] else 'FAIL'}", file=sys.stderr, flush=True)
    scenarios = tuple(next((r["paper"] for r in rows if "paper" in r), {s: 0 for s in TABLE1}))
    md = table(rows, scenarios)
    out = Path(args.out)
    (out / "other_sim.json").write_text(json.dumps(rows, indent=1))
    (out / "other_sim.md").write_text(
        f"# Another simulator: tuned / paper's gains, E_p [mm], tune --trials {args.trials}, "
        f"seed {args.seed}, identified from the paper's {args.id_scenario} log\n\n{md}\n")
    print(md)
    return 0 if all(r["passed"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
