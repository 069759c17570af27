"""Fleet benchmark: identify -> tune on random plants and every kind of log, scored on the truth.

For each of ``--plants`` seeded random plants (:func:`fleet_plant`, a spread of:
friction F_C 30-120 N, F_S/F_C 1.1-1.8, v_s 2-8 mm/s, alpha 1-3, b_v 1500-5000 N s/m, valve C
±30 % and b 0.12-0.30 per valve, delays 1-4 ms, minimum pulse 1-3 ms, payload 0-1.5 kg, a seal
leak, sensor noise, both PWM update modes) and each log kind

* ``a``: the identification run, sensors every 0.5 ms (``simulate --experiment identification``);
* ``b``: the same run at the 4 ms control rate;
* ``c``: a closed-loop 4 ms log of the paper's gains over the Table-1 references back to back
  (0.5 Hz sine, 0.75 Hz sine, smooth square; 37 s, no labels that identify may use);
* ``d``: the commissioning run, a second protocol (``simulate --experiment commissioning``);
* ``e``: a 12 s closed-loop 4 ms log of the paper's gains on ``sine-0.5hz`` (what ``deploy
  --log`` writes);
* ``t``: no log: the true plant read as a model (``model_from_plant``: every nominal exact, every
  range the value ±20 %), a perfect nominal: whether identification is what limits the tuned
  controller,

it runs ``identify`` on the log, ``tune`` (the command, with a fixed modest trial budget) on the
model, and scores the tuned controller and ``data/controller-paper.yaml`` on the **true** plant
in every Table-1 scenario and the disturbance scenario: E_p and E_rms averaged over noise seeds
1-3 (one seed's maximum is too noisy a judge). A row passes when identify and tune both exit 0
and the tuned controller's mean E_p is below the paper's in every Table-1 scenario.

Real-rig effects (:mod:`pneutune.control.sim.rig_effects`: valve armature lag, lines, heat
transfer, LuGre pre-sliding, sensor lags, IO delay, supply droop) are on in half the plants,
those whose index is 0 or 3 modulo 4 (so both PWM modes have some), at magnitudes drawn inside
the published ranges with the seed ``[seed, index, 24]``. The share, the ranges and the seed
were fixed before any measurement. ``--no-effects`` runs the same plants without them. The
second table compares, per plant, the tune from the identification run (``a``) with the tune
from a closed-loop log (``c``, else ``e``): mean E_p and E_rms over the Table-1 scenarios, and
the tune's own figure on the true plant (:func:`tune_figure`), which weighs the two as the tune
does.

    .venv/bin/python benchmarks/fleet.py [--plants 12] [--kinds a,b,c,d] [--trials 60]
        [--only 0,3] [--out reports/fleet] [--json] [--no-effects]

Prints the table (plant x log -> identify errors, tune status, E_p tuned / paper) and writes
``OUT/fleet.json`` and ``OUT/fleet.md``. Exit status 0 when every row passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.constants import VALVES
from pneutune.control.contracts.atomic import sha256_file
from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.model import save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.contracts.yamlio import write_yaml
from pneutune.control.sim import rig_effects
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import (
    AMPLITUDE,
    GROUPS,
    SCENARIOS,
    Scenario,
    sine,
    smooth_square,
)
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.objective import reference_figures
from pneutune.tune.report import FLOW_LIMITED  # the share of the window report.md flags

KINDS = {
    "a": "identification run, 0.5 ms",
    "b": "identification run, 4 ms",
    "c": "closed loop, paper's gains, Table-1 references, 37 s, 4 ms",
    "d": "commissioning run (second protocol), 4 ms",
    "e": "closed loop, paper's gains, sine-0.5hz, 12 s, 4 ms",
    "t": "no log: the true plant as the model (model_from_plant, ranges ±20 %)",
}
PAPER = Path(__file__).resolve().parents[1] / "data" / "controller-paper.yaml"
SCORED = GROUPS["all"]
#: The quality targets on the true plant [mm]: Table-1 scenarios, disturbance-0.5hz.
QUALITY_MM, QUALITY_DISTURBANCE_MM = 0.20, 0.30
#: Noise seeds the controllers are scored with (the mean over them is the score).
SCORE_SEEDS = (1, 2, 3)
#: The plants with real-rig effects: index modulo 4 in this set (half of them, both PWM modes).
EFFECT_PLANTS = (0, 3)


def has_effects(index: int) -> bool:
    """Whether fleet plant ``index`` carries real-rig effects."""
    return index % 4 in EFFECT_PLANTS


def fleet_plant(index: int, seed: int = 0, effects: bool = True) -> PlantConfig:
    """Random plant ``index`` of the fleet (deterministic in ``seed`` and ``index``).

    The payload is folded into ``mass`` (payload 0), so that the heavy scenario adds its
    1.136 kg on top of the plant's own load, on the true plant as in the tuner's draws. With
    ``effects`` (the default) the plants of :func:`has_effects` get every real-rig effect, at
    magnitudes drawn from their own generator, so the rest of the plant is the same either way.
    """
    rng = np.random.default_rng([seed, index, 11])
    u = rng.uniform
    F_C = u(30.0, 120.0)
    valves = {}
    for name in VALVES:
        delay_on = u(1.0e-3, 4.0e-3)
        valves[name] = {"C": 8.373e-9 * u(0.7, 1.3), "b": u(0.12, 0.30),
                        "delay_on": delay_on, "delay_off": u(1.0e-3, 4.0e-3),
                        "min_pulse": min(u(1.0e-3, 3.0e-3), delay_on)}
    data = {
        "rig": {"pwm_update": "latched" if index % 2 else "immediate"},
        "mass": 1.05 + u(0.0, 1.5),
        "friction": {"F_C": F_C, "F_S": F_C * u(1.1, 1.8), "v_s": u(2.0e-3, 8.0e-3),
                     "alpha": u(1.0, 3.0), "b_v": u(1500.0, 5000.0)},
        "valves": valves,
        "leak": {"C": u(0.2e-10, 2.0e-10)},
        "disturbance": {"F_n": u(-10.0, 10.0)},
        "sensors": {"x_noise": u(2.0e-6, 1.0e-5), "p_noise": u(100.0, 600.0)},
        "sim": {"seed": int(1000 + index)},
    }
    plant = PlantConfig().with_updates(data, source=f"<fleet plant {index}>")
    if effects and has_effects(index):
        m = rig_effects.draw(np.random.default_rng([seed, index, 24]))
        plant = plant.with_updates(rig_effects.plant_updates(m),
                                   source=f"<fleet plant {index}, real-rig effects>")
    return plant


def _quintic(t: np.ndarray, x0: float, x1: float, T: float) -> np.ndarray:
    z = np.clip(t / T, 0.0, 1.0)
    s = z**3 * (10.0 - 15.0 * z + 6.0 * z * z)
    ds = 30.0 * z**2 * (1.0 - z) ** 2 / T
    dds = 60.0 * z * (1.0 - z) * (1.0 - 2.0 * z) / T**2
    d = x1 - x0
    return np.column_stack([x0 + d * s, d * ds, d * dds])


def table1_sequence(t: np.ndarray, center: float) -> np.ndarray:
    """The Table-1 references back to back: 12 s of each sine, a 1 s move, 12 s of square."""
    out = np.empty((t.size, 3))
    parts = ((0.0, 12.0, lambda tt: sine(tt, center, AMPLITUDE, 0.5)),
             (12.0, 24.0, lambda tt: sine(tt, center, AMPLITUDE, 0.75)),
             (24.0, 25.0, lambda tt: _quintic(tt, center, center - AMPLITUDE, 1.0)),
             (25.0, np.inf, lambda tt: smooth_square(tt, center, AMPLITUDE, 0.5)))
    for t0, t1, f in parts:
        sel = (t >= t0) & (t < t1)
        if sel.any():
            out[sel] = f(t[sel] - t0)
    return out


SEQUENCE = Scenario("table1-sequence", "Table-1 references back to back", 37.0, 2.0,
                    table1_sequence)


def write_log(kind: str, plant: PlantConfig, path: Path, seed: int) -> None:
    """Simulate the log of ``kind`` on ``plant`` and save it as MCAP."""
    run = {"seed": str(seed), "fleet_kind": kind}
    if kind in ("a", "b"):
        from pneutune.control.rig.identification_run import simulate_identification

        rec = simulate_identification(plant, seed=seed,
                                      sample_period=5e-4 if kind == "a" else plant.rig.Ts)
        run["experiment"] = "identification"
        rec.save(path, rig=plant.rig_metadata(), run=run)
    elif kind == "d":
        from pneutune.control.rig.commissioning_run import simulate_commissioning

        rec = simulate_commissioning(plant, seed=seed)
        run["experiment"] = "commissioning"
        rec.save(path, rig=plant.rig_metadata(), run=run)
    else:
        paper = load_controller(PAPER)
        sc = SEQUENCE if kind == "c" else SCENARIOS["sine-0.5hz"]
        res = simulate_scenario(paper, sc, plant, seed=seed)
        if kind == "e":  # what deploy --log writes: tune replays this closed loop on the model
            run.update(scenario=sc.name, controller=str(PAPER),
                       controller_sha256=sha256_file(PAPER))
        res.recording().save(path, rig=plant.rig_metadata(), run=run)


@dataclass
class Row:
    """One plant x log."""

    plant: int
    kind: str
    pwm: str
    #: the real-rig effects the true plant has
    effects: list[str] | None = None
    identify: str = "-"
    errors: dict[str, float] | None = None
    tune: str = "-"
    tune_note: str = ""
    e_p: dict[str, tuple[float, float]] | None = None
    #: per scenario, (tuned, paper) E_rms [mm], mean over SCORE_SEEDS
    e_rms: dict[str, tuple[float, float]] | None = None
    seconds: float = 0.0
    tune_seconds: float = 0.0
    #: per scenario, Metrics.flow_limited of the tuned controller on the true plant (the share of
    #: the window with a valve held fully open for 0.1 s or more)
    held_open: dict[str, float] | None = None
    #: tune's ``log_check`` (tune/logcheck.py): the log's closed loop replayed on the model
    log_check: dict[str, Any] | None = None

    def flow_limited(self) -> list[str]:
        """Scenarios where the tuned controller holds a valve fully open, 0.1 s or more at a
        time, for at least FLOW_LIMITED of the metric window (its E_p is set by the valves'
        flow)."""
        return [s for s, f in (self.held_open or {}).items() if f >= FLOW_LIMITED]

    @property
    def passed(self) -> bool:
        """identify and tune exit 0 and tuned E_p < paper's in every Table-1 scenario."""
        if self.identify != "ok" or self.tune != "ok" or not self.e_p:
            return False
        return all(self.e_p[s][0] < self.e_p[s][1] for s in GROUPS["table1"])

    @property
    def on_target(self) -> bool:
        """The E_p target: tuned E_p <= 0.20 mm on every Table-1 scenario and
        <= 0.30 mm on disturbance-0.5hz, on the true plant."""
        if not self.e_p:
            return False
        return all(self.e_p[s][0] <= (QUALITY_DISTURBANCE_MM if s == "disturbance-0.5hz"
                                      else QUALITY_MM) for s in SCORED if s in self.e_p)


def id_errors(model_path: Path, plant: PlantConfig) -> dict[str, float]:
    """Relative errors of the identified model against the true plant (worst valve for C, b)."""
    from pneutune.control.contracts.model import load_model

    m = load_model(model_path)
    tv = plant.valves.ordered()
    mv = m.valves.ordered()
    c = [abs(a.C / b.C - 1.0) for a, b in zip(mv, tv, strict=True)]
    bb = [abs(a.b / b.b - 1.0) for a, b in zip(mv, tv, strict=True)]
    f, tf = m.friction, plant.friction
    return {"C": max(c), "b": max(bb), "F_C": f.F_C / tf.F_C - 1.0, "b_v": f.b_v / tf.b_v - 1.0,
            "M": m.mass / plant.total_mass - 1.0,
            "F_S_range": [m.friction.ranges.F_S[0], m.friction.ranges.F_S[1]]
            if m.friction.ranges is not None else [float("nan")] * 2,
            "F_S": tf.F_S, "outside": outside(m, plant)}


def outside(model: Any, plant: PlantConfig) -> list[str]:
    """The coordinates tune samples whose range misses the true plant's value."""
    from pneutune.control.sim.model_box import uncertainty_box

    truth = {"mass": plant.total_mass, "friction.b_v": plant.friction.b_v,
             "friction.F_C": plant.friction.F_C, "friction.F_S": plant.friction.F_S,
             "friction.v_s": plant.friction.v_s, "friction.alpha": plant.friction.alpha,
             "disturbance.F_n": plant.disturbance.F_n}
    for name, v in zip(VALVES, plant.valves.ordered(), strict=True):
        truth[f"valves.{name}.C"] = v.C
        truth[f"valves.{name}.b"] = v.b
    return [c.key for c in uncertainty_box(model)
            if c.key in truth and not c.low <= truth[c.key] <= c.high]


def score(controller_path: Path, plant: PlantConfig, seeds: tuple[int, ...] = SCORE_SEEDS
          ) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """Mean E_p and E_rms [mm] over the noise ``seeds`` (inf if a run failed) and, from the
    first seed, Metrics.flow_limited of a controller on the true plant, per scored scenario."""
    ctl = load_controller(controller_path)
    e_p, e_rms, full = {}, {}, {}
    for name in SCORED:
        ps, rs = [], []
        for seed in seeds:
            m = simulate_scenario(ctl, SCENARIOS[name], plant, seed=seed).metrics
            ok = m.status == "ok"
            ps.append(m.E_p_mm if ok else float("inf"))
            rs.append(m.E_rms_mm if ok else float("inf"))
            if seed == seeds[0]:
                full[name] = m.flow_limited
        e_p[name] = float(np.mean(ps))
        e_rms[name] = float(np.mean(rs))
    return e_p, e_rms, full


def _exe(name: str) -> str:
    return shutil.which(name, path=os.path.dirname(sys.executable)) or name


def run_row(plant_index: int, kind: str, args: argparse.Namespace) -> Row:
    """Log, identify, tune and score one plant x log kind."""
    t0 = time.perf_counter()
    plant = fleet_plant(plant_index, args.seed, effects=not args.no_effects)
    row = Row(plant_index, kind, plant.rig.pwm_update, effects=list(plant.effects))
    work = Path(args.out) / f"plant{plant_index:02d}" / kind
    work.mkdir(parents=True, exist_ok=True)
    write_yaml(work.parent / "plant.yaml", plant.to_dict(), header="fleet plant (truth)")
    model = work / "identify" / "model.yaml"
    if kind == "t":
        model.parent.mkdir(parents=True, exist_ok=True)
        save_model(model_from_plant(plant), model)
    elif not (args.reuse_identify and model.is_file()):
        log = work / "run.mcap"
        if not log.is_file():
            write_log(kind, plant, log, seed=plant_index + 1)
        proc = subprocess.run([_exe("identify"), str(log), "--out", str(work / "identify"),
                               "--json"], capture_output=True, text=True)
        if proc.returncode != 0:
            row.identify = f"exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}"
            row.seconds = time.perf_counter() - t0
            return row
    row.identify = "ok"
    row.errors = id_errors(model, plant)
    if args.identify_only:
        row.seconds = time.perf_counter() - t0
        return row
    out = work / "tune"
    if out.exists() and not args.resume:
        shutil.rmtree(out)
    t_tune = time.perf_counter()
    proc = subprocess.run([_exe("tune"), "--model", str(model), "--trials", str(args.trials),
                           "--out", str(out), "--seed", str(args.tune_seed),
                           "--draws", str(args.draws), "--restarts", str(args.restarts),
                           "--json"],
                          capture_output=True, text=True)
    row.tune_seconds = time.perf_counter() - t_tune
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or [""]
        row.tune = f"exit {proc.returncode}"
        row.tune_note = tail[0][:200]
        row.seconds = time.perf_counter() - t0
        return row
    res = json.loads(proc.stdout)
    row.tune = "ok"
    row.log_check = res.get("log_check")
    narrowed = res.get("narrowed") or []
    tr = res["trials"]
    row.tune_note = (f"{tr['complete']}/{tr['finished']} complete, {row.tune_seconds:.0f} s"
                     + (f"; narrowed {len(narrowed)}" if narrowed else ""))
    tuned, tuned_rms, row.held_open = score(out / "controller.yaml", plant)
    paper, paper_rms, _ = score(PAPER, plant)
    row.e_p = {s: (tuned[s], paper[s]) for s in SCORED}
    row.e_rms = {s: (tuned_rms[s], paper_rms[s]) for s in SCORED}
    row.seconds = time.perf_counter() - t0
    return row


def _pct(x: float) -> str:
    return f"{x * 100:+.0f}%" if np.isfinite(x) else "nan"


def table(rows: list[Row]) -> str:
    """Markdown table of the fleet."""
    head = ("| plant | PWM | effects | log | C | b | F_C | b_v | M | F_S range (true) | truth "
            "outside the ranges | tune | "
            + " | ".join(f"{s} E_p" for s in SCORED) + " | pass | E_p target |")
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [head, sep]
    for r in rows:
        e = r.errors or {}
        ids = ([f"{e['C'] * 100:.1f}%", f"{e['b'] * 100:.0f}%", _pct(e["F_C"]), _pct(e["b_v"]),
                _pct(e["M"]),
                f"[{e['F_S_range'][0]:.0f}, {e['F_S_range'][1]:.0f}] ({e['F_S']:.0f})",
                ", ".join(e.get("outside", [])) or "none"]
               if e else [r.identify] + [""] * 6)
        flow = r.flow_limited()
        eps = ([f"{r.e_p[s][0]:.2f}{'†' if s in flow else ''} / {r.e_p[s][1]:.2f}"
                for s in SCORED] if r.e_p else ["-"] * len(SCORED))
        tune = r.tune if r.tune != "ok" else f"ok ({r.tune_note})"
        if r.tune != "ok" and r.tune_note:
            tune += f": {r.tune_note}"
        fx = "all" if r.effects and len(r.effects) == len(rig_effects.EFFECTS) else (
            ", ".join(r.effects) if r.effects else "none")
        lines.append(f"| {r.plant} | {r.pwm} | {fx} | {r.kind} | " + " | ".join(ids)
                     + f" | {tune} | "
                     + " | ".join(eps) + f" | {'yes' if r.passed else '**no**'} | "
                     f"{'yes' if r.on_target else 'no'} |")
    return "\n".join(lines)


def _table1_means(r: Row) -> tuple[float, float, float, float] | None:
    """Mean over the Table-1 scenarios of (tuned E_p, tuned E_rms, paper E_p, paper E_rms)."""
    if not r.e_p or not r.e_rms:
        return None
    names = GROUPS["table1"]
    return (float(np.mean([r.e_p[s][0] for s in names])),
            float(np.mean([r.e_rms[s][0] for s in names])),
            float(np.mean([r.e_p[s][1] for s in names])),
            float(np.mean([r.e_rms[s][1] for s in names])))


def tune_figure(r: Row) -> float | None:
    """The tracking part of the tune's objective on the true plant: the mean over the scored
    scenarios of 0.5 (E_p / E_p,ref + E_rms / E_rms,ref), references from Table 1
    (:func:`~pneutune.tune.objective.reference_figures`); None without scores."""
    if not r.e_p or not r.e_rms:
        return None
    terms = []
    for s in r.e_p:
        ref_p, ref_rms = reference_figures(SCENARIOS[s])
        terms.append(0.5 * (r.e_p[s][0] / ref_p + r.e_rms[s][0] / ref_rms))
    return float(np.mean(terms))


def comparison(rows: list[Row]) -> str:
    """Per plant: the tune from the identification run (a) against the tune from a closed-loop
    log (c, else e), mean E_p / E_rms over the Table-1 scenarios on the true plant [mm], and
    the tune's figure (:func:`tune_figure`) of each."""
    by = {(r.plant, r.kind): r for r in rows}
    plants = sorted({r.plant for r in rows})
    lines = ["| plant | effects | paper's gains E_p / E_rms | identification-run tune (a) | "
             "closed-loop-log tune | a at least as good | tune's figure a / other |",
             "|---|---|---|---|---|---|---|"]
    wins = []
    figs: list[tuple[float, float]] = []
    for i in plants:
        a = by.get((i, "a"))
        c = by.get((i, "c")) or by.get((i, "e"))
        ma = _table1_means(a) if a else None
        mc = _table1_means(c) if c else None
        if ma is None and mc is None:
            continue
        ref = ma or mc
        assert ref is not None
        fx = "yes" if (a or c) and (a or c).effects else "no"  # type: ignore[union-attr]
        cell_a = f"{ma[0]:.3f} / {ma[1]:.3f}" if ma else "-"
        cell_c = f"{mc[0]:.3f} / {mc[1]:.3f} ({c.kind})" if mc and c else "-"
        better = "-"
        if ma and mc:
            ok = ma[0] <= mc[0] and ma[1] <= mc[1]
            wins.append(ok)
            better = "yes" if ok else "no"
        fa, fc = (tune_figure(x) if x else None for x in (a, c))
        if fa is not None and fc is not None:
            figs.append((fa, fc))
        cell_f = " / ".join("-" if f is None else f"{f:.3f}" for f in (fa, fc))
        lines.append(f"| {i} | {fx} | {ref[2]:.3f} / {ref[3]:.3f} | {cell_a} | {cell_c} | "
                     f"{better} | {cell_f} |")
    if wins:
        pairs = [(_table1_means(by[(i, "a")]), _table1_means(by.get((i, "c")) or by[(i, "e")]))
                 for i in plants if (i, "a") in by and ((i, "c") in by or (i, "e") in by)]
        pairs = [(x, y) for x, y in pairs if x and y]
        if pairs:
            lines.append("")
            lines.append(f"mean over the plants: identification-run tune E_p "
                         f"{np.mean([x[0] for x, _ in pairs]):.3f} / E_rms "
                         f"{np.mean([x[1] for x, _ in pairs]):.3f} mm; closed-loop-log tune "
                         f"E_p {np.mean([y[0] for _, y in pairs]):.3f} / E_rms "
                         f"{np.mean([y[1] for _, y in pairs]):.3f} mm")
            if figs:
                lines[-1] += (f"; the tune's figure {np.mean([x for x, _ in figs]):.3f} against "
                              f"{np.mean([y for _, y in figs]):.3f} (lower is better)")
    return "\n".join(lines)


def summarise(rows: list[Row]) -> str:
    """One line: rows that pass, rows on the E_p target, the tune wall times."""
    walls = [r.tune_seconds for r in rows if r.tune_seconds > 0.0]
    wall = (f"; tune wall time {min(walls):.0f}-{max(walls):.0f} s (median "
            f"{float(np.median(walls)):.0f} s)" if walls else "")
    flow = sum(bool(r.flow_limited()) for r in rows)
    return (f"{sum(r.passed for r in rows)}/{len(rows)} rows pass (tuned beats the paper's "
            f"gains on every Table-1 scenario); {sum(r.on_target for r in rows)}/{len(rows)} "
            f"on the E_p target (<= {QUALITY_MM:.2f} mm, disturbance <= "
            f"{QUALITY_DISTURBANCE_MM:.2f} mm); {flow} with a flow-limited scenario (†: a valve "
            f"held fully open, 0.1 s or more at a time, >= {FLOW_LIMITED:.0%} of the "
            f"window){wall}")


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main() -> int:
    """Run the fleet and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", type=int, default=12)
    ap.add_argument("--only", help="comma-separated plant indices (default: all)")
    kinds_help = "; ".join(f"{k} = {v}" for k, v in KINDS.items()).replace("%", "%%")
    ap.add_argument("--kinds", default="a,b,c,d",
                    help=f"comma-separated log kinds (default a,b,c,d): {kinds_help}")
    ap.add_argument("--trials", type=int, default=60, help="tune --trials (default 60)")
    ap.add_argument("--seed", type=int, default=0, help="fleet seed (default 0)")
    ap.add_argument("--tune-seed", type=int, default=1, help="tune --seed (default 1)")
    ap.add_argument("--restarts", type=int, default=1,
                    help="tune --restarts (default 1: one study)")
    ap.add_argument("--draws", type=int, default=8,
                    help="tune --draws (default 8, tune's; 1 tunes on the model's nominal plant "
                    "alone: with --kinds t, the true plant itself)")
    ap.add_argument("--out", default="reports/fleet")
    ap.add_argument("--no-effects", action="store_true",
                    help="the same plants without their real-rig effects")
    ap.add_argument("--resume", action="store_true", help="keep existing tune studies")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON on stdout")
    ap.add_argument("--reuse-identify", action="store_true",
                    help="where OUT/plantNN/KIND/identify/model.yaml exists, tune it as it is "
                    "(no new log, no identify)")
    ap.add_argument("--identify-only", action="store_true",
                    help="log (or reuse OUT's logs) and identify only: the identify columns")
    ap.add_argument("--table", metavar="FLEET.json",
                    help="only print the table of an earlier run's fleet.json")
    ap.add_argument("--rescore", action="store_true",
                    help="with --table: score the controllers of that run on the true plants "
                    "again (same noise seeds) and rewrite its fleet.json and fleet.md")
    args = ap.parse_args()
    if args.table:
        path = Path(args.table)
        rows = [Row(**{k: v for k, v in r.items() if k in Row.__dataclass_fields__})
                for r in json.loads(path.read_text())]
        if args.rescore:
            for r in rows:
                ctl = path.parent / f"plant{r.plant:02d}" / r.kind / "tune" / "controller.yaml"
                if r.tune == "ok" and ctl.is_file():
                    plant = fleet_plant(r.plant, args.seed, effects=not args.no_effects)
                    tuned, tuned_rms, r.held_open = score(ctl, plant)
                    paper, paper_rms, _ = score(PAPER, plant)
                    r.e_p = {s: (tuned[s], paper[s]) for s in SCORED}
                    r.e_rms = {s: (tuned_rms[s], paper_rms[s]) for s in SCORED}
            _write_atomic(path.parent / "fleet.md", table(rows) + "\n\n" + summarise(rows)
                          + "\n\n" + comparison(rows) + "\n")
            _write_atomic(path, json.dumps([r.__dict__ | {"passed": r.passed,
                                                          "on_target": r.on_target}
                                            for r in rows], indent=1, default=float))
        print(table(rows))
        print(summarise(rows))
        print(comparison(rows))
        return 0
    plants = ([int(i) for i in args.only.split(",")] if args.only
              else list(range(args.plants)))
    kinds = [k.strip() for k in args.kinds.split(",")]
    for k in kinds:
        if k not in KINDS:
            ap.error(f"unknown log kind {k!r}; expected one of {', '.join(KINDS)}")
    rows: list[Row] = []
    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i in plants:
        for k in kinds:
            r = run_row(i, k, args)
            rows.append(r)
            sys.stderr.write(f"plant {i} log {k}: identify {r.identify}, tune {r.tune} "
                             f"{r.tune_note}, {'pass' if r.passed else 'FAIL'} "
                             f"({r.seconds:.0f} s)\n")
            # after every row, so that an interrupted fleet keeps what it measured
            summary = (summarise(rows) + f"; {(time.perf_counter() - t0) / 60:.1f} min; tune "
                       f"--trials {args.trials} --seed {args.tune_seed} --draws {args.draws} "
                       f"--restarts {args.restarts}; "
                       "kinds: " + "; ".join(f"{k} = {KINDS[k]}" for k in kinds))
            text = table(rows)
            data = [r.__dict__ | {"passed": r.passed, "on_target": r.on_target} for r in rows]
            _write_atomic(out / "fleet.md", text + "\n\n" + summary + "\n\n"
                          + comparison(rows) + "\n")
            _write_atomic(out / "fleet.json", json.dumps(data, indent=1, default=float))
    if args.json:
        print(json.dumps({"rows": data, "summary": summary}, default=float))
    else:
        print(text)
        print(summary)
        print(comparison(rows))
    return 0 if all(r.passed for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
