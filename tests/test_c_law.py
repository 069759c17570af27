"""The C99 control law (control/law/c: ptlaw.c, ptlaw.h, the generated pt_layout.h) compiled the
way a target compiles it, against the library the install built (which the simulator, tune and
deploy call through the numba wrappers of control/law/darc.py), back to back on the same
measurement sequences.

The law exists once, in C; tests/test_law_reference.py holds it to what it computed before it
moved to C. Here a second build of the same sources, with exactly the strict flags the sources
promise to compile cleanly under (``-std=c99 -Wall -Wextra -Wpedantic -Werror -O2``), loaded
with ctypes, is fed the very arrays the installed law is fed: the packed config
(:func:`pneutune.control.law.layout.pack`), the flat state and measurement vectors. A stale
installed library (sources edited, not rebuilt) or build flags that change the arithmetic show
here.

Tolerances. Both builds perform the same operations in the same order, so they are expected to
agree bit for bit, and do on x86-64 Linux (both call the process's libm for atan and pow). The
comparisons still allow 1e-9 relative, plus an absolute floor of 1e-9 of the largest
magnitude the same state slot (or duty) takes over the sequence, for values near zero (e1, e2,
e3, the θ̂ rates, off-diagonal covariances: a difference there carries the rounding of the
operands' scale, not of the value itself). That is what a build on another libm, or with
other roundings, needs: roundings that differ (one product of the Joseph update reassociated,
or a build that fuses every multiply-add) grow through the filters and the loop to at most 1 %
of this bound over these sequences, 5e-8 relative at worst on a value near zero.
Integer-valued outputs (the Eq. (33) case, the step count, the dither's period index) must be
equal, which the same bound enforces since they differ by at least 1 when they differ. NaN
must sit where the installed law has NaN.
"""

from __future__ import annotations

import ctypes
import dataclasses
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law import c_header
from pneutune.control.law.darc import (
    M_A_R,
    M_P_A,
    M_P_B,
    M_P_S,
    M_T,
    M_V_R,
    M_X,
    M_X_R,
    MEAS_SIZE,
    S_STATUS,
    STATE_SIZE,
    init_state,
    step_into,
)
from pneutune.control.law.layout import CFG_LAYOUT, pack
from pneutune.control.sim.closed_loop import prepare_run, run_prepared
from pneutune.control.sim.scenarios import SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
C_DIR = ROOT / "control" / "law" / "c"
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
GCC = shutil.which("gcc")
#: The exact flags the C must build under without a warning.
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2", "-fPIC", "-shared")
#: Relative tolerance of every comparison (module docstring: 100 times what other
#: roundings give).
RTOL = 1e-9
#: Absolute floor, as a fraction of the largest magnitude of the slot over the sequence.
FLOOR = 1e-9

pytestmark = pytest.mark.skipif(GCC is None, reason="gcc is not on PATH: the C control law "
                                "(control/law/c) cannot be compiled, so there is nothing to test")

#: The law's variants; ``original_darc/model`` is original_darc with original_darc_accel: model.
LAW_VARIANTS = ("modified_darc", "direct_diff", "original_darc", "original_darc/model", "pid")
#: Duration of each closed-loop run whose measurements are replayed [s].
DURATION = 2.5
#: Two scenarios: the 0.75 Hz sine with a 40 N force step inside the window, and the smooth
#: square (a move, a hold, a move back), both shortened to DURATION.
SEQ_SCENARIOS = (
    dataclasses.replace(SCENARIOS["sine-0.75hz"], duration=DURATION,
                        plant_updates={"disturbance": {"force_steps": [[1.3, 40.0]]}}),
    dataclasses.replace(SCENARIOS["square-0.5hz"], duration=DURATION),
)
PWM_UPDATES = ("immediate", "latched")


def _compile(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """gcc with :data:`CFLAGS` (and ``extra``) on every .c file of the port, into ``out``."""
    sources = sorted(str(p) for p in C_DIR.glob("*.c"))
    return subprocess.run([GCC, *CFLAGS, *extra, "-o", str(out), *sources],
                          capture_output=True, text=True, check=False)


class CLaw:
    """ctypes view of ``pt_step_into`` and ``pt_init_state`` (double build).

    Parameters
    ----------
    lib : ctypes.CDLL
        The loaded shared library.
    """

    def __init__(self, lib: ctypes.CDLL) -> None:
        self.lib = lib
        lib.pt_step_into.restype = ctypes.c_int
        lib.pt_step_into.argtypes = [ctypes.c_void_p] * 4
        lib.pt_init_state.restype = ctypes.c_int
        lib.pt_init_state.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_double,
                                      ctypes.c_double, ctypes.c_double]

    def init_state(self, vec: np.ndarray, x0: float, p_a0: float,
                   p_b0: float) -> tuple[int, np.ndarray]:
        """``pt_init_state`` into a fresh (STATE_SIZE,) vector: (return code, state)."""
        state = np.full(STATE_SIZE, -7.0)  # anything: the C must write every slot
        rc = self.lib.pt_init_state(state.ctypes.data, vec.ctypes.data, x0, p_a0, p_b0)
        return rc, state


@pytest.fixture(scope="session")
def c_law(tmp_path_factory: pytest.TempPathFactory) -> CLaw:
    """The C law compiled with exactly :data:`CFLAGS` into a tmp folder, loaded."""
    out = tmp_path_factory.mktemp("ptlaw") / "libptlaw.so"
    proc = _compile(out)
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr
    return CLaw(ctypes.CDLL(str(out)))


def _controller(variant: str, dead_zone: str, position_feedback: str,
                pwm_update: str = "immediate") -> ControllerConfig:
    """The paper's controller with a law variant (``original_darc/model`` as in
    :data:`LAW_VARIANTS`), dead-zone mode, position feedback and the rig's PWM update mode."""
    name, _, accel = variant.partition("/")
    base = load_controller(PAPER_YAML)
    return base.model_copy(update={
        "variant": name, "original_darc_accel": accel or "filtered", "dead_zone": dead_zone,
        "position_feedback": position_feedback,
        "rig": base.rig.model_copy(update={"pwm_update": pwm_update})})


@dataclasses.dataclass
class Run:
    """What a law did over a sequence: per step the case, the duties and the state after it."""

    cases: np.ndarray
    duties: np.ndarray
    states: np.ndarray


def _replay_installed(vec: np.ndarray, meas: np.ndarray, state0: np.ndarray) -> Run:
    n = meas.shape[0]
    run = Run(np.zeros(n, dtype=np.int64), np.zeros((n, 4)), np.zeros((n, STATE_SIZE)))
    state = state0.copy()
    duties = np.zeros(4)
    for k in range(n):
        run.cases[k] = step_into(state, meas[k], vec, duties)
        run.duties[k] = duties
        run.states[k] = state
    return run


def _replay_c(c_law: CLaw, vec: np.ndarray, meas: np.ndarray, state0: np.ndarray) -> Run:
    n = meas.shape[0]
    run = Run(np.zeros(n, dtype=np.int64), np.zeros((n, 4)), np.zeros((n, STATE_SIZE)))
    state = state0.copy()
    duties = np.zeros(4)
    step = c_law.lib.pt_step_into
    p_state, p_vec, p_duties = state.ctypes.data, vec.ctypes.data, duties.ctypes.data
    base, row = meas.ctypes.data, meas.strides[0]
    for k in range(n):
        run.cases[k] = step(p_state, base + k * row, p_vec, p_duties)
        run.duties[k] = duties
        run.states[k] = state
    return run


def _mismatch(ref: np.ndarray, got: np.ndarray) -> np.ndarray:
    """Per element, True where ``got`` is not within tolerance of ``ref`` (module docstring)."""
    scale = np.where(np.isfinite(ref), np.abs(ref), 0.0).max(axis=0)
    with np.errstate(invalid="ignore"):
        close = np.abs(got - ref) <= RTOL * np.abs(ref) + FLOOR * scale
    return ~(close | (ref == got) | (np.isnan(ref) & np.isnan(got)))


def _assert_agree(label: str, ref: Run, got: Run) -> float:
    """Case, duties and full state of ``got`` (the strict build) equal ``ref`` (the installed
    law) at every step, within RTOL and the floor; returns the largest relative difference
    seen (0 when bit for bit)."""
    differ = np.flatnonzero(ref.cases != got.cases)
    assert differ.size == 0, (f"{label}: Eq. (33) case differs first at step {differ[0]}: "
                              f"installed {ref.cases[differ[0]]}, "
                              f"strict build {got.cases[differ[0]]}")
    worst = 0.0
    for what, a, b in (("duties", ref.duties, got.duties), ("state", ref.states, got.states)):
        bad = np.argwhere(_mismatch(a, b))
        if bad.size:
            k, j = bad[0]
            raise AssertionError(f"{label}: {what}[{j}] differs first at step {k}: "
                                 f"installed {a[k, j]!r}, strict build {b[k, j]!r}")
        finite = np.isfinite(a) & np.isfinite(b) & (a != b)
        if finite.any():
            worst = max(worst, float(np.max(np.abs(a - b)[finite] / np.abs(a)[finite])))
    return worst


def _start(c_law: CLaw, vec: np.ndarray, x0: float, p_a0: float, p_b0: float) -> np.ndarray:
    """The initial state of both laws: init_state, checked equal to pt_init_state bit for bit
    (the same operations on the same values; numpy's float64 ``Ts**2`` and ``Ts**4`` are libm's
    pow, which the C calls too)."""
    state0 = init_state(vec, x0, p_a0, p_b0)
    rc, c_state0 = c_law.init_state(vec, x0, p_a0, p_b0)
    assert rc == 0
    np.testing.assert_array_equal(c_state0, state0)
    return state0


def _closed_loop_meas(controller: ControllerConfig, pwm_update: str, seed: int
                      ) -> Iterator[tuple[str, np.ndarray, tuple[float, float, float], np.ndarray]]:
    """Per scenario of :data:`SEQ_SCENARIOS`, a closed-loop run of ``controller`` on the default
    plant with ``rig.pwm_update`` (:func:`~pneutune.control.sim.closed_loop.simulate_scenario`
    in its two parts): the scenario's name, the measurement vectors the step was fed, the
    controller's ``(x0, p_a0, p_b0)`` and the duties the loop commanded."""
    plant = PlantConfig().with_updates({"rig": {"pwm_update": pwm_update}})
    for scenario in SEQ_SCENARIOS:
        run = prepare_run(scenario, plant, seed)
        res = run_prepared(run, controller)
        n = res.sensors.shape[0]
        meas = np.empty((n, MEAS_SIZE))
        meas[:, M_T] = np.arange(n) * run.Ts  # the loop's t = k Ts
        meas[:, [M_X, M_P_A, M_P_B, M_P_S]] = res.sensors
        meas[:, [M_X_R, M_V_R, M_A_R]] = run.reference[:n]
        yield scenario.name, meas, (float(run.reference[0, 0]), run.p_a0, run.p_b0), res.duties


LAW_CASES = [(v, dz, pf) for v in LAW_VARIANTS for dz in ("up", "dither")
             for pf in ("measured", "filtered")]


def test_layout_header_is_current(tmp_path: Path) -> None:
    """pt_layout.h is what the Python constants generate (``--check`` exits 0), and ``--check``
    exits 1 on a stale or missing copy (in process and through ``python -m``)."""
    assert c_header.main(["--check"]) == 0
    stale = tmp_path / "pt_layout.h"
    stale.write_text(c_header.layout_header().replace("#define PT_CFG_TS 4", "#define PT_CFG_TS 5"),
                     encoding="ascii")
    assert c_header.main(["--check", "--output", str(stale)]) == 1
    assert c_header.main(["--check", "--output", str(tmp_path / "missing.h")]) == 1
    assert c_header.main(["--output", str(stale)]) == 0
    assert c_header.main(["--check", "--output", str(stale)]) == 0
    stale.write_text("/* stale */\n", encoding="ascii")
    cli = subprocess.run([sys.executable, "-m", "pneutune.control.law.c_header", "--check",
                          "--output", str(stale)], capture_output=True, text=True, check=False)
    assert cli.returncode == 1 and "out of date" in cli.stderr


@pytest.mark.parametrize(("variant", "dead_zone", "position_feedback"), LAW_CASES)
def test_closed_loop_sequences_agree(c_law: CLaw, variant: str, dead_zone: str,
                                     position_feedback: str) -> None:
    """Each law configuration's own closed-loop measurements (two scenarios, both PWM update
    modes of the plant, 2.5 s each) replayed through both laws from equal initial states: case,
    duties and the full state vector agree at every step (tolerances: module docstring). The
    replay through the installed law reproduces the closed loop's duties exactly, so the
    sequences are what the loop saw."""
    seed = 1 + LAW_CASES.index((variant, dead_zone, position_feedback))
    cases_seen: set[int] = set()
    for pwm_update in PWM_UPDATES:
        controller = _controller(variant, dead_zone, position_feedback, pwm_update)
        vec = pack(controller)
        for name, meas, start, loop_duties in _closed_loop_meas(controller, pwm_update, seed):
            label = f"{variant}/{dead_zone}/{position_feedback} on {name}, {pwm_update}"
            state0 = _start(c_law, vec, *start)
            ref = _replay_installed(vec, meas, state0)
            np.testing.assert_array_equal(ref.duties, loop_duties, err_msg=label)
            _assert_agree(label, ref, _replay_c(c_law, vec, meas, state0))
            cases_seen.update(np.unique(ref.cases).tolist())
    assert cases_seen & {2, 4}, "the runs should reach the PWM cases of Eq. (33)"


NAN, INF = float("nan"), float("inf")
#: Pathological samples, each held for 3 steps inside a realistic sequence: (what, {index: value}).
FAULTS: tuple[tuple[str, dict[int, float]], ...] = (
    ("x NaN", {M_X: NAN}), ("x +inf", {M_X: INF}), ("x -inf", {M_X: -INF}),
    ("x 1 km past the stroke", {M_X: 1.0e3}), ("x -1 km", {M_X: -1.0e3}),
    ("x subnormal", {M_X: 5.0e-324}),
    ("p_a NaN", {M_P_A: NAN}), ("p_a 0", {M_P_A: 0.0}), ("p_a negative", {M_P_A: -2.0e5}),
    ("p_a 1e12", {M_P_A: 1.0e12}), ("p_a +inf", {M_P_A: INF}),
    ("p_b NaN", {M_P_B: NAN}), ("p_b above supply", {M_P_B: 9.0e5}), ("p_b -inf", {M_P_B: -INF}),
    ("p_s NaN", {M_P_S: NAN}), ("p_s 0", {M_P_S: 0.0}),
    ("no flow in mode 1", {M_P_A: 6.0e5, M_P_S: 6.0e5, M_P_B: 1.0e5}),
    ("no flow in mode 2", {M_P_A: 1.0e5, M_P_S: 6.0e5, M_P_B: 6.0e5}),
    ("x_r NaN", {M_X_R: NAN}), ("v_r NaN", {M_V_R: NAN}), ("v_r 1e6", {M_V_R: 1.0e6}),
    ("a_r NaN", {M_A_R: NAN}), ("a_r -1e9", {M_A_R: -1.0e9}),
    ("t NaN", {M_T: NAN}), ("t backwards", {M_T: -1.0}), ("t 1e9 s ahead", {M_T: 1.0e9}),
    ("everything NaN", dict.fromkeys(range(MEAS_SIZE), NAN)),
)


@pytest.fixture(scope="module")
def realistic_meas() -> np.ndarray:
    """60 samples of a closed loop (the paper's controller, the sine scenario): the base into
    which :data:`FAULTS` are injected."""
    controller = _controller("modified_darc", "up", "measured")
    _, meas, _, _ = next(_closed_loop_meas(controller, "immediate", seed=99))
    return np.ascontiguousarray(meas[200:260])


def _extreme_meas(seed: int, n: int = 300) -> np.ndarray:
    """Finite but extreme measurements: positions far past both stroke ends, pressures from
    below zero to 10 bar with ties at p0, p_a, p_s, reference speeds around the adaptation
    threshold and far above, large accelerations, jittered sample times."""
    rng = np.random.default_rng(seed)
    meas = np.empty((n, MEAS_SIZE))
    meas[:, M_T] = np.arange(n) * 0.004 + rng.uniform(-0.003, 0.003, n)
    meas[:, M_X] = rng.uniform(-0.1, 0.15, n)
    for j in (M_P_A, M_P_B, M_P_S):
        meas[:, j] = rng.uniform(-1.0e5, 1.0e6, n)
    tie = rng.random(n)
    meas[tie < 0.1, M_P_A] = meas[tie < 0.1, M_P_S]
    meas[(tie > 0.1) & (tie < 0.2), M_P_B] = 101325.0
    meas[:, M_X_R] = rng.uniform(-0.01, 0.06, n)
    meas[:, M_V_R] = rng.choice([0.0, 0.0009, -0.0011, 0.3, -5.0], n)
    meas[:, M_A_R] = rng.normal(0.0, 50.0, n)
    return meas


@pytest.mark.parametrize(("variant", "dead_zone", "position_feedback"), LAW_CASES)
def test_nan_and_extreme_measurements_agree(c_law: CLaw, realistic_meas: np.ndarray,
                                            variant: str, dead_zone: str,
                                            position_feedback: str) -> None:
    """Every fault of :data:`FAULTS` (NaN, infinities, pressures out of range, time jumps) held
    for 3 steps in a realistic sequence, and 300 finite extreme samples: both laws agree at
    every step, NaN where the installed law has NaN (tolerances: module docstring)."""
    controller = _controller(variant, dead_zone, position_feedback)
    vec = pack(controller)
    x0 = float(realistic_meas[0, M_X])
    state0 = _start(c_law, vec, x0, 3.2e5, 2.9e5)
    for what, values in FAULTS:
        meas = realistic_meas.copy()
        for j, value in values.items():
            meas[30:33, j] = value
        label = f"{variant}/{dead_zone}/{position_feedback} with {what}"
        _assert_agree(label, _replay_installed(vec, meas, state0),
                      _replay_c(c_law, vec, meas, state0))
    meas = _extreme_meas(seed=LAW_CASES.index((variant, dead_zone, position_feedback)))
    ref = _replay_installed(vec, meas, state0)
    _assert_agree(f"{variant}/{dead_zone}/{position_feedback} on extreme samples", ref,
                  _replay_c(c_law, vec, meas, state0))


def test_wrong_layout(c_law: CLaw) -> None:
    """A config vector of another layout: both steps close every valve, return 0 and set the
    status; pt_init_state refuses it (returns 1, state untouched) where init_state raises."""
    vec = pack(_controller("modified_darc", "up", "measured"))
    state0 = _start(c_law, vec, 0.02, 3.0e5, 3.0e5)
    bad = vec.copy()
    bad[CFG_LAYOUT] = 0.0
    meas = np.array([[0.0, 0.03, 3.0e5, 3.0e5, 6.0e5, 0.02, 0.05, 0.0]])
    ref = _replay_installed(bad, meas, state0)
    got = _replay_c(c_law, bad, meas, state0)
    _assert_agree("wrong layout", ref, got)
    assert got.cases[0] == 0 and got.states[0, S_STATUS] == 1.0
    np.testing.assert_array_equal(got.duties[0], 0.0)
    rc, state = c_law.init_state(bad, 0.02, 3.0e5, 3.0e5)
    assert rc == 1
    np.testing.assert_array_equal(state, -7.0)


def test_float_build_compiles(tmp_path: Path) -> None:
    """With -DPT_REAL_FLOAT (pt_real = float, the float math functions) the C builds under the
    same flags without a warning (compiled only: a float law cannot equal the double one)."""
    proc = _compile(tmp_path / "libptlaw_float.so", "-DPT_REAL_FLOAT")
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr


def test_the_laws_physics_is_the_plants(c_law: CLaw) -> None:
    """The ISO 6358 flow (Eq. 7) and S_f (Eq. 4) the law's model computes in C are the plant's
    numba functions (control/physics) bit for bit, on random and edge inputs: one formula in two
    languages, held equal (the plant's inner loop stays numba, where it inlines)."""
    from pneutune.control.physics.flow import iso6358_flow
    from pneutune.control.physics.friction import smooth_sign, smooth_sign_derivative

    lib = c_law.lib
    d = ctypes.c_double
    lib.pt_iso6358_flow.restype = d
    lib.pt_iso6358_flow.argtypes = [d] * 5
    for name in ("pt_smooth_sign", "pt_smooth_sign_derivative"):
        getattr(lib, name).restype = d
        getattr(lib, name).argtypes = [d]
    rng = np.random.default_rng(5)
    n = 4000
    C = rng.uniform(1e-9, 5e-8, n)
    b = rng.uniform(0.0, 0.9, n)
    p_u = rng.uniform(-1e5, 8e5, n)
    p_d = np.where(rng.random(n) < 0.2, p_u * rng.uniform(0.995, 1.0, n),
                   rng.uniform(0.0, 8e5, n))
    T = rng.uniform(250.0, 350.0, n)
    for k in range(n):
        args = (C[k], b[k], p_u[k], p_d[k], T[k])
        assert lib.pt_iso6358_flow(*args) == iso6358_flow(*args), args
    for v in (*rng.normal(0.0, 0.05, 2000), 0.0, -0.0, 1e-300, 50.0, -50.0):
        assert lib.pt_smooth_sign(v) == smooth_sign(v), v
        assert lib.pt_smooth_sign_derivative(v) == smooth_sign_derivative(v), v
