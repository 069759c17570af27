"""The paper's rig reproduced: Table 1 with the paper's gains on a plant with real-rig effects.

The paper's gains (data/controller-paper.yaml) on the ideal simulated rig track better than the
paper's rig did (E_rms 0.09-0.13 mm against Table 1's 0.16-0.23 mm): a real axis has dynamics
the paper's model lacks. A paper-rig plant (``data/plant-paper-rig.yaml``, once a search finds
one within tolerance on both seed sets; docs/real-rig.md says how close the searches came) is
the paper's geometry and valves plus those effects at magnitudes inside published ranges
(docs/real-rig.md gives each range and its source). This script shows how close a plant comes
to Table 1.

* default: run the four Table-1 scenarios with the paper's gains on ``--plant`` for noise seeds
  ``--seeds`` (default 1 2 3), and print E_p and E_rms (mean over the seeds and their range)
  against Table 1 with the relative difference; the row passes within ``--tolerance`` (25 %).
* ``--search N --out P.yaml``: choose the effect magnitudes by a seeded Optuna search (TPE,
  ``--search-seed``) of N trials (or fewer, if ``--search-timeout`` runs out first) inside the
  published ranges (:data:`pneutune.control.sim.rig_effects.MAGNITUDES`, and :data:`FRICTION`),
  minimising the largest relative difference from Table 1 over the eight figures (mean over
  ``--seeds``). Every magnitude is rounded to :data:`SIGNIFICANT` significant figures, and every
  plant.yaml number derived from them to :data:`DERIVED_SIGNIFICANT`, *before* the plant is
  built: the file written holds exactly the plant that was evaluated. The best ``--check-top``
  trials are then run on the noise seeds ``--check-seeds`` (default 4 5 6), and
  the one whose worst figure over both seed sets is smallest is written, with a header saying
  how it was made, each magnitude with its range and source, and its Table-1 comparison on both
  seed sets. ``--trials-log`` keeps every trial: a JSON line of its number, worst difference and
  magnitudes. The ranges are fixed here, before any search: a search may pick inside
  them, never widen them.

    .venv/bin/python benchmarks/paper_rig.py [--plant data/plant-paper-rig.yaml] [--seeds 1 2 3]
    nice -n 10 .venv/bin/python benchmarks/paper_rig.py --search 1500 --search-timeout 3600 \\
        --out data/plant-paper-rig.yaml
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import textwrap
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig, load_plant
from pneutune.control.contracts.yamlio import write_yaml
from pneutune.control.law.layout import pack
from pneutune.control.sim import rig_effects
from pneutune.control.sim.closed_loop import simulate_scenario
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "data" / "controller-paper.yaml"
PLANT = ROOT / "data" / "plant-paper-rig.yaml"

#: What else the paper does not give, and the search may pick: the friction levels (only b_v is
#: in the paper, with the bounds 2000-5000 N s/m of its θ3; the others within
#: benchmarks/fleet.py's spread) and the sensors' noise (0.1-0.5 % of a 10 bar span for the
#: pressure transmitters; 2-20 um for a potentiometer on a 16-bit card): name -> (low, high).
FRICTION: dict[str, tuple[float, float]] = {
    "F_C": (30.0, 120.0),  # Coulomb level [N]
    "F_S_ratio": (1.1, 1.8),  # F_S / F_C [-]
    "v_s": (2.0e-3, 8.0e-3),  # Stribeck velocity [m/s]
    "b_v": (2000.0, 5000.0),  # viscous coefficient [N s/m]
    "p_noise": (100.0, 5000.0),  # pressure noise std [Pa]
    "x_noise": (2.0e-6, 2.0e-5),  # position noise std [m]
}

#: Significant figures of every magnitude, inside the search's objective.
SIGNIFICANT: int = 2
#: Significant figures of the plant.yaml numbers derived from the magnitudes (a line's delay and
#: volume, F_S).
DERIVED_SIGNIFICANT: int = 3

#: Each magnitude's unit and the source of its range (docs/real-rig.md gives them in full).
SOURCES: dict[str, tuple[str, str]] = {
    "tau_open": ("s", "valve armature, 20-30 % of fast 3/2 solenoid valves' switching times "
                 "(Festo MH1, Matrix 821, SMC SX90; Topcu et al. 2006)"),
    "tau_close": ("s", "as tau_open"),
    "line_length": ("m", "4 mm bore tube (Festo PUN); delay = length / 337 m/s"),
    "line_C": ("m^3/(s Pa)", "choked tube flow with entry loss and friction (Richer and "
               "Hurmuzlu 2000)"),
    "heat_h": ("W/(m^2 K)", "cylinder chamber convection (Carneiro and de Almeida 2006)"),
    "sigma0": ("N/m", "LuGre (Canudas de Wit et al. 1995), pre-sliding deflection 5-500 um"),
    "sigma1": ("N s/m", "LuGre bristle damping near critical with the moving mass"),
    "p_lag": ("s", "pressure transmitter 10-90 % response 0.1-10 ms (WIKA, Huba 401/402)"),
    "x_lag": ("s", "position conditioning"),
    "io_delay": ("s", "software-timed output after a hardware-timed read (NI-DAQmx), up to "
                 "one sample"),
    "supply_C": ("m^3/(s Pa)", "regulator conductance (ISO 6953 method), an estimate"),
    "supply_volume": ("m^3", "manifold and buffer at the valves, an estimate"),
    "F_C": ("N", "Coulomb level, benchmarks/fleet.py's spread"),
    "F_S_ratio": ("-", "F_S / F_C, benchmarks/fleet.py's spread"),
    "v_s": ("m/s", "Stribeck velocity, benchmarks/fleet.py's spread"),
    "b_v": ("N s/m", "viscous, the paper's theta3 bounds"),
    "p_noise": ("Pa", "0.1-0.5 % of a 10 bar transmitter span (low end 100 Pa)"),
    "x_noise": ("m", "potentiometer on a 16-bit card"),
}


def significant(value: float, digits: int) -> float:
    """``value`` rounded to ``digits`` significant figures.

    Parameters
    ----------
    value : float
        Any finite number.
    digits : int
        Significant figures to keep (>= 1).

    Returns
    -------
    float
        The rounded number, exactly as a YAML file written with ``repr`` reads it back.
    """
    return float(f"{value:.{digits - 1}e}")


def ranges() -> dict[str, tuple[float, float, bool]]:
    """The searched magnitudes: name -> (low, high, log-scale).

    Returns
    -------
    dict
        Every magnitude of :data:`~pneutune.control.sim.rig_effects.MAGNITUDES` and
        :data:`FRICTION`, with its published range.
    """
    out = {k: (r.low, r.high, r.log) for k, r in rig_effects.MAGNITUDES.items()}
    out |= {k: (lo, hi, False) for k, (lo, hi) in FRICTION.items()}
    return out


def _round_tree(node: Any, digits: int) -> Any:
    """A copy of nested updates with every float rounded to ``digits`` significant figures."""
    if isinstance(node, Mapping):
        return {k: _round_tree(v, digits) for k, v in node.items()}
    if isinstance(node, float):
        return significant(node, digits)
    return node


def plant_updates(m: Mapping[str, float]) -> dict[str, Any]:
    """plant.yaml updates for the magnitudes ``m``.

    Parameters
    ----------
    m : mapping
        Every magnitude of :data:`~pneutune.control.sim.rig_effects.MAGNITUDES` and
        :data:`FRICTION` (SI units).

    Returns
    -------
    dict
        Every effect of :mod:`pneutune.control.sim.rig_effects` and the friction and noise of
        :data:`FRICTION`, each number rounded to :data:`DERIVED_SIGNIFICANT` significant
        figures (the magnitudes themselves, at :data:`SIGNIFICANT` figures, pass unchanged).
    """
    upd = rig_effects.plant_updates(m)
    upd["friction"].update({"F_C": m["F_C"], "F_S": m["F_C"] * m["F_S_ratio"], "v_s": m["v_s"],
                            "b_v": m["b_v"]})
    upd["sensors"].update({"p_noise": m["p_noise"], "x_noise": m["x_noise"]})
    return _round_tree(upd, DERIVED_SIGNIFICANT)


def build_plant(m: Mapping[str, float], pwm_update: str = "immediate",
                p_at: str = "chamber") -> PlantConfig:
    """The paper's plant (the default :class:`PlantConfig`) with the magnitudes ``m``.

    ``pwm_update`` is the plant's ``rig.pwm_update``: how the PWM board takes a new duty (the
    paper's board updates the four duties "synchronously", which does not say which).
    """
    upd = plant_updates(m)
    if pwm_update != "immediate":
        upd["rig"] = {"pwm_update": pwm_update}
    if p_at != "chamber":
        upd["sensors"]["p_at"] = p_at
    return PlantConfig().with_updates(upd)


def table1(plant: PlantConfig, seeds: list[int]) -> dict[str, np.ndarray]:
    """E_p and E_rms [mm] of the paper's gains per Table-1 scenario.

    Parameters
    ----------
    plant : PlantConfig
        The simulated rig.
    seeds : list of int
        Noise seeds.

    Returns
    -------
    dict
        Scenario name -> array (len(seeds), 2) of (E_p, E_rms) in mm.
    """
    ctl = load_controller(PAPER)
    vec = pack(ctl)
    out = {}
    for name in GROUPS["table1"]:
        rows = []
        for seed in seeds:
            m = simulate_scenario(ctl, SCENARIOS[name], plant, seed=seed, cfg_vec=vec).metrics
            rows.append((m.E_p_mm, m.E_rms_mm))
        out[name] = np.array(rows)
    return out


def differences(res: Mapping[str, np.ndarray]) -> np.ndarray:
    """Relative differences from Table 1 of the mean figures: (scenarios, 2) of E_p, E_rms."""
    rows = []
    for name, arr in res.items():
        paper = SCENARIOS[name].paper
        assert paper is not None
        rows.append(arr.mean(axis=0) / np.asarray(paper) - 1.0)
    return np.array(rows)


def worst_difference(res: Mapping[str, np.ndarray]) -> float:
    """The largest |relative difference| from Table 1 over the eight mean figures."""
    return float(np.abs(differences(res)).max())


def table_lines(res: Mapping[str, np.ndarray], tolerance: float) -> tuple[list[str], bool]:
    """The comparison with Table 1 as text lines.

    Parameters
    ----------
    res : mapping
        :func:`table1`'s result.
    tolerance : float
        Largest accepted |relative difference|.

    Returns
    -------
    lines : list of str
        A header line, one line per scenario and a verdict.
    ok : bool
        Whether every figure is within ``tolerance``.
    """
    ok = True
    lines = [f"{'scenario':18s} {'E_p paper':>9s} {'E_p here (range)':>24s} {'diff':>7s}   "
             f"{'E_rms paper':>11s} {'E_rms here (range)':>24s} {'diff':>7s}"]
    for name, arr in res.items():
        paper = SCENARIOS[name].paper
        assert paper is not None
        cells = []
        for j in range(2):
            mean = arr[:, j].mean()
            diff = mean / paper[j] - 1.0
            ok = ok and abs(diff) <= tolerance
            cells.append(f"{paper[j]:9.2f} {mean:8.3f} ({arr[:, j].min():.3f}-"
                         f"{arr[:, j].max():.3f}) {diff:+7.1%}")
        lines.append(f"{name:18s} {cells[0]}   {cells[1]}")
    lines.append(f"worst figure {worst_difference(res):.1%}; every figure within "
                 f"{tolerance:.0%} of Table 1: {'yes' if ok else 'no'}")
    return lines, ok


def report(res: Mapping[str, np.ndarray], tolerance: float) -> bool:
    """Print the comparison; whether every figure is within ``tolerance``."""
    lines, ok = table_lines(res, tolerance)
    print("\n".join(lines))
    return ok


def search(trials: int, seeds: list[int], seed: int, start: Mapping[str, float] | None = None,
           timeout: float | None = None, log: Path | None = None,
           pwm_update: str = "immediate", p_at: str = "chamber",
           ) -> tuple[list[tuple[dict[str, float], float]], int]:
    """Seeded TPE search of the magnitudes, each rounded before its plant is built.

    Parameters
    ----------
    trials : int
        Number of trials.
    seeds : list of int
        Noise seeds of the objective (the worst figure of their mean).
    seed : int
        Seed of the sampler.
    start : mapping, optional
        Magnitudes of the first trial (an earlier search's).
    timeout : float, optional
        Stop starting trials after this many seconds.
    log : Path, optional
        Append each trial's magnitudes and worst difference to this file, a JSON line each.
    pwm_update : str
        The plants' ``rig.pwm_update``.
    p_at : str
        The plants' ``sensors.p_at``: where the chamber pressure transmitters sit.

    Returns
    -------
    found : list of (dict, float)
        Every distinct evaluated set of (rounded) magnitudes, complete, with its worst
        difference, best first.
    n_trials : int
        The trials run (fewer than ``trials`` if ``timeout`` ran out).
    """
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    space = ranges()
    t0 = time.perf_counter()
    best = [np.inf, -1]

    def objective(trial: optuna.Trial) -> float:
        m = {k: significant(trial.suggest_float(k, lo, hi, log=log), SIGNIFICANT)
             for k, (lo, hi, log) in space.items()}
        # rounding may step just outside a range: back to its bound
        m = {k: min(max(v, space[k][0]), space[k][1]) for k, v in m.items()}
        trial.set_user_attr("m", m)
        worst = worst_difference(table1(build_plant(m, pwm_update, p_at), seeds))
        if worst < best[0]:
            best[:] = [worst, trial.number]
        if log is not None:
            with log.open("a") as f:
                f.write(json.dumps({"trial": trial.number, "worst": worst, "m": m}) + "\n")
        print(f"trial {trial.number:4d} ({time.perf_counter() - t0:5.0f} s): worst "
              f"{worst:6.1%}  (best {best[0]:5.1%} at trial {best[1]})", flush=True)
        return worst

    sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=20, multivariate=True)
    study = optuna.create_study(sampler=sampler)
    if start is not None:
        study.enqueue_trial({k: v for k, v in start.items() if k in space})
    study.optimize(objective, n_trials=trials, timeout=timeout)
    done = sorted((t for t in study.trials if t.value is not None), key=lambda t: t.value)
    out: list[tuple[dict[str, float], float]] = []
    seen: set[tuple[tuple[str, float], ...]] = set()
    for t in done:
        m = t.user_attrs["m"]
        key = tuple(sorted(m.items()))
        if key not in seen:
            seen.add(key)
            out.append((m, float(t.value)))
    return out, len(study.trials)


def header_text(m: Mapping[str, float], command: str, tables: Mapping[str, list[str]],
                effects: tuple[str, ...] = tuple(rig_effects.EFFECTS)) -> str:
    """The plant file's comment header.

    Parameters
    ----------
    m : mapping
        The magnitudes written.
    command : str
        The command line that made the file.
    tables : mapping
        Seed-set label -> :func:`table_lines` of the plant.
    effects : tuple of str
        The plant's real-rig effects (``PlantConfig.effects``).

    Returns
    -------
    str
        Plain text, one comment line per line.
    """
    rng = ranges()
    lines = [
        "The paper's rig (Qian et al. 2014, Sec. 5.1: geometry, valves, the default plant) with",
        *textwrap.wrap("real-rig effects: " + ", ".join(effects) + ", at magnitudes inside the "
                       "published ranges of control/sim/rig_effects.py (MAGNITUDES) and "
                       "benchmarks/paper_rig.py (FRICTION); docs/real-rig.md gives the sources. "
                       "With the paper's gains (data/controller-paper.yaml) it reproduces "
                       "Table 1 (below).", 92, break_on_hyphens=False),
        "",
        f"Made {time.strftime('%Y-%m-%d')} by:",
        f"  {command}",
        "a seeded TPE search minimising the worst |relative difference| from Table 1 over the",
        "eight figures (mean over the --seeds noise seeds), every magnitude rounded to "
        f"{SIGNIFICANT}",
        f"significant figures (the numbers derived from them to {DERIVED_SIGNIFICANT}) before "
        "its plant",
        "was built, so this file is exactly the plant evaluated; the best --check-top trials were",
        "re-run on the --check-seeds noise seeds and the one with the smallest worst figure over",
        "both seed sets kept. Reproduce the table: .venv/bin/python benchmarks/paper_rig.py",
        "",
        "Magnitudes (value, unit, published range; source):",
    ]
    for k, v in m.items():
        unit, source = SOURCES[k]
        lo, hi, _ = rng[k]
        lines.append(f"  {k:13s} {v:<8.3g} {unit:10s} {lo:.3g}-{hi:.3g}; {source}")
    for label, tab in tables.items():
        lines += ["", f"Table 1 against this plant, mean (range) over noise seeds {label}:"]
        lines += [f"  {t}" for t in tab]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the comparison (or the search); exit 0 when every figure is within tolerance."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", type=Path, default=PLANT, help="plant.yaml to compare")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="noise seeds")
    ap.add_argument("--tolerance", type=float, default=0.25, help="relative (default 0.25)")
    ap.add_argument("--search", type=int, default=0, metavar="N",
                    help="choose the magnitudes by N search trials instead")
    ap.add_argument("--search-seed", type=int, default=1, help="seed of the search")
    ap.add_argument("--search-timeout", type=float, metavar="S",
                    help="stop the search after S seconds (the trials run are reported)")
    ap.add_argument("--check-seeds", type=int, nargs="+", default=[4, 5, 6],
                    help="noise seeds the best trials are checked on (default 4 5 6)")
    ap.add_argument("--check-top", type=int, default=20, metavar="K",
                    help="how many of the best trials to check (default 20)")
    ap.add_argument("--out", type=Path, help="where --search writes the best plant (and its "
                    "magnitudes beside it, as OUT.params.json)")
    ap.add_argument("--trials-log", type=Path, metavar="LOG.jsonl",
                    help="append every search trial's magnitudes and worst difference here")
    ap.add_argument("--start", type=Path, metavar="PARAMS.json",
                    help="--search starts from these magnitudes (an earlier search's)")
    ap.add_argument("--pwm-update", choices=("immediate", "latched"), default="immediate",
                    help="the searched plants' rig.pwm_update (default immediate)")
    ap.add_argument("--p-at", choices=("chamber", "valves"), default="chamber",
                    help="the searched plants' sensors.p_at: the chamber transmitters at the "
                    "cylinder or at the valves' side of the lines (default chamber)")
    args = ap.parse_args(argv)
    if args.search:
        if args.out is None:
            ap.error("--search needs --out")
        t0 = time.perf_counter()
        start = json.loads(args.start.read_text()) if args.start else None
        found, n_run = search(args.search, args.seeds, args.search_seed, start,
                              args.search_timeout, args.trials_log, args.pwm_update,
                              args.p_at)
        print(f"search: {n_run} trials, {len(found)} distinct plants in "
              f"{time.perf_counter() - t0:.0f} s; checking the best "
              f"{min(args.check_top, len(found))} on seeds "
              f"{' '.join(map(str, args.check_seeds))}", flush=True)
        checked = []
        for i, (m, worst) in enumerate(found[:args.check_top]):
            check = worst_difference(table1(build_plant(m, args.pwm_update, args.p_at),
                                            args.check_seeds))
            checked.append((max(worst, check), i, m))
            print(f"  #{i:2d}: seeds {' '.join(map(str, args.seeds))} {worst:6.1%}, seeds "
                  f"{' '.join(map(str, args.check_seeds))} {check:6.1%}", flush=True)
        score, i, best = min(checked, key=lambda c: (c[0], c[1]))
        print(f"kept #{i}: worst {score:.1%} over both seed sets "
              f"({time.perf_counter() - t0:.0f} s in all)")
        for k, v in best.items():
            print(f"  {k} = {v:.3g}")
        plant = build_plant(best, args.pwm_update, args.p_at)
        tables = {}
        for seeds in (args.seeds, args.check_seeds):
            tables[" ".join(map(str, seeds))] = table_lines(table1(plant, seeds),
                                                            args.tolerance)[0]
        # the command that reproduces it: the trials run (a timeout's), without the timeout
        cmd_args = ["--search", str(n_run), "--search-seed", str(args.search_seed),
                    "--seeds", *map(str, args.seeds), "--check-seeds",
                    *map(str, args.check_seeds), "--check-top", str(args.check_top)]
        cmd_args += ["--start", str(args.start)] if args.start else []
        if args.pwm_update != "immediate":
            cmd_args += ["--pwm-update", args.pwm_update]
        if args.p_at != "chamber":
            cmd_args += ["--p-at", args.p_at]
        cmd_args += ["--out", str(args.out)]
        command = "nice -n 10 .venv/bin/python benchmarks/paper_rig.py " + shlex.join(cmd_args)
        header = header_text(best, command, tables, plant.effects)
        write_yaml(args.out, plant.to_dict(), header=header)
        params = args.out.with_suffix(".params.json")
        params.write_text(json.dumps(best, indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.out} and {params}")
        args.plant = args.out
    plant = load_plant(args.plant)
    print(f"{args.plant.name}: effects {', '.join(plant.effects) or 'none'}; paper's gains; "
          f"noise seeds {' '.join(map(str, args.seeds))}")
    t0 = time.perf_counter()
    ok = report(table1(plant, args.seeds), args.tolerance)
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
