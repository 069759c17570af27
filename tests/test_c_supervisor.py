"""The C supervisor and controller (control/law/c: pt_supervisor.c, pt_controller.c, the generated
pt_sup_layout.h) built as a target builds them, against the deploy runtime, back to back.

The C is compiled once per module with the flags the port promises to build cleanly under
(together with the law, ptlaw.c, and a small shim that reports the structs' layout), loaded with
ctypes and fed the samples the Python gets:

* the supervisor alone (``pt_sup_check_sensors``, ``pt_sup_check_estimates``) against
  :class:`~pneutune.control.rig.supervisor.Supervisor` (the same C as the install built it,
  behind the runtime's packing and events) on sequences that trigger every fault and
  warning, at the thresholds' exact values and one ulp past them, on a clean closed loop and on
  random sequences: the same fault (and channel) and the same warnings at every sample;
* the controller (``pt_controller_step``) against
  :func:`~pneutune.control.rig.scenario_run.run_scenario` on the simulated rig with faults
  injected (:mod:`pneutune.control.rig.faults`): the C is fed the readings (and sample times)
  the runtime read, sample by sample, and must write the very duties the runtime wrote until
  the fault, the fail-safe duties from the fault's sample on (latched), with the runtime's
  fault code and warnings.

Decisions are compared exactly, and the duties bit for bit: the controller runs the same law
(ptlaw.c) as the runtime's step, with the same operations on the same doubles
(tests/test_c_law.py).
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import math
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rig_helpers import PAPER_YAML, SINE, TS

from pneutune.control.contracts.controller import ControllerConfig, load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.law.darc import STATE_SIZE
from pneutune.control.law.layout import CFG_LAYOUT, CFG_SIZE, pack
from pneutune.control.rig import supervisor_pack as sp
from pneutune.control.rig.faults import Fault, FaultySimRig
from pneutune.control.rig.runtime import START_TOLERANCE
from pneutune.control.rig.scenario_run import ScenarioResult, run_scenario, scenario_reference
from pneutune.control.rig.supervisor import (
    CHANNELS,
    EXHAUST_DUTIES,
    FAIL_SAFE_DUTIES,
    WATCHED_THETA,
    Event,
    Supervisor,
    SupervisorSettings,
)
from pneutune.control.sim.closed_loop import scenario_plant

ROOT = Path(__file__).resolve().parents[1]
C_DIR = ROOT / "control" / "law" / "c"
GCC = shutil.which("gcc")
#: The exact flags the C must build under without a warning.
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2", "-fPIC", "-shared")
SOURCES = ("ptlaw.c", "pt_supervisor.c", "pt_controller.c")
NEW_FILES = ("pt_supervisor.h", "pt_supervisor.c", "pt_controller.h", "pt_controller.c")

#: The tests that compile the C (the Python side is tested without a compiler).
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not on PATH: the C supervisor "
                               "(control/law/c) cannot be compiled")

#: A test-only translation unit: sizes and offsets of the API's structs, for the ctypes mirror.
SHIM = """#include <stddef.h>
#include "pt_controller.h"
size_t pt_test_layout(int i);
size_t pt_test_layout(int i)
{
    switch (i) {
    case 0: return sizeof(pt_config_t);
    case 1: return offsetof(pt_config_t, sup);
    case 2: return offsetof(pt_config_t, fail_safe);
    case 3: return offsetof(pt_config_t, sha256);
    case 4: return offsetof(pt_config_t, provenance);
    case 5: return sizeof(pt_controller_t);
    case 6: return offsetof(pt_controller_t, sup);
    case 7: return offsetof(pt_controller_t, status);
    case 8: return sizeof(pt_sensors_t);
    case 9: return sizeof(pt_reference_t);
    default: return 0;
    }
}
"""


class CSensors(ctypes.Structure):
    """``pt_sensors_t``."""

    _fields_ = [("x", ctypes.c_double), ("p_a", ctypes.c_double), ("p_b", ctypes.c_double),
                ("p_s", ctypes.c_double)]


class CReference(ctypes.Structure):
    """``pt_reference_t``."""

    _fields_ = [("x_r", ctypes.c_double), ("v_r", ctypes.c_double), ("a_r", ctypes.c_double)]


class CConfig(ctypes.Structure):
    """``pt_config_t``."""

    _fields_ = [("law", ctypes.c_double * CFG_SIZE), ("sup", ctypes.c_double * sp.SUP_SIZE),
                ("fail_safe", ctypes.c_double * 4), ("sha256", ctypes.c_char_p),
                ("provenance", ctypes.c_char_p)]


class CController(ctypes.Structure):
    """``pt_controller_t``."""

    _fields_ = [("law", ctypes.c_double * STATE_SIZE),
                ("sup", ctypes.c_double * sp.SUP_STATE_SIZE), ("status", ctypes.c_uint32)]


def _compile(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """gcc with :data:`CFLAGS` (and ``extra``) on the law, the supervisor and the controller."""
    return subprocess.run([GCC, *CFLAGS, *extra, "-I", str(C_DIR), "-o", str(out),
                           *(str(C_DIR / s) for s in SOURCES), "-lm"],
                          capture_output=True, text=True, check=False)


class CLib:
    """ctypes view of the supervisor and controller API (double build).

    Parameters
    ----------
    lib : ctypes.CDLL
        The loaded shared library.
    """

    def __init__(self, lib: ctypes.CDLL) -> None:
        self.lib = lib
        vp, d, u32 = ctypes.c_void_p, ctypes.c_double, ctypes.c_uint32
        lib.pt_sup_reset.argtypes = [vp]
        lib.pt_sup_reset.restype = None
        lib.pt_sup_check_sensors.argtypes = [vp, vp, d, vp, vp]
        lib.pt_sup_check_sensors.restype = u32
        lib.pt_sup_check_estimates.argtypes = [vp, vp, d, d, vp]
        lib.pt_sup_check_estimates.restype = u32
        lib.pt_first_fault.argtypes = [u32]
        lib.pt_first_fault.restype = ctypes.c_int
        lib.pt_fault_name.argtypes = [ctypes.c_int]
        lib.pt_fault_name.restype = ctypes.c_char_p
        lib.pt_controller_init.argtypes = [vp, vp, vp]
        lib.pt_controller_init.restype = ctypes.c_int
        lib.pt_controller_step.argtypes = [vp, vp, vp, vp, d, vp]
        lib.pt_controller_step.restype = u32
        lib.pt_controller_step_stamped.argtypes = [vp, vp, vp, vp, vp, d, vp]
        lib.pt_controller_step_stamped.restype = u32
        lib.pt_controller_trip.argtypes = [vp, vp, u32, vp]
        lib.pt_controller_trip.restype = u32
        lib.pt_test_layout.argtypes = [ctypes.c_int]
        lib.pt_test_layout.restype = ctypes.c_size_t


@pytest.fixture(scope="module")
def clib(tmp_path_factory: pytest.TempPathFactory) -> CLib:
    """The law, supervisor and controller compiled with exactly :data:`CFLAGS` (plus the layout
    shim) into a tmp folder, warning-free, loaded."""
    if GCC is None:
        pytest.skip("gcc is not on PATH: the C supervisor (control/law/c) cannot be compiled")
    folder = tmp_path_factory.mktemp("ptsup")
    shim = folder / "shim.c"
    shim.write_text(SHIM, encoding="ascii")
    out = folder / "libptsup.so"
    proc = _compile(out, str(shim))
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr
    return CLib(ctypes.CDLL(str(out)))


@pytest.fixture(scope="module")
def paper() -> ControllerConfig:
    return load_controller(PAPER_YAML)


@pytest.fixture(scope="module")
def settings(paper: ControllerConfig) -> SupervisorSettings:
    return SupervisorSettings.from_controller(paper)


# -- the header, the packing, the build ----------------------------------------------------------


def test_sup_layout_header_is_current(tmp_path: Path) -> None:
    """pt_sup_layout.h is what the Python tables generate; ``--check`` exits 1 on a stale or
    missing copy (in process and through ``python -m``)."""
    assert sp.main(["--check"]) == 0
    stale = tmp_path / "pt_sup_layout.h"
    stale.write_text(sp.sup_layout_header().replace("#define PT_SUP_P_MAX 9",
                                                    "#define PT_SUP_P_MAX 8"), encoding="ascii")
    assert sp.main(["--check", "--output", str(stale)]) == 1
    assert sp.main(["--check", "--output", str(tmp_path / "missing.h")]) == 1
    assert sp.main(["--output", str(stale)]) == 0
    assert sp.main(["--check", "--output", str(stale)]) == 0
    stale.write_text("/* stale */\n", encoding="ascii")
    cli = subprocess.run([sys.executable, "-m", "pneutune.control.rig.supervisor_pack", "--check",
                          "--output", str(stale)], capture_output=True, text=True, check=False)
    assert cli.returncode == 1 and "out of date" in cli.stderr


def test_pack_supervisor(paper: ControllerConfig, settings: SupervisorSettings) -> None:
    """The vector holds the thresholds the Python compares with; a controller packs as its
    default settings; the status bits follow FAULT_CODES and the names decode."""
    vec = sp.pack_supervisor(settings)
    assert vec.shape == (sp.SUP_SIZE,) and vec.dtype == np.float64
    np.testing.assert_array_equal(vec, sp.pack_supervisor(paper))
    assert vec[sp.SUP_LAYOUT] == sp.SUP_LAYOUT_ID < 2 ** 24
    assert vec[sp.SUP_SUPPLY_MIN] == settings.supply_min
    assert (vec[sp.SUP_P_SENSOR_LO], vec[sp.SUP_P_SENSOR_HI]) == settings.p_sensor_range
    assert vec[sp.SUP_X_LIM_HI] == settings.x_max + settings.x_tolerance
    assert vec[sp.SUP_START_TOL] == START_TOLERANCE
    assert sp.pack_supervisor(settings, start_tolerance=math.inf)[sp.SUP_START_TOL] == math.inf
    with pytest.raises(ValueError, match="start_tolerance"):
        sp.pack_supervisor(settings, start_tolerance=-1.0)
    off = sp.pack_supervisor(dataclasses.replace(settings, freeze_detection=False))
    assert off[sp.SUP_FREEZE] == 0.0 and vec[sp.SUP_FREEZE] == 1.0
    assert sp.STATUS_FAULT_CODES[:6] == ("sensor_nan", "sensor_range", "sensor_stale",
                                         "position_limit", "overpressure", "supply_loss")
    assert [sp.STATUS_BITS[f"FAULT_{c.upper()}"] for c in sp.STATUS_FAULT_CODES] == list(
        range(len(sp.STATUS_FAULT_CODES)))
    word = (1 << sp.STATUS_BITS["FAULT_OVERPRESSURE"]) | (1 << sp.STATUS_BITS["WARN_THETA_M_LOW"])
    assert sp.status_codes(word) == ("overpressure", "theta_m_low")
    assert sp.first_fault(word) == "overpressure" and sp.first_fault(0) is None
    np.testing.assert_array_equal(sp.pack_fail_safe("exhaust"), EXHAUST_DUTIES)
    np.testing.assert_array_equal(sp.pack_fail_safe(), FAIL_SAFE_DUTIES)
    with pytest.raises(ValueError):
        sp.pack_fail_safe([0.0, 1.5, 0.0, 0.0])
    with pytest.raises(ValueError):
        sp.pack_fail_safe("vent")


def test_struct_layout_and_names(clib: CLib) -> None:
    """The ctypes mirror of the API's structs has the C's sizes and offsets; the fault names
    come in the Python order."""
    lay = clib.lib.pt_test_layout
    assert lay(0) == ctypes.sizeof(CConfig)
    assert lay(1) == CConfig.sup.offset and lay(2) == CConfig.fail_safe.offset
    assert lay(3) == CConfig.sha256.offset and lay(4) == CConfig.provenance.offset
    assert lay(5) == ctypes.sizeof(CController)
    assert lay(6) == CController.sup.offset and lay(7) == CController.status.offset
    assert lay(8) == ctypes.sizeof(CSensors) and lay(9) == ctypes.sizeof(CReference)
    names = [clib.lib.pt_fault_name(i).decode() for i in range(len(sp.STATUS_FAULT_CODES))]
    assert names == list(sp.STATUS_FAULT_CODES)
    assert clib.lib.pt_fault_name(-1) == b"" and clib.lib.pt_fault_name(99) == b""
    for i in range(len(sp.STATUS_FAULT_CODES)):
        word = (1 << i) | (1 << sp.STATUS_BITS["WARN_REIDENTIFY_SUPPLY"])
        assert clib.lib.pt_first_fault(word) == i
    assert clib.lib.pt_first_fault(1 << sp.STATUS_BITS["STATUS_BAD_LAYOUT"]) == -1


@needs_gcc
def test_float_build_compiles(tmp_path: Path) -> None:
    """With -DPT_REAL_FLOAT the law, supervisor and controller build under the same flags without
    a warning (compiled only: float thresholds cannot equal the double decisions at an ulp)."""
    proc = _compile(tmp_path / "libptsup_float.so", "-DPT_REAL_FLOAT")
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr


def test_sources_use_only_the_allowed_headers() -> None:
    """The new C includes only <math.h>, <stddef.h>, <stdint.h> and the port's own headers, and
    allocates nothing."""
    for name in NEW_FILES:
        text = (C_DIR / name).read_text(encoding="ascii")
        for inc in re.findall(r"#include\s*([<\"][^>\"]+[>\"])", text):
            assert inc in ("<math.h>", "<stddef.h>", "<stdint.h>", '"ptlaw.h"', '"pt_layout.h"',
                           '"pt_sup_layout.h"', '"pt_supervisor.h"', '"pt_controller.h"'), \
                (name, inc)
        assert not re.search(r"\b(malloc|calloc|realloc|free|alloca)\s*\(", text), name


# -- the supervisor alone, back to back -----------------------------------------------------------


def _py_channel(ev: Event) -> str:
    """The channel a Python fault message names."""
    if ev.code in ("sensor_nan", "sensor_range", "sensor_stale"):
        m = re.match(r"sensor (\w+)", ev.message)
        assert m is not None, ev.message
        return m.group(1)
    if ev.code == "overpressure":
        return ev.message.split(" = ", 1)[0]
    return {"position_limit": "x", "supply_loss": "p_s"}[ev.code]


def _py_warnings(events: list[Event]) -> frozenset[str]:
    """Python warning events as the C's status names: the codes, and per θ̂ event its detail."""
    out = set()
    for e in events:
        out.add(e.code)
        if e.code == "reidentify_theta":
            m = re.match(r"θ̂ (\S+) = .* of its (lower|upper) bound", e.message)
            assert m is not None, e.message
            out.add(f"theta_{m.group(1).lower()}_{'low' if m.group(2) == 'lower' else 'high'}")
    return frozenset(out)


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What a supervisor decided on one sample."""

    fault: str | None
    channel: str | None
    warnings: frozenset[str]


@dataclasses.dataclass
class Samples:
    """Samples to feed both supervisors: times, readings, sample times (or None), θ̂."""

    t: np.ndarray
    sensors: np.ndarray
    stamps: np.ndarray | None
    theta: np.ndarray


def _replay_py(settings: SupervisorSettings, seq: Samples) -> list[Outcome]:
    """The runtime's supervisor on every sample: check_sensors, then check_estimates (also after a
    fault: the supervisor alone keeps judging)."""
    sup = Supervisor(settings)
    out = []
    for k in range(seq.t.shape[0]):
        t = float(seq.t[k])
        ev = sup.check_sensors(t, seq.sensors[k], None if seq.stamps is None else seq.stamps[k])
        warns = sup.check_estimates(t, float(seq.sensors[k, 3]), seq.theta[k])
        out.append(Outcome(None if ev is None else ev.code,
                           None if ev is None else _py_channel(ev), _py_warnings(warns)))
    return out


def _replay_c(clib: CLib, vec: np.ndarray, seq: Samples) -> list[Outcome]:
    """The C supervisor on the same samples, in the same calls; its status words checked to
    hold only fault or warning bits, at most one fault bit, with a fault channel."""
    lib = clib.lib
    state = np.full(sp.SUP_STATE_SIZE, -7.0)
    lib.pt_sup_reset(state.ctypes.data)
    sensors = np.ascontiguousarray(seq.sensors, dtype=np.float64)
    theta = np.ascontiguousarray(seq.theta, dtype=np.float64)
    stamps = None if seq.stamps is None else np.ascontiguousarray(seq.stamps, dtype=np.float64)
    p_state, p_vec = state.ctypes.data, vec.ctypes.data
    out = []
    for k in range(seq.t.shape[0]):
        t = float(seq.t[k])
        p_stamps = None if stamps is None else stamps.ctypes.data + k * stamps.strides[0]
        p_sensors = sensors.ctypes.data + k * sensors.strides[0]
        f = lib.pt_sup_check_sensors(p_state, p_vec, t, p_sensors, p_stamps)
        ch = int(state[sp.SUP_S_FAULT_CHANNEL])
        w = lib.pt_sup_check_estimates(p_state, p_vec, t, float(sensors[k, 3]),
                                       theta.ctypes.data + k * theta.strides[0])
        assert not f & ~sp.FAULT_MASK and not w & ~sp.WARN_MASK
        assert bin(f).count("1") <= 1, "at most one fault bit"
        assert (f == 0) == (ch == -1)
        out.append(Outcome(sp.first_fault(f), CHANNELS[ch] if f else None,
                           frozenset(sp.status_codes(w))))
    return out


def _assert_same(label: str, ref: list[Outcome], got: list[Outcome]) -> None:
    """Equal decisions at every sample; the first difference otherwise."""
    for k, (a, b) in enumerate(zip(ref, got, strict=True)):
        assert a == b, f"{label}: sample {k}: Python {a}, C {b}"


@pytest.fixture(scope="module")
def clean_seq(paper: ControllerConfig) -> Samples:
    """3 s of the sine closed loop on the simulated rig under the runtime (no sample times):
    its readings and θ̂, and the sample times a fresh rig reports (every channel new)."""
    rig = _RecordingRig(scenario_plant(PlantConfig(), SINE), x0=_x_r0(),
                        seed=1, report_sample_times=False)
    res = run_scenario(paper, SINE, rig, duration=3.0)
    assert res.fault is None and res.loop.events == []
    rec = res.loop.recording
    t = np.arange(rec.n) * TS
    return Samples(t, rec.sensors_.copy(), np.repeat(t[:, None], 4, axis=1),
                     rec.state_[:, -6:].copy())


def _up(v: float) -> float:
    return float(np.nextafter(v, math.inf))


def _down(v: float) -> float:
    return float(np.nextafter(v, -math.inf))


K = 300  # where the sequences below inject


def _set(col: int, value: float, k0: int = K, k1: int = K + 1) -> Callable[[Samples], None]:
    def edit(seq: Samples) -> None:
        seq.sensors[k0:k1, col] = value
    return edit


def _freeze(col: int, stamp: bool) -> Callable[[Samples], None]:
    def edit(seq: Samples) -> None:
        if stamp:
            assert seq.stamps is not None
            seq.stamps[K:, col] = seq.t[K - 1]
        else:
            seq.sensors[K:, col] = seq.sensors[K, col]
    return edit


def _combined(seq: Samples) -> None:
    """Several faults in one sample, every pair in the order of the checks."""
    v = _paper_vec()
    s = seq.sensors
    s[100, [0, 1]] = [math.nan, -1.0]                               # nan before range
    s[110, [0, 2]] = [_up(v[sp.SUP_X_SPAN_HI]), 1.0e9]               # range x before range p_b
    s[120, [1, 3]] = [-1.0, math.inf]                                # nan p_s before range p_a
    s[130, [0, 1]] = [_up(v[sp.SUP_X_LIM_HI]), _up(v[sp.SUP_P_MAX])]  # position before pressure
    s[140, [2, 3]] = [_up(v[sp.SUP_P_MAX]), _down(v[sp.SUP_SUPPLY_MIN])]  # pressure, supply
    s[150, [1, 2]] = [_up(v[sp.SUP_P_MAX]), _up(v[sp.SUP_P_MAX])]    # p_a before p_b
    s[160:, 3] = s[160, 3]                                           # stale p_s ...
    s[166, 0] = _up(v[sp.SUP_X_LIM_HI])                              # ... before position


def _supply(seq: Samples) -> None:
    """A 0.4 s dip (no warning), then a lasting drop of 1.2 bar (warned after 0.5 s)."""
    seq.sensors[100:200, 3] -= 1.2e5
    seq.sensors[250:, 3] -= 1.2e5


def _theta(seq: Samples) -> None:
    """M on its lower bound for 1.2 s then off and on again, b_v exactly at the band's edge
    below theta_max from the start, A_f near its lower bound for 0.8 s only."""
    a = load_controller(PAPER_YAML).adaptation
    seq.theta[100:400, 0] = a.theta_min[0]
    seq.theta[450:700, 0] = a.theta_min[0]
    lo, hi = a.theta_min[2], a.theta_max[2]
    seq.theta[:, 2] = hi - 0.02 * (hi - lo)
    seq.theta[500:700, 3] = a.theta_min[3]


@functools.cache
def _paper_vec() -> np.ndarray:
    return sp.pack_supervisor(load_controller(PAPER_YAML))


def _v(name: str) -> float:
    """A threshold of the paper's controller, by its slot name."""
    return float(_paper_vec()[getattr(sp, name)])


#: (name, edit of the clean sequence, use sample times, settings changes, expected first
#: (code, sample) or None, expected warnings {sample: names})
SEQUENCES: list[tuple[str, Callable[[Samples], None], bool, dict[str, object],
                      tuple[str, int] | None, dict[int, set[str]]]] = [
    ("clean", lambda s: None, False, {}, None, {}),
    ("clean-stamped", lambda s: None, True, {}, None, {}),
    *[(f"nan-{ch}", _set(i, math.nan), False, {}, ("sensor_nan", K), {})
      for i, ch in enumerate(CHANNELS)],
    ("inf-p_a", _set(1, math.inf), False, {}, ("sensor_nan", K), {}),
    ("-inf-x", _set(0, -math.inf), False, {}, ("sensor_nan", K), {}),
    ("range-x-low", _set(0, _down(_v("SUP_X_SPAN_LO"))), False, {}, ("sensor_range", K), {}),
    ("range-x-high", _set(0, _up(_v("SUP_X_SPAN_HI"))), False, {}, ("sensor_range", K), {}),
    ("x-at-span-low-is-position", _set(0, _v("SUP_X_SPAN_LO")), False, {},
     ("position_limit", K), {}),
    *[(f"range-{ch}-low", _set(i, _down(_v("SUP_P_SENSOR_LO"))), False, {},
       ("sensor_range", K), {}) for i, ch in enumerate(CHANNELS) if i > 0],
    *[(f"range-{ch}-high", _set(i, _up(_v("SUP_P_SENSOR_HI"))), False, {},
       ("sensor_range", K), {}) for i, ch in enumerate(CHANNELS) if i > 0],
    ("p_a-at-sensor-max-is-overpressure", _set(1, _v("SUP_P_SENSOR_HI")), False, {},
     ("overpressure", K), {}),
    ("p_s-at-sensor-min-is-supply-loss", _set(3, _v("SUP_P_SENSOR_LO")), False, {},
     ("supply_loss", K), {}),
    *[(f"stale-{ch}-values", _freeze(i, stamp=False), False, {}, ("sensor_stale", K + 6), {})
      for i, ch in enumerate(CHANNELS) if i > 0],
    ("frozen-x-values-is-fine", _freeze(0, stamp=False), False, {}, None, {}),
    ("frozen-p_a-without-freeze-detection", _freeze(1, stamp=False), False,
     {"freeze_detection": False}, None, {}),
    *[(f"stale-{ch}-stamps", _freeze(i, stamp=True), True, {}, ("sensor_stale", K + 5), {})
      for i, ch in enumerate(CHANNELS)],
    ("position-limit-high", _set(0, _up(_v("SUP_X_LIM_HI"))), False, {},
     ("position_limit", K), {}),
    ("position-limit-low", _set(0, _down(_v("SUP_X_LIM_LO"))), False, {},
     ("position_limit", K), {}),
    ("position-within-tolerance", _set(0, _v("SUP_X_LIM_HI"), K, K + 50), False, {}, None, {}),
    ("overpressure-p_a", _set(1, _up(_v("SUP_P_MAX"))), False, {}, ("overpressure", K), {}),
    ("overpressure-p_b", _set(2, _up(_v("SUP_P_MAX"))), False, {}, ("overpressure", K), {}),
    ("p_max-exactly", _set(2, _v("SUP_P_MAX")), False, {}, None, {}),
    ("supply-loss", _set(3, _down(_v("SUP_SUPPLY_MIN"))), False, {}, ("supply_loss", K), {}),
    ("supply-min-exactly", _set(3, _v("SUP_SUPPLY_MIN")), False, {}, None, {}),
    ("combined", _combined, False, {}, ("sensor_nan", 100), {}),
    ("supply-warning", _supply, False, {}, None, {375: {"reidentify_supply"}}),
    ("theta-warning", _theta, False, {}, None,
     {250: {"reidentify_theta", "theta_b_v_high"}, 350: {"reidentify_theta", "theta_m_low"}}),
]


@pytest.mark.parametrize(("name", "edit", "stamped", "changes", "first", "warned"), SEQUENCES,
                         ids=[s[0] for s in SEQUENCES])
def test_supervisor_sequences_agree(clib: CLib, settings: SupervisorSettings,
                                    clean_seq: Samples, name: str,
                                    edit: Callable[[Samples], None], stamped: bool,
                                    changes: dict[str, object], first: tuple[str, int] | None,
                                    warned: dict[int, set[str]]) -> None:
    """The clean closed loop with one fault or warning cause injected: both supervisors take
    the same decision at every sample (fault code, its channel, the warnings; they keep being
    called after a fault), and the sequence does trigger what it is named after."""
    seq = Samples(clean_seq.t, clean_seq.sensors.copy(),
                    clean_seq.stamps.copy() if stamped and clean_seq.stamps is not None else None,
                    clean_seq.theta.copy())
    edit(seq)
    s = dataclasses.replace(settings, **changes) if changes else settings
    ref = _replay_py(s, seq)
    _assert_same(name, ref, _replay_c(clib, sp.pack_supervisor(s), seq))
    faults = [(o.fault, k) for k, o in enumerate(ref) if o.fault is not None]
    assert (faults[0] if faults else None) == first
    assert {k: set(o.warnings) for k, o in enumerate(ref) if o.warnings} == warned


def _fuzz(settings: SupervisorSettings, seed: int, stamped: bool, n: int = 4000) -> Samples:
    """Random samples from the values that matter: each threshold, one ulp either side, NaN and
    infinities, long runs of repeated readings, sample times around the timeout, θ̂ dwelling on
    and off the bands; every cause comes and goes (the supervisors keep running after a
    fault)."""
    rng = np.random.default_rng(seed)
    v = sp.pack_supervisor(settings)
    t = np.arange(n) * TS

    def around(*xs: float) -> list[float]:
        return [y for x in xs for y in (_down(x), x, _up(x))]

    special = [
        around(v[sp.SUP_X_SPAN_LO], v[sp.SUP_X_SPAN_HI], v[sp.SUP_X_LIM_LO], v[sp.SUP_X_LIM_HI]),
        around(v[sp.SUP_P_SENSOR_LO], v[sp.SUP_P_SENSOR_HI], v[sp.SUP_P_MAX]),
        around(v[sp.SUP_P_SENSOR_LO], v[sp.SUP_P_SENSOR_HI], v[sp.SUP_P_MAX]),
        around(v[sp.SUP_SUPPLY_MIN], v[sp.SUP_P_S_MODEL] - v[sp.SUP_SUPPLY_WARN_DELTA],
               v[sp.SUP_P_S_MODEL] + v[sp.SUP_SUPPLY_WARN_DELTA]),
    ]
    sensors = np.empty((n, 4))
    mode = np.zeros(4, dtype=int)  # 0 fresh, 1 frozen, 2 special values
    drift = 0.0  # the supply's offset from the model's: 0 or a lasting 1.2 bar drop
    for k in range(n):
        if rng.random() < 0.005:
            drift = -1.2e5 - drift if drift else -1.2e5
        fresh = np.array([rng.uniform(settings.x_min, settings.x_max),
                          rng.uniform(2.0e5, 6.0e5), rng.uniform(2.0e5, 6.0e5),
                          settings.p_s_model + drift + rng.normal(0.0, 3.0e3)])
        for i in range(4):
            if rng.random() < 0.02:
                mode[i] = rng.choice(3, p=[0.7, 0.1, 0.2])
            if mode[i] == 1 and k > 0:
                sensors[k, i] = sensors[k - 1, i]
            elif mode[i] == 2:
                sensors[k, i] = rng.choice([*special[i], math.nan, math.inf, -math.inf])
            else:
                sensors[k, i] = fresh[i]
    stamps = None
    if stamped:
        ages = rng.choice([0.0, TS, settings.sensor_timeout_s, _up(settings.sensor_timeout_s),
                           settings.sensor_timeout_s + 1e-9, 0.024], size=(n, 4),
                          p=[0.9, 0.05, 0.02, 0.01, 0.01, 0.01])
        stamps = t[:, None] - ages
    a_lo, a_hi = np.array(settings.theta_min), np.array(settings.theta_max)
    theta = np.repeat(((a_lo + a_hi) / 2)[None, :], n, axis=0)
    for j in WATCHED_THETA:
        lo, hi = a_lo[j], a_hi[j]
        band = settings.theta_band * (hi - lo)
        choices = [*around(lo + band, hi - band), lo, hi, 0.5 * (lo + hi)]
        value = choices[-1]
        for k in range(n):
            if rng.random() < 0.004:
                value = choices[rng.integers(len(choices))]
            theta[k, j] = value
    return Samples(t, sensors, stamps, theta)


@pytest.mark.parametrize(("seed", "stamped"), [(1, False), (2, True), (3, False)])
def test_supervisor_random_sequences_agree(clib: CLib, settings: SupervisorSettings, seed: int,
                                           stamped: bool) -> None:
    """4000 random samples around every threshold (:func:`_fuzz`): the same decision at every
    sample, and the sequences reach every fault and warning."""
    seq = _fuzz(settings, seed, stamped)
    ref = _replay_py(settings, seq)
    _assert_same(f"random seed {seed}", ref, _replay_c(clib, sp.pack_supervisor(settings), seq))
    seen = {o.fault for o in ref} | {w for o in ref for w in o.warnings}
    assert set(sp.STATUS_FAULT_CODES[:6]) <= seen, seen
    assert {"reidentify_supply", "reidentify_theta"} <= seen, seen


def test_supervisor_time_boundaries(clib: CLib, settings: SupervisorSettings) -> None:
    """Times that put an age or a hold exactly on its threshold, one ulp either side (the times
    need not be k Ts): stale only past the timeout (sample times and values), the warnings from
    the hold time on; both supervisors alike."""
    v = sp.pack_supervisor(settings)
    age, hold_s, hold_t = v[sp.SUP_STALE_AGE], v[sp.SUP_SUPPLY_HOLD], v[sp.SUP_THETA_HOLD]
    t0 = 0.0  # the ages below are then the times themselves, exactly
    good = np.array([0.02, 3.0e5, 3.1e5, 6.0e5])
    a = settings.theta_min, settings.theta_max
    theta0 = 0.5 * (np.array(a[0]) + np.array(a[1]))
    rng = np.random.default_rng(5)

    def samples(times: list[float]) -> Samples:
        n = len(times)
        sensors = good + rng.uniform(0.0, 1.0e3, (n, 4)) * np.array([1e-9, 1.0, 1.0, 1.0])
        return Samples(np.array(times), sensors, None, np.repeat(theta0[None, :], n, axis=0))

    cases: list[tuple[str, Samples, list[str | None]]] = []
    # values: p_a frozen from t0, judged at exactly the age, then one ulp later
    seq = samples([t0, age / 2, age, _up(age)])
    seq.sensors[:, 1] = seq.sensors[0, 1]
    cases.append(("values", seq, [None, None, None, "sensor_stale"]))
    # sample times: x last new at t0
    seq = samples([age, _up(age)])
    seq.stamps = np.repeat(seq.t[:, None], 4, axis=1)
    seq.stamps[:, 0] = t0
    cases.append(("stamps", seq, [None, "sensor_stale"]))
    # supply 1.2 bar low from t0: warned when held reaches the hold time, not an ulp before
    seq = samples([t0, _down(hold_s), hold_s, 2 * hold_s])
    seq.sensors[:, 3] = settings.p_s_model - 1.2e5 + np.arange(4)  # changing: not stale
    cases.append(("supply", seq, [None, None, "reidentify_supply", None]))
    # θ̂ of A_f on the edge of the band below θ_max from t0
    seq = samples([t0, _down(hold_t), hold_t])
    lo, hi = settings.theta_min[3], settings.theta_max[3]
    seq.theta[:, 3] = hi - settings.theta_band * (hi - lo)
    cases.append(("theta", seq, [None, None, "reidentify_theta"]))
    for name, seq, expected in cases:
        ref = _replay_py(settings, seq)
        _assert_same(name, ref, _replay_c(clib, v, seq))
        got = [o.fault or next((w for w in sorted(o.warnings) if w.startswith("re")), None)
               for o in ref]
        assert got == expected, name


def test_bad_sup_layout(clib: CLib, settings: SupervisorSettings) -> None:
    """A settings vector of another layout: both checks return PT_STATUS_BAD_LAYOUT and touch
    nothing."""
    vec = sp.pack_supervisor(settings)
    vec[sp.SUP_LAYOUT] = 0.0
    state = np.full(sp.SUP_STATE_SIZE, 3.0)
    sensors = np.array([0.02, 3.0e5, 3.0e5, 6.0e5])
    bad = 1 << sp.STATUS_BITS["STATUS_BAD_LAYOUT"]
    assert clib.lib.pt_sup_check_sensors(state.ctypes.data, vec.ctypes.data, 0.0,
                                         sensors.ctypes.data, None) == bad
    assert clib.lib.pt_sup_check_estimates(state.ctypes.data, vec.ctypes.data, 0.0, 6.0e5,
                                           np.zeros(6).ctypes.data) == bad
    np.testing.assert_array_equal(state, 3.0)


# -- the controller against the runtime ---------------------------------------------------------


class _RecordingRig(FaultySimRig):
    """The faulty simulated rig, keeping every reading and sample-time vector it hands out."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        self.reads: list[np.ndarray] = []
        self.stamps: list[np.ndarray | None] = []
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]

    def read(self) -> np.ndarray:
        vals = super().read()
        self.reads.append(vals.copy())
        return vals

    def sample_times(self) -> np.ndarray | None:
        st = super().sample_times()
        self.stamps.append(None if st is None else st.copy())
        return st


def _x_r0() -> float:
    plant = scenario_plant(PlantConfig(), SINE)
    return float(scenario_reference(SINE, plant.rig_metadata())[0, 0])


def _with(controller: ControllerConfig, **limits: float) -> ControllerConfig:
    return controller.model_copy(update={"limits": controller.limits.model_copy(update=limits)})


def _theta_on_bound(controller: ControllerConfig) -> ControllerConfig:
    """θ̂ of the mass frozen (γ 0) 1 % of its range above θ_min: warned after the hold time."""
    a = controller.adaptation
    lo, hi = a.theta_min[0], a.theta_max[0]
    return controller.model_copy(update={"adaptation": a.model_copy(update={
        "theta_0": (lo + 0.01 * (hi - lo), *a.theta_0[1:]), "gamma": (0.0, *a.gamma[1:])})})


@dataclasses.dataclass(frozen=True)
class Deploy:
    """One runtime case: the config change, injected faults, rig options, fail-safe, expected
    fault code (None: the run completes) and the warnings' samples."""

    name: str
    change: Callable[[ControllerConfig], ControllerConfig] = lambda c: c
    faults: tuple[Fault, ...] = ()
    report_sample_times: bool = True
    fail_safe: tuple[float, float, float, float] = FAIL_SAFE_DUTIES
    x0_shift: float = 0.0
    home: str = "auto"
    duration: float = 2.0
    fault: str | None = None
    warned: tuple[int, ...] = ()


DEPLOYS = [
    Deploy("clean", duration=3.0),
    Deploy("clean-values", report_sample_times=False, duration=3.0),
    Deploy("nan-p_a-exhaust", faults=(Fault("nan", 1.0, "p_a"),), fail_safe=EXHAUST_DUTIES,
           fault="sensor_nan"),
    Deploy("nan-x", faults=(Fault("nan", 1.0, "x"),), fault="sensor_nan"),
    Deploy("range-p_s", faults=(Fault("value", 1.0, "p_s", 2.5e6),), fault="sensor_range"),
    Deploy("range-x", faults=(Fault("value", 1.0, "x", 1.0),), fault="sensor_range"),
    Deploy("stale-x-stamps", faults=(Fault("stale", 1.0, "x"),), fault="sensor_stale"),
    Deploy("stale-p_b-values", faults=(Fault("stale", 1.0, "p_b", stamp=False),),
           report_sample_times=False, fault="sensor_stale"),
    Deploy("position-limit", change=lambda c: _with(c, x_max=0.035), fault="position_limit"),
    Deploy("overpressure", change=lambda c: _with(c, p_max=4.0e5), fault="overpressure"),
    Deploy("supply-loss", faults=(Fault("supply", 1.0, value=2.0e5),), fault="supply_loss"),
    Deploy("supply-warning", faults=(Fault("supply", 1.0, value=4.8e5),), warned=(375,)),
    Deploy("theta-warning", change=_theta_on_bound, warned=(250,)),
    Deploy("start-position", x0_shift=2.0e-3, home="off", duration=0.2,
           fault="start_position"),
]


def _config(controller: ControllerConfig, fail_safe: tuple[float, ...],
            start_tolerance: float = START_TOLERANCE) -> CConfig:
    cfg = CConfig()
    cfg.law[:] = pack(controller).tolist()
    cfg.sup[:] = sp.pack_supervisor(controller, start_tolerance=start_tolerance).tolist()
    cfg.fail_safe[:] = list(fail_safe)
    cfg.sha256 = b"0" * 64
    cfg.provenance = b"tests/test_c_supervisor.py"
    return cfg


@dataclasses.dataclass
class CRun:
    """What the C controller did: per sample the status and duties, the law state per sample."""

    status: np.ndarray
    duties: np.ndarray
    law: np.ndarray


def _run_c(clib: CLib, cfg: CConfig, reads: list[np.ndarray], stamps: list[np.ndarray | None],
           ref: np.ndarray, first: np.ndarray | None = None) -> CRun:
    """Feed the C controller the runtime's readings (and sample times) with the reference at
    t = k Ts; past the last reading, the last fit reading again (a latched controller must keep
    the fail-safe whatever it reads)."""
    lib = clib.lib
    c = CController()
    first_s = None if first is None else ctypes.byref(CSensors(*first.tolist()))
    assert lib.pt_controller_init(ctypes.byref(c), ctypes.byref(cfg), first_s) == 0
    n = ref.shape[0]
    run = CRun(np.zeros(n, dtype=np.int64), np.zeros((n, 4)), np.zeros((n, STATE_SIZE)))
    duties = (ctypes.c_double * 4)()
    for k in range(n):
        j = k if k < len(reads) else max(0, len(reads) - 2)
        s = CSensors(*reads[j].tolist())
        r = CReference(*ref[k].tolist())
        st = stamps[j] if k < len(reads) else None
        if st is None:
            run.status[k] = lib.pt_controller_step(ctypes.byref(c), ctypes.byref(cfg),
                                                   ctypes.byref(s), ctypes.byref(r), k * TS,
                                                   duties)
        else:
            p = (ctypes.c_double * 4)(*st.tolist())
            run.status[k] = lib.pt_controller_step_stamped(ctypes.byref(c), ctypes.byref(cfg),
                                                           ctypes.byref(s), p, ctypes.byref(r),
                                                           k * TS, duties)
        run.duties[k] = list(duties)
        run.law[k] = list(c.law)
    return run


def _deploy_py(controller: ControllerConfig, case: Deploy) -> tuple[_RecordingRig, ScenarioResult]:
    plant = scenario_plant(PlantConfig(), SINE)
    rig = _RecordingRig(plant, faults=case.faults, x0=_x_r0() + case.x0_shift, seed=1,
                        report_sample_times=case.report_sample_times)
    res = run_scenario(controller, SINE, rig, duration=case.duration, fail_safe=case.fail_safe,
                       plant=plant, seed=1, home=case.home)
    return rig, res


@pytest.mark.parametrize("case", DEPLOYS, ids=[d.name for d in DEPLOYS])
def test_controller_matches_runtime(clib: CLib, paper: ControllerConfig, case: Deploy) -> None:
    """The runtime on the simulated rig with a fault injected, and the C controller fed what the
    runtime read: the same duties, bit for bit, at every sample before the fault; the fail-safe
    duties from the fault's sample on, whatever comes next, with the runtime's fault code
    latched; the law state untouched from the fault on (NaN never reaches it); the warnings at
    the runtime's samples."""
    controller = case.change(paper)
    rig, res = _deploy_py(controller, case)
    ref = scenario_reference(SINE, rig.rig_metadata())[:round(case.duration / TS)]
    n = ref.shape[0]
    fault = res.fault
    assert (None if fault is None else fault.code) == case.fault
    k_fault = n if fault is None else round(fault.t / TS)
    assert len(rig.reads) == min(n, k_fault + 1)
    run = _run_c(clib, _config(controller, case.fail_safe), rig.reads, rig.stamps, ref)
    # before the fault: the runtime's duties, no fault
    py_duties = res.loop.recording.duties_
    np.testing.assert_array_equal(run.duties[:k_fault], py_duties[:k_fault], err_msg=case.name)
    assert not np.any(run.status[:k_fault] & sp.FAULT_MASK), case.name
    # from the fault on: the fail-safe, the fault latched, the law frozen
    if fault is not None:
        np.testing.assert_array_equal(run.duties[k_fault:], np.broadcast_to(case.fail_safe,
                                                                           (n - k_fault, 4)))
        np.testing.assert_array_equal(rig.last_duties, case.fail_safe)
        codes = {sp.first_fault(int(st)) for st in run.status[k_fault:]}
        assert codes == {fault.code}, (case.name, codes)
        assert {int(st) & sp.WARN_MASK for st in run.status[k_fault:]} == {0}
        before = run.law[k_fault - 1] if k_fault else np.zeros(STATE_SIZE)
        np.testing.assert_array_equal(run.law[k_fault:], np.broadcast_to(
            before, (n - k_fault, STATE_SIZE)))
        assert np.all(np.isfinite(run.law[k_fault:])), "NaN reached the law"
    # the warnings, at the runtime's samples
    py_warn = {round(e.t / TS): _py_warnings([e]) for e in res.loop.events
               if e.level == "warning"}
    c_warn = {k: frozenset(sp.status_codes(int(st) & sp.WARN_MASK))
              for k, st in enumerate(run.status) if int(st) & sp.WARN_MASK}
    assert c_warn == py_warn, case.name
    assert sorted(py_warn) == list(case.warned)


def test_controller_homing_first(clib: CLib, paper: ControllerConfig) -> None:
    """``first`` given: the law starts at the first reading, as the runtime's homing move does
    (its reference starts there, start check off): the homing samples' duties bit for bit."""
    case = Deploy("homing", x0_shift=3.0e-3, home="always", duration=0.1)
    rig, res = _deploy_py(paper, case)
    assert res.homing is not None and res.homing.fault is None and res.fault is None
    n_home = res.homing.n_done
    ref = res.homing.recording.reference_
    cfg = _config(paper, FAIL_SAFE_DUTIES, start_tolerance=math.inf)
    run = _run_c(clib, cfg, rig.reads[:n_home], rig.stamps[:n_home], ref, first=rig.reads[0])
    np.testing.assert_array_equal(run.duties, res.homing.recording.duties_)
    assert not np.any(run.status)


def test_controller_config_and_trip(clib: CLib, paper: ControllerConfig,
                                    clean_seq: Samples) -> None:
    """A config of another layout (law or supervisor) or fail-safe duties outside [0, 1]:
    init returns 1, every step closes every valve and returns the config bit. A fault the target
    finds itself (rig_io) latches the fail-safe like any other, and a later one does not
    replace it; a re-init starts afresh."""
    lib = clib.lib
    ref = scenario_reference(SINE, scenario_plant(PlantConfig(), SINE).rig_metadata())
    duties = (ctypes.c_double * 4)()
    s = CSensors(*clean_seq.sensors[0].tolist())
    r = CReference(*ref[0].tolist())
    bits = sp.STATUS_BITS
    for what, bit in (("law", "STATUS_BAD_LAYOUT"), ("sup", "STATUS_BAD_LAYOUT"),
                      ("fail_safe", "STATUS_BAD_FAIL_SAFE")):
        cfg = _config(paper, EXHAUST_DUTIES)
        if what == "law":
            cfg.law[CFG_LAYOUT] = 0.0
        elif what == "sup":
            cfg.sup[sp.SUP_LAYOUT] = 1.0
        else:
            cfg.fail_safe[1] = math.nan
        c = CController()
        assert lib.pt_controller_init(ctypes.byref(c), ctypes.byref(cfg), None) == 1
        for k in range(3):
            st = lib.pt_controller_step(ctypes.byref(c), ctypes.byref(cfg), ctypes.byref(s),
                                        ctypes.byref(r), k * TS, duties)
            assert st == 1 << bits[bit], what
            assert list(duties) == [0.0] * 4
    cfg = _config(paper, EXHAUST_DUTIES)
    c = CController()
    assert lib.pt_controller_init(ctypes.byref(c), ctypes.byref(cfg), None) == 0
    assert lib.pt_controller_step(ctypes.byref(c), ctypes.byref(cfg), ctypes.byref(s),
                                  ctypes.byref(r), 0.0, duties) == 0
    law = list(c.law)
    rig_io = 1 << bits["FAULT_RIG_IO"]
    assert lib.pt_controller_trip(ctypes.byref(c), ctypes.byref(cfg), 0, duties) == rig_io
    assert list(duties) == list(EXHAUST_DUTIES)
    over = 1 << bits["FAULT_OVERPRESSURE"]
    assert lib.pt_controller_trip(ctypes.byref(c), ctypes.byref(cfg), over, duties) == rig_io
    s1 = CSensors(*clean_seq.sensors[1].tolist())
    assert lib.pt_controller_step(ctypes.byref(c), ctypes.byref(cfg), ctypes.byref(s1),
                                  ctypes.byref(CReference(*ref[1].tolist())), TS,
                                  duties) == rig_io
    assert list(duties) == list(EXHAUST_DUTIES) and list(c.law) == law
    assert c.status == rig_io
    # a NaN reference is a fault of its own (the runtime never gets one): fail-safe at once
    assert lib.pt_controller_init(ctypes.byref(c), ctypes.byref(cfg), None) == 0
    assert c.status == 0
    bad_r = CReference(ref[0, 0], math.nan, 0.0)
    assert lib.pt_controller_step(ctypes.byref(c), ctypes.byref(cfg), ctypes.byref(s),
                                  ctypes.byref(bad_r), 0.0, duties) == 1 << bits[
                                      "FAULT_REFERENCE_NAN"]
    assert list(duties) == list(EXHAUST_DUTIES)
    assert not any(c.law)  # the law was never initialised, let alone stepped
