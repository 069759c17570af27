"""What the control law computes today, frozen as fixed input sequences and their outputs.

``tests/data/law_reference.npz`` holds, for every case of :func:`reference_cases`, the
measurement vectors fed to :func:`pneutune.control.law.darc.step_into` at every sample of a
short closed-loop run, the packed config, the controller state before the first step, and what
the step returned: the duties and the Eq. (33) case at every sample and the whole state vector
after every :data:`STATE_EVERY`-th step and after the last. Replayed open loop through a later
implementation of the step (:func:`replay`), the same measurements must give the same outputs
(tests/test_law_reference.py).

The cases cover every variant of the law (``original_darc`` also with its model acceleration),
every scenario of ``GROUPS["all"]`` for ``modified_darc`` and several for each other variant,
both PWM update modes of the plant, both dead-zone modes, both position feedbacks, two plants
and two sensor-noise seeds. Each runs :data:`DURATION` seconds of its scenario; the force steps
of a scenario (``disturbance-0.5hz``) are moved into that window in proportion, so that they
still act on the measurements.

The measurement vectors are rebuilt from what the closed loop records (sample time, sensors,
reference), and :func:`record_case` checks that replaying them through the step gives exactly
the duties and logged controller state of the closed loop before storing anything.

Closed-loop runs only reach Eq. (33) cases 2 and 4. Two ``edge`` cases therefore take a
closed-loop sequence and edit it (:func:`edge_edits`): stretches of chamber pressures at which
the active mode's valves pass no flow (cases 1 and 5 for ``pid``, whose Q_Ld does not depend on
the pressures) and a few samples with a non-finite reference speed (a non-finite Q_Ld: case 3,
every valve closed). Their outputs are recorded by replaying the edited sequence open loop.

Regenerate only for a deliberate change of what the law computes, and say so in the commit::

    .venv/bin/python tests/law_reference.py --write    # writes the file (byte-reproducible)
    .venv/bin/python tests/law_reference.py --check    # replays it, prints the differences
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import io
import json
import sys
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.darc import (
    M_P_A,
    M_P_B,
    M_P_S,
    M_V_R,
    MEAS_FIELDS,
    MEAS_SIZE,
    S_WORK,
    STATE_SIZE,
    init_state,
    step_into,
)
from pneutune.control.law.layout import CFG_LAYOUT_ID, CFG_P0, CFG_SIZE, pack
from pneutune.control.sim.closed_loop import LOG_INDEX, STATUS_OK, prepare_run, run_prepared
from pneutune.control.sim.plant_variants import PLANT_VARIANTS
from pneutune.control.sim.scenarios import GROUPS, SCENARIOS, Scenario

ROOT = Path(__file__).resolve().parents[1]
#: The reference file.
REFERENCE = Path(__file__).resolve().parent / "data" / "law_reference.npz"
#: The paper's controller (Sec. 5.1), the base of every case.
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
#: Length of every run [s].
DURATION = 2.0
#: The state vector is stored after steps k with k % STATE_EVERY == 0, and after the last.
STATE_EVERY = 25
#: Version of the file's layout (keys and index), bumped when it changes.
FORMAT = 1
#: The law's variants: the controller variants, with ``original_darc/model`` for
#: ``original_darc`` with ``original_darc_accel: model``.
LAW_VARIANTS: tuple[str, ...] = ("modified_darc", "direct_diff", "original_darc",
                                 "original_darc/model", "pid")
#: Plants by name: plant.yaml updates of the default plant (the paper's rig).
PLANTS: dict[str, dict[str, Any]] = {
    "paper": {},
    "stiff-friction-heavy": PLANT_VARIANTS["stiff-friction-heavy"],
}
#: A fixed zip timestamp, so that the same arrays always give the same bytes.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class Case:
    """One recorded run: a controller variant and options on a scenario, plant and seed.

    Attributes
    ----------
    variant : str
        One of :data:`LAW_VARIANTS`.
    scenario : str
        A scenario of ``GROUPS["all"]``, run for :data:`DURATION` seconds.
    plant : str
        A key of :data:`PLANTS`.
    pwm_update : str
        The plant's ``rig.pwm_update`` (immediate | latched); the controller's is set alike.
    dead_zone : str
        The controller's ``dead_zone`` (up | dither).
    position_feedback : str
        The controller's ``position_feedback`` (measured | filtered).
    seed : int
        Sensor-noise seed.
    edits : str
        ``none`` (the closed loop's measurements) or ``edge`` (:func:`edge_edits` applied).
    """

    variant: str
    scenario: str
    plant: str
    pwm_update: str
    dead_zone: str
    position_feedback: str
    seed: int
    edits: str = "none"

    def describe(self) -> dict[str, Any]:
        """The case as plain data (its entry in the file's JSON index)."""
        return dataclasses.asdict(self)

    def controller(self, base: ControllerConfig | None = None) -> ControllerConfig:
        """The controller of the case: the paper's with the variant and options set.

        Parameters
        ----------
        base : ControllerConfig, optional
            The paper's controller, if already loaded.

        Returns
        -------
        ControllerConfig
            Validated.
        """
        ctl = base if base is not None else load_controller(PAPER_YAML)
        variant, _, accel = self.variant.partition("/")
        doc = ctl.to_dict()
        doc.update(variant=variant, original_darc_accel=accel or "filtered",
                   dead_zone=self.dead_zone, position_feedback=self.position_feedback)
        doc["rig"]["pwm_update"] = self.pwm_update
        return ControllerConfig.model_validate(doc)

    def plant_config(self) -> PlantConfig:
        """The plant of the case: :data:`PLANTS` entry, then the PWM update mode."""
        updates = copy.deepcopy(PLANTS[self.plant])
        updates.setdefault("rig", {})["pwm_update"] = self.pwm_update
        return PlantConfig().with_updates(updates, source=f"law reference plant {self.plant}")

    def scenario_run(self) -> Scenario:
        """The scenario cut to :data:`DURATION`, its force steps moved into the window."""
        sc = SCENARIOS[self.scenario]
        updates = copy.deepcopy(sc.plant_updates)
        steps = updates.get("disturbance", {}).get("force_steps")
        if steps:
            scale = DURATION / sc.duration
            updates["disturbance"]["force_steps"] = [[t * scale, f] for t, f in steps]
        return dataclasses.replace(sc, duration=DURATION, plant_updates=updates)


def reference_cases() -> list[Case]:
    """The recorded cases, in the order of the file.

    Four option sets (plant, PWM update, dead zone, position feedback, seed): ``base`` (paper
    rig, immediate, up, measured, seed 1), ``alt`` (stiff plant, latched, dither, filtered,
    seed 2), and two mixes. ``modified_darc`` runs ``base`` and ``alt`` on every scenario and
    the mixes on one each; every other variant runs each option set once, on scenarios taken in
    turn, so that each sees four scenarios.

    Returns
    -------
    list of Case
    """
    options = {
        "base": ("paper", "immediate", "up", "measured", 1),
        "alt": ("stiff-friction-heavy", "latched", "dither", "filtered", 2),
        "mix1": ("paper", "latched", "up", "filtered", 2),
        "mix2": ("stiff-friction-heavy", "immediate", "dither", "measured", 1),
    }
    scenarios = GROUPS["all"]
    cases = [Case("modified_darc", sc, *options[o]) for o in ("base", "alt") for sc in scenarios]
    cases += [Case("modified_darc", "square-0.5hz", *options["mix1"]),
              Case("modified_darc", "sine-0.5hz-heavy", *options["mix2"])]
    for i, variant in enumerate(LAW_VARIANTS[1:]):
        for j, o in enumerate(("base", "alt", "mix1", "mix2")):
            cases.append(Case(variant, scenarios[(i + j) % len(scenarios)], *options[o]))
    cases += [Case("pid", "sine-0.5hz", *options["base"], edits="edge"),
              Case("direct_diff", "sine-0.75hz", *options["mix1"], edits="edge")]
    return cases


def edge_edits(meas: np.ndarray, cases: np.ndarray, p0: float) -> np.ndarray:
    """A closed-loop measurement sequence edited to reach the rare Eq. (33) cases.

    Up to 12 samples in 100..199 where the step returned case 2 get ``p_a = p_s, p_b = p0``
    (a_in and b_out pass no flow); up to 12 in 250..349 where it returned case 4 get
    ``p_a = p0, p_b = p_s`` (a_out and b_in pass none); samples 200, 201 and 400 get a NaN
    reference speed.

    Parameters
    ----------
    meas : (n, MEAS_SIZE) float64
        The closed loop's measurements (n > 400).
    cases : (n,) int
        The cases the step returned for them.
    p0 : float
        Ambient pressure of the controller [Pa abs].

    Returns
    -------
    (n, MEAS_SIZE) float64
        An edited copy.
    """
    out = np.array(meas, dtype=np.float64)
    k = np.arange(out.shape[0])
    a_fill = np.flatnonzero((cases == 2) & (k >= 100) & (k < 200))[:12]
    b_fill = np.flatnonzero((cases == 4) & (k >= 250) & (k < 350))[:12]
    out[a_fill, M_P_A] = out[a_fill, M_P_S]
    out[a_fill, M_P_B] = p0
    out[b_fill, M_P_A] = p0
    out[b_fill, M_P_B] = out[b_fill, M_P_S]
    out[[200, 201, 400], M_V_R] = np.nan
    return out


def state_rows(n: int) -> np.ndarray:
    """The samples after whose step the state is stored: every :data:`STATE_EVERY`-th, and the
    last.

    Parameters
    ----------
    n : int
        Samples in the run.

    Returns
    -------
    (m,) int64
        Increasing sample indices.
    """
    return np.unique(np.append(np.arange(0, n, STATE_EVERY), n - 1)).astype(np.int64)


def replay(meas: np.ndarray, cfg: np.ndarray, state0: np.ndarray,
           rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feed a measurement sequence through the current step, open loop.

    Parameters
    ----------
    meas : (n, MEAS_SIZE) float64
        One measurement vector per sample.
    cfg : (CFG_SIZE,) float64
        Packed config.
    state0 : (STATE_SIZE,) float64
        State before the first step (not changed).
    rows : (m,) int
        Samples after whose step the state is returned.

    Returns
    -------
    duties : (n, 4) float64
        Duties of every step.
    cases : (n,) int64
        Eq. (33) case returned by every step.
    states : (m, STATE_SIZE) float64
        The state after the steps of ``rows``.
    """
    n = meas.shape[0]
    state = np.array(state0, dtype=np.float64)
    cfg = np.ascontiguousarray(cfg, dtype=np.float64)
    duties = np.zeros((n, 4))
    cases = np.zeros(n, dtype=np.int64)
    states = np.zeros((len(rows), state.shape[0]))
    want = {int(k): i for i, k in enumerate(rows)}
    d = np.zeros(4)
    for k in range(n):
        cases[k] = step_into(state, np.ascontiguousarray(meas[k]), cfg, d)
        duties[k] = d
        if k in want:
            states[want[k]] = state
    return duties, cases, states


def record_case(case: Case, base: ControllerConfig | None = None) -> dict[str, np.ndarray]:
    """Run one case in closed loop and record its step inputs and outputs.

    Parameters
    ----------
    case : Case
        The case.
    base : ControllerConfig, optional
        The paper's controller, if already loaded.

    Returns
    -------
    dict of ndarray
        ``meas`` (n, MEAS_SIZE), ``cfg`` (CFG_SIZE,), ``state0`` (STATE_SIZE,), ``duties``
        (n, 4), ``case`` (n,) int64, ``state_rows`` (m,) int64, ``states`` (m, STATE_SIZE).
        For an ``edge`` case, the edited measurements and the open-loop replay's outputs.

    Raises
    ------
    RuntimeError
        The run stopped early, or replaying the rebuilt measurements does not give exactly the
        closed loop's duties and logged controller state.
    """
    ctl = case.controller(base)
    run = prepare_run(case.scenario_run(), case.plant_config(), case.seed)
    res = run_prepared(run, ctl)
    n = res.sensors.shape[0]
    if res.metrics.status != STATUS_OK or n != run.n:
        raise RuntimeError(f"{case}: the closed loop stopped after {n} of {run.n} samples "
                           f"({res.metrics.status})")
    t = np.arange(n) * run.Ts  # run_kernel's t = k * Ts
    meas = np.column_stack([t, res.sensors, res.reference[:n]])
    cfg = pack(ctl)
    state0 = init_state(cfg, float(run.reference[0, 0]), run.p_a0, run.p_b0)
    duties, cases, every = replay(meas, cfg, state0, np.arange(n))
    if not (np.array_equal(duties, res.duties)
            and np.array_equal(every[:, LOG_INDEX], res.control_state)):
        raise RuntimeError(f"{case}: replaying the rebuilt measurements does not reproduce the "
                           f"closed loop's duties and controller state")
    if case.edits == "edge":
        meas = edge_edits(meas, cases, float(cfg[CFG_P0]))
        duties, cases, every = replay(meas, cfg, state0, np.arange(n))
    rows = state_rows(n)
    return {"meas": meas, "cfg": cfg, "state0": state0, "duties": duties, "case": cases,
            "state_rows": rows, "states": every[rows]}


def case_id(i: int) -> str:
    """Key prefix of case ``i`` in the file (``case07``)."""
    return f"case{i:02d}"


def build_reference() -> dict[str, np.ndarray]:
    """Every case of :func:`reference_cases`, recorded, as the arrays of the file.

    Returns
    -------
    dict of ndarray
        ``<id>/<array>`` per case (:func:`record_case`, ``<id>`` from :func:`case_id`) and
        ``index``: a JSON string describing the file and each case.
    """
    base = load_controller(PAPER_YAML)
    out: dict[str, np.ndarray] = {}
    entries = []
    for i, case in enumerate(reference_cases()):
        rec = record_case(case, base)
        for name, arr in rec.items():
            out[f"{case_id(i)}/{name}"] = arr
        entries.append({"id": case_id(i), **case.describe(), "samples": int(rec["meas"].shape[0]),
                        "cases_seen": sorted({int(c) for c in rec["case"]})})
    index = {
        "format": FORMAT, "duration_s": DURATION, "state_every": STATE_EVERY,
        "meas_fields": list(MEAS_FIELDS), "meas_size": MEAS_SIZE, "state_size": STATE_SIZE,
        "state_compared": S_WORK, "cfg_size": CFG_SIZE, "cfg_layout_id": CFG_LAYOUT_ID,
        "cases": entries,
    }
    out["index"] = np.array(json.dumps(index, indent=1, sort_keys=True))
    return out


def write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """:func:`numpy.savez_compressed` with fixed zip timestamps (same arrays, same bytes).

    Parameters
    ----------
    path : Path
        Destination (overwritten).
    arrays : mapping of str to ndarray
        Stored as ``<key>.npy``, in the mapping's order; read back by :func:`numpy.load`.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, mode="w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, arr in arrays.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arr), allow_pickle=False)
    path.write_bytes(buf.getvalue())


def load_reference(path: Path = REFERENCE) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The file's index and arrays.

    Parameters
    ----------
    path : Path
        The file (default :data:`REFERENCE`).

    Returns
    -------
    index : dict
        The JSON index (:func:`build_reference`).
    arrays : dict of ndarray
        Every other array, by key.
    """
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    index = json.loads(str(arrays.pop("index")))
    return index, arrays


def slot_scale(expected: np.ndarray) -> np.ndarray:
    """Per column (per state slot or valve), the largest magnitude of the expected values.

    Parameters
    ----------
    expected : (m, k) float64

    Returns
    -------
    (k,) float64
        Non-finite values are ignored; 0 for a column that is all zero.
    """
    finite = np.where(np.isfinite(expected), np.abs(expected), 0.0)
    return finite.max(axis=0) if expected.shape[0] else np.zeros(expected.shape[1])


def scaled_diff(actual: np.ndarray, expected: np.ndarray, scale: np.ndarray) -> float:
    """Largest ``|actual - expected| / max(|expected|, scale)`` (relative, with a floor).

    Parameters
    ----------
    actual, expected : (m, k) float64
    scale : (k,) float64
        Absolute floor of the denominator per column.

    Returns
    -------
    float
        0 where the two are identical (also for equal infinities and both NaN); inf where they
        differ and the denominator is 0, or only one is finite.
    """
    same = (actual == expected) | (np.isnan(actual) & np.isnan(expected))
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(actual - expected) / np.maximum(np.abs(expected), scale)
    rel = np.where(same, 0.0, np.where(np.isnan(rel), np.inf, rel))
    return float(rel.max()) if rel.size else 0.0


def compare_case(arrays: Mapping[str, np.ndarray], cid: str) -> dict[str, float]:
    """Replay one stored case through the current step and measure the differences.

    Parameters
    ----------
    arrays : mapping of str to ndarray
        The file's arrays (:func:`load_reference`).
    cid : str
        The case's key prefix.

    Returns
    -------
    dict
        ``duties`` and ``states``: :func:`scaled_diff` of the replay against the stored values
        (duties with a floor of 1, their full scale; states per slot with the floor
        :func:`slot_scale` of the stored states, over the slots before the Kalman scratch
        ``S_WORK``); ``case_mismatches``: samples whose returned case differs; ``scratch``:
        :func:`scaled_diff` over the scratch slots (informative only).
    """
    meas, cfg = arrays[f"{cid}/meas"], arrays[f"{cid}/cfg"]
    rows = arrays[f"{cid}/state_rows"]
    duties, cases, states = replay(meas, cfg, arrays[f"{cid}/state0"], rows)
    want_states = arrays[f"{cid}/states"]
    if states.shape != want_states.shape:
        return {"duties": np.inf, "states": np.inf, "case_mismatches": float(len(cases)),
                "scratch": np.inf}
    keep, scratch = slice(0, S_WORK), slice(S_WORK, None)
    return {
        "duties": scaled_diff(duties, arrays[f"{cid}/duties"], np.ones(4)),
        "states": scaled_diff(states[:, keep], want_states[:, keep],
                              slot_scale(want_states[:, keep])),
        "case_mismatches": float(np.count_nonzero(cases != arrays[f"{cid}/case"])),
        "scratch": scaled_diff(states[:, scratch], want_states[:, scratch],
                               slot_scale(want_states[:, scratch])),
    }


def _check(path: Path) -> int:
    """Replay the file and print the differences per case; 1 if any is above 1e-9."""
    index, arrays = load_reference(path)
    worst = {"duties": 0.0, "states": 0.0, "case_mismatches": 0.0, "scratch": 0.0}
    for entry in index["cases"]:
        diff = compare_case(arrays, entry["id"])
        label = (f"{entry['id']} {entry['variant']:<19} {entry['scenario']:<17} "
                 f"{entry['plant']:<20} {entry['pwm_update']:<9} {entry['dead_zone']:<6} "
                 f"{entry['position_feedback']:<8} seed {entry['seed']} {entry['edits']:<4}")
        print(f"{label}  duties {diff['duties']:.3g}  states {diff['states']:.3g}  "
              f"case mismatches {int(diff['case_mismatches'])}  scratch {diff['scratch']:.3g}")
        worst = {k: max(worst[k], diff[k]) for k in worst}
    print(f"max over {len(index['cases'])} cases: duties {worst['duties']:.3g}, "
          f"states {worst['states']:.3g}, case mismatches {int(worst['case_mismatches'])}, "
          f"scratch {worst['scratch']:.3g}")
    ok = worst["duties"] <= 1e-9 and worst["states"] <= 1e-9 and worst["case_mismatches"] == 0
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    """Command line: ``--write`` records the file, ``--check`` replays it.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help=f"record and write {REFERENCE.name}")
    mode.add_argument("--check", action="store_true", help="replay the file, print differences")
    parser.add_argument("--path", type=Path, default=REFERENCE, help="the file")
    args = parser.parse_args(argv)
    if args.write:
        arrays = build_reference()
        write_npz(args.path, arrays)
        n_cases = len(json.loads(str(arrays["index"]))["cases"])
        print(f"{args.path}: {n_cases} cases, {args.path.stat().st_size} bytes")
        return 0
    return _check(args.path)


if __name__ == "__main__":
    sys.exit(main())
