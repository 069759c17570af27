"""``deploy --emit c``: the controller as the C99 folder a target compiles (control/rig/emit_c.py).

The paper's controller is emitted once per module into a tmp folder; then the folder is
compiled exactly as a target would (``cc -std=c99 -Wall -Wextra -Wpedantic -Werror -O2``, in
double and with ``-DPT_REAL_FLOAT``, with clang too when it is installed), the bare-metal example
(docs/examples/baremetal) is linked against it and run, and a shared build of it is loaded with
ctypes:

* ``PT_CONFIG`` holds ``pack(controller)`` and ``pack_supervisor(controller)`` bit for bit (and,
  in the float build, exactly their rounding to float32), the fail-safe duties and the file's
  sha256;
* the emitted controller, fed the readings of a deploy run on the simulated rig, writes the very
  duties the deploy runtime (the installed law behind the installed supervisor) wrote, bit for bit;
* bad input is exit status 2 with one ``error:`` line: an invalid controller.yaml (the line
  ``deploy`` itself prints), an out folder holding other files, an unknown fail-safe, a setting
  the C does not handle, a value float cannot hold.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import math
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rig_helpers import PAPER_YAML, TS

from pneutune.control.cli.common import run_cli
from pneutune.control.cli.deploy import main
from pneutune.control.contracts.controller import (
    DEAD_ZONE_MODES,
    ORIGINAL_DARC_ACCEL,
    POSITION_FEEDBACK,
    VARIANTS,
    ControllerConfig,
    load_controller,
)
from pneutune.control.errors import ConfigError, ExperimentError
from pneutune.control.law.cbuild import SOURCE_DIR
from pneutune.control.law.darc import STATE_SIZE
from pneutune.control.law.layout import CFG_SIZE, CFG_VARIANT, pack
from pneutune.control.rig import emit_c as ec
from pneutune.control.rig import supervisor_pack as sp
from pneutune.control.rig.deploy import deploy
from pneutune.control.rig.supervisor import FAIL_SAFE_MODES

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "examples" / "baremetal"
CC = shutil.which("cc")
CLANG = shutil.which("clang")
#: Exactly the line a target's build must pass without a warning.
STRICT = ("-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2")
COMPILERS = [c for c in (CC, CLANG) if c is not None]

needs_cc = pytest.mark.skipif(CC is None, reason="no cc on PATH: the emitted C cannot be built")


@pytest.fixture(scope="module")
def paper() -> ControllerConfig:
    return load_controller(PAPER_YAML)


@pytest.fixture(scope="module")
def emitted(tmp_path_factory: pytest.TempPathFactory) -> ec.EmitResult:
    """data/controller-paper.yaml emitted (double, fail-safe hold) into a fresh folder."""
    return ec.emit_c(PAPER_YAML, tmp_path_factory.mktemp("emit") / "axis1")


def _c_files(folder: Path) -> list[str]:
    return sorted(str(p) for p in folder.glob("*.c"))


def _cc(compiler: str, *args: str, cwd: Path) -> None:
    proc = subprocess.run([compiler, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr


@pytest.fixture(scope="module")
def shared(emitted: ec.EmitResult, tmp_path_factory: pytest.TempPathFactory
           ) -> dict[str, ctypes.CDLL]:
    """The emitted folder as shared libraries, double and float, loaded."""
    if CC is None:
        pytest.skip("no cc on PATH")
    folder = tmp_path_factory.mktemp("emit-shared")
    libs = {}
    for real, defs in (("double", ()), ("float", ("-DPT_REAL_FLOAT",))):
        lib = folder / f"libemitted-{real}.so"
        _cc(CC, *STRICT, "-fPIC", "-shared", *defs, "-o", str(lib), *_c_files(emitted.out),
            "-lm", cwd=folder)
        libs[real] = ctypes.CDLL(str(lib))
    return libs


def _config_type(real: str) -> type[ctypes.Structure]:
    t = ctypes.c_double if real == "double" else ctypes.c_float

    class CConfig(ctypes.Structure):
        _fields_ = [("law", t * CFG_SIZE), ("sup", t * sp.SUP_SIZE), ("fail_safe", t * 4),
                    ("sha256", ctypes.c_char_p), ("provenance", ctypes.c_char_p)]

    return CConfig


class CSensors(ctypes.Structure):
    _fields_ = [("x", ctypes.c_double), ("p_a", ctypes.c_double), ("p_b", ctypes.c_double),
                ("p_s", ctypes.c_double)]


class CReference(ctypes.Structure):
    _fields_ = [("x_r", ctypes.c_double), ("v_r", ctypes.c_double), ("a_r", ctypes.c_double)]


class CController(ctypes.Structure):
    _fields_ = [("law", ctypes.c_double * STATE_SIZE),
                ("sup", ctypes.c_double * sp.SUP_STATE_SIZE), ("status", ctypes.c_uint32)]


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        run_cli(main, argv)
    out, err = capsys.readouterr()
    return int(exc.value.code), out, err


# -- the folder ------------------------------------------------------------------------------


def test_folder_holds_the_sources_and_the_config(emitted: ec.EmitResult) -> None:
    """The sources and headers verbatim, the generated files, the file's sha256 in PT_CONFIG
    and in README.txt, the provenance line, nothing left beside the folder."""
    out = emitted.out
    assert sorted(p.name for p in out.iterdir()) == sorted(ec.FILES)
    for name in (*ec.SOURCES, *ec.HEADERS):
        assert (out / name).read_bytes() == (SOURCE_DIR / name).read_bytes(), name
    sha = hashlib.sha256(PAPER_YAML.read_bytes()).hexdigest()
    assert emitted.sha256 == sha
    config_c = (out / "pt_config.c").read_text(encoding="ascii")
    assert f'.sha256 = "{sha}",' in config_c
    assert sha in (out / "README.txt").read_text(encoding="ascii")
    assert "extern const pt_config_t PT_CONFIG;" in (out / "pt_config.h").read_text()
    assert emitted.provenance.startswith("controller-paper.yaml; variant modified_darc; "
                                         "fail-safe hold; no tune provenance")
    # every slot named from the layout tables, at its offset
    assert "/* [24] CFG_K1: k1 [1/s] */" in config_c
    assert "/* [107..618] CFG_PWM_DUTY:" in config_c
    assert "/* [21] SUP_START_TOL:" in config_c
    readme = (out / "README.txt").read_text(encoding="ascii")
    assert ec.BUILD_LINE in readme and "-DPT_REAL_FLOAT" in readme and "-lm" in readme
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no temporary folder left


@needs_cc
@pytest.mark.parametrize("compiler", COMPILERS, ids=lambda c: Path(c).name)
@pytest.mark.parametrize("real", ["double", "float"])
def test_strict_build_and_the_baremetal_example(emitted: ec.EmitResult, tmp_path: Path,
                                                compiler: str, real: str) -> None:
    """``cc -std=c99 -Wall -Wextra -Wpedantic -Werror -O2 -c *.c`` passes without a word (with
    -DPT_REAL_FLOAT too); the bare-metal example links against the objects and runs its 10 s
    loop on the stub I/O without a fault (exit 0)."""
    defs = ["-DPT_REAL_FLOAT"] if real == "float" else []
    _cc(compiler, *STRICT, *defs, "-c", *_c_files(emitted.out), cwd=tmp_path)
    objs = sorted(str(p) for p in tmp_path.glob("*.o"))
    assert sorted(Path(o).name for o in objs) == sorted(ec.BUILD_PRODUCTS[:-1])
    exe = tmp_path / "baremetal"
    _cc(compiler, *STRICT, *defs, "-I", str(emitted.out), "-I", str(EXAMPLE), "-o", str(exe),
        str(EXAMPLE / "main.c"), str(EXAMPLE / "stub_io.c"), *objs, "-lm", cwd=tmp_path)
    proc = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert emitted.sha256 in proc.stdout
    assert "2500 ticks of 4.0 ms, 2500 watchdog kicks" in proc.stdout


@pytest.mark.parametrize("real", ["double", "float"])
def test_config_is_pack_bit_for_bit(shared: dict[str, ctypes.CDLL], paper: ControllerConfig,
                                    emitted: ec.EmitResult, real: str) -> None:
    """PT_CONFIG read from the build: the law and supervisor vectors are pack() and
    pack_supervisor() bit for bit in double, their float32 rounding in float; the fail-safe
    duties, sha256 and provenance as emitted."""
    cfg = _config_type(real).in_dll(shared[real], "PT_CONFIG")
    dtype = np.float64 if real == "double" else np.float32
    law = np.ctypeslib.as_array(cfg.law).copy()
    sup = np.ctypeslib.as_array(cfg.sup).copy()
    want_law = pack(paper).astype(dtype)
    want_sup = sp.pack_supervisor(paper).astype(dtype)
    ints = np.int64 if real == "double" else np.int32
    np.testing.assert_array_equal(law.view(ints), want_law.view(ints))
    np.testing.assert_array_equal(sup.view(ints), want_sup.view(ints))
    assert list(cfg.fail_safe) == list(FAIL_SAFE_MODES["hold"])
    assert cfg.sha256.decode() == emitted.sha256
    assert cfg.provenance.decode() == emitted.provenance


def test_controller_reproduces_deploy_bit_for_bit(shared: dict[str, ctypes.CDLL],
                                                  emitted: ec.EmitResult) -> None:
    """The emitted controller (pt_controller_step on PT_CONFIG), fed the readings of a deploy
    run on the simulated rig, writes the duties the deploy runtime wrote, bit for bit, and
    raises nothing."""
    run = deploy(PAPER_YAML, rig="sim", scenarios="sine-0.5hz", duration=2.0, seed=1)
    res = run.runs[0].result
    assert res.fault is None and res.homing is None
    rec = res.loop.recording
    lib = shared["double"]
    vp = ctypes.c_void_p
    lib.pt_controller_init.argtypes = [vp, vp, vp]
    lib.pt_controller_step.argtypes = [vp, vp, vp, vp, ctypes.c_double, vp]
    lib.pt_controller_step.restype = ctypes.c_uint32
    cfg = _config_type("double").in_dll(lib, "PT_CONFIG")
    c = CController()
    assert lib.pt_controller_init(ctypes.byref(c), ctypes.byref(cfg), None) == 0
    duties = (ctypes.c_double * 4)()
    got = np.empty((rec.n, 4))
    for k in range(rec.n):
        s = CSensors(*rec.sensors_[k].tolist())
        r = CReference(*rec.reference_[k].tolist())
        st = lib.pt_controller_step(ctypes.byref(c), ctypes.byref(cfg), ctypes.byref(s),
                                    ctypes.byref(r), k * TS, duties)
        assert st == 0, (k, sp.status_codes(st))
        got[k] = list(duties)
    assert rec.n == 500
    np.testing.assert_array_equal(got.view(np.int64), rec.duties_.view(np.int64))


# -- the command -----------------------------------------------------------------------------


def test_cli_json_and_reemit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--json`` prints one object; a folder holding an earlier emit and the products of its
    Makefile is replaced (``make`` builds the library first); the exhaust fail-safe and
    --real float reach PT_CONFIG and the Makefile."""
    out = tmp_path / "axis1"
    code, stdout, _ = _run([str(PAPER_YAML), "--emit", "c", "--out", str(out), "--json"], capsys)
    assert code == 0
    summary = json.loads(stdout)
    assert summary["files"] == list(ec.FILES) and summary["out"] == str(out)
    assert summary["sha256"] == hashlib.sha256(PAPER_YAML.read_bytes()).hexdigest()
    if shutil.which("make") and CC is not None:
        proc = subprocess.run(["make", "-s"], cwd=out, capture_output=True, text=True,
                              timeout=120, check=False)
        assert proc.returncode == 0, proc.stderr
        assert (out / ec.LIBRARY).is_file()
    code, _, err = _run([str(PAPER_YAML), "--emit", "c", "--out", str(out),
                         "--fail-safe", "exhaust", "--real", "float"], capsys)
    assert code == 0, err
    assert f"wrote {out}/" in err and "-DPT_REAL_FLOAT -c" in err
    assert sorted(p.name for p in out.iterdir()) == sorted(ec.FILES)  # build products gone
    text = (out / "pt_config.c").read_text()
    assert ".fail_safe = {PT_V(0.0), PT_V(1.0), PT_V(0.0), PT_V(1.0)}," in text
    assert "PT_DEFS = -DPT_REAL_FLOAT" in (out / "Makefile").read_text()
    assert [p.name for p in tmp_path.iterdir()] == ["axis1"]


def test_invalid_controller_is_refused_as_deploy_refuses_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An invalid controller.yaml: exit 2 and the very `error:` line deploy prints (the file and
    the key); nothing written."""
    d = yaml.safe_load(PAPER_YAML.read_text(encoding="utf-8"))
    d["gains"]["k1"] = -65.0
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(d), encoding="utf-8")
    out = tmp_path / "axis1"
    code, stdout, err = _run([str(bad), "--emit", "c", "--out", str(out)], capsys)
    assert code == 2 and stdout == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert str(bad) in lines[0] and "gains.k1" in lines[0]
    assert not out.exists()
    code, _, deploy_err = _run([str(bad)], capsys)
    assert code == 2 and deploy_err == err


def test_foreign_out_folder_is_refused(tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """An out folder holding a file an emit did not write (or a subfolder), or a file as out:
    exit 2 naming --out and what is there; nothing touched."""
    out = tmp_path / "axis1"
    out.mkdir()
    (out / "ptlaw.c").write_text("/* mine */\n")
    (out / "notes.txt").write_text("keep me\n")
    code, _, err = _run([str(PAPER_YAML), "--emit", "c", "--out", str(out)], capsys)
    assert code == 2
    assert err.startswith("error: --out ") and "notes.txt" in err and err.count("\n") == 1
    assert (out / "notes.txt").read_text() == "keep me\n"
    assert (out / "ptlaw.c").read_text() == "/* mine */\n"
    (out / "notes.txt").unlink()
    (out / "sub").mkdir()
    assert _run([str(PAPER_YAML), "--emit", "c", "--out", str(out)], capsys)[0] == 2
    afile = tmp_path / "file"
    afile.write_text("x")
    code, _, err = _run([str(PAPER_YAML), "--emit", "c", "--out", str(afile)], capsys)
    assert code == 2 and "not a folder" in err
    # an empty folder is fine
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _run([str(PAPER_YAML), "--emit", "c", "--out", str(empty)], capsys)[0] == 0
    assert sorted(p.name for p in empty.iterdir()) == sorted(ec.FILES)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["axis1", "empty", "file"]


@pytest.mark.parametrize("argv, words", [
    (["--fail-safe", "vent"], ("--fail-safe", "invalid choice")),
    (["--real", "half"], ("--real", "invalid choice")),
    (["--scenario", "all"], ("--scenario", "does not apply")),
    (["--rig", "pipe-sim"], ("--rig", "does not apply")),
], ids=["fail-safe", "real", "scenario", "rig"])
def test_bad_flags(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                   words: tuple[str, ...]) -> None:
    """Unknown choices (argparse) and flags of a run: exit 2, one error line, nothing written."""
    out = tmp_path / "axis1"
    code, _, err = _run([str(PAPER_YAML), "--emit", "c", "--out", str(out), *argv], capsys)
    assert code == 2 and err.count("\n") == 1
    assert all(w in err for w in words), err
    assert not out.exists()


def test_emit_needs_out_and_out_needs_emit(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run([str(PAPER_YAML), "--emit", "c"], capsys)
    assert code == 2 and "--out" in err
    code, _, err = _run([str(PAPER_YAML), "--out", str(tmp_path / "x")], capsys)
    assert code == 2 and "--emit c" in err


def test_library_arguments(paper: ControllerConfig, tmp_path: Path) -> None:
    """The library names its arguments; an in-memory config is hashed over its canonical JSON
    (as deploy logs it)."""
    with pytest.raises(ExperimentError, match="fail_safe must be one of"):
        ec.emit_c(paper, tmp_path / "a", fail_safe="vent")
    with pytest.raises(ExperimentError, match="real must be one of"):
        ec.emit_c(paper, tmp_path / "a", real="half")
    with pytest.raises(ExperimentError, match="controller must be"):
        ec.emit_c(42, tmp_path / "a")  # type: ignore[arg-type]
    res = ec.emit_c(paper, tmp_path / "a")
    text = json.dumps(paper.to_dict(), sort_keys=True)
    assert res.sha256 == hashlib.sha256(text.encode()).hexdigest()
    assert res.controller == "<controller>" and res.provenance.startswith("<controller>;")


# -- what the C supports ---------------------------------------------------------------------


def _variant(paper: ControllerConfig, **update: Any) -> ControllerConfig:
    return paper.model_copy(update=update)


def test_the_c_runs_every_setting_of_contract_4(paper: ControllerConfig, tmp_path: Path) -> None:
    """Every variant, position feedback, original_darc acceleration and dead-zone mode of
    contract 4 is one the C handles: each emits."""
    layout_h = (SOURCE_DIR / "pt_layout.h").read_text()
    law_c = (SOURCE_DIR / "ptlaw.c").read_text()
    for variant in VARIANTS:
        for fb in POSITION_FEEDBACK:
            for accel in ORIGINAL_DARC_ACCEL:
                for dz in DEAD_ZONE_MODES:
                    cfg = _variant(paper, variant=variant, position_feedback=fb,
                                   original_darc_accel=accel, dead_zone=dz)
                    assert ec.c_support(pack(cfg), layout_h, law_c) == [], cfg
    for variant in VARIANTS:
        res = ec.emit_c(_variant(paper, variant=variant, dead_zone="dither"),
                        tmp_path / variant)
        assert f"variant {variant}" in res.provenance


def test_a_setting_the_c_does_not_handle_is_refused(
        paper: ControllerConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A code pt_layout.h does not define, or one ptlaw.c does not handle (here: a copy of the
    C sources whose law lost its dither branch), is a ConfigError naming the key: exit 2."""
    layout_h = (SOURCE_DIR / "pt_layout.h").read_text()
    law_c = (SOURCE_DIR / "ptlaw.c").read_text()
    vec = pack(paper)
    vec[CFG_VARIANT] = 7.0
    [(key, rule)] = ec.c_support(vec, layout_h, law_c)
    assert key == "variant" and "pt_layout.h defines no such code" in rule
    crippled = tmp_path / "c"
    shutil.copytree(SOURCE_DIR, crippled)
    text = (crippled / "ptlaw.c").read_text().replace("== PT_DZ_DITHER", "== 12345")
    (crippled / "ptlaw.c").write_text(text)
    monkeypatch.setattr(ec, "SOURCE_DIR", crippled)
    dither = tmp_path / "dither.yaml"
    d = yaml.safe_load(PAPER_YAML.read_text(encoding="utf-8"))
    d["dead_zone"] = "dither"
    dither.write_text(yaml.safe_dump(d), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"dead_zone: 'dither'.*ptlaw\.c does not handle it"):
        ec.emit_c(dither, tmp_path / "out")
    code, _, err = _run([str(dither), "--emit", "c", "--out", str(tmp_path / "out")], capsys)
    assert code == 2 and f"{dither}: dead_zone:" in err
    assert not (tmp_path / "out").exists()
    # the up mode, code 0, is the branch the C takes when no test matches: still runs
    ec.emit_c(PAPER_YAML, tmp_path / "out")


def test_float_refuses_what_a_float_cannot_hold(paper: ControllerConfig, tmp_path: Path) -> None:
    """A value that is 0 or subnormal in single precision (a valve C of 1e-40 m^3/(s Pa),
    valid in contract 4) is refused for float, naming the slot; double emits it."""
    valves = paper.valves.model_copy(update={
        "b_in": paper.valves.b_in.model_copy(update={"C": 1.0e-40})})
    cfg = _variant(paper, valves=valves)
    with pytest.raises(ExperimentError, match=r"real 'float' cannot hold CFG_VALVE_C\[2\] = "
                                              r"1e-40 .*underflows"):
        ec.emit_c(cfg, tmp_path / "f", real="float")
    assert not (tmp_path / "f").exists()
    ec.emit_c(cfg, tmp_path / "d")
    assert f" PT_V({1e-40:.17g}), " in (tmp_path / "d" / "pt_config.c").read_text()


def test_literals_read_back() -> None:
    """%.17g reads back as the same double, integers get a point, infinities HUGE_VAL."""
    rng = np.random.default_rng(1)
    for v in [0.0, -0.0, 1.0, 1e300, 5e-324, 0.1, 1114107.0, *rng.standard_normal(200) * 1e3]:
        lit = ec._c_literal(float(v))
        assert float(lit) == v and math.copysign(1.0, float(lit)) == math.copysign(1.0, v)
        assert any(c in lit for c in ".e")
    assert ec._c_literal(math.inf) == "HUGE_VAL" and ec._c_literal(-math.inf) == "-HUGE_VAL"
