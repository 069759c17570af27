"""``emit_c(controller, out)``: a controller as the C99 folder a target compiles.

``deploy --emit c`` is this function at the command line.

A PLC or a microcontroller runs the controller that ``deploy`` runs, with no Python and no YAML
parser: the law (``ptlaw.c``), the safety supervisor (``pt_supervisor.c``) and the controller API
around both (``pt_controller.c``), the very sources the install compiles, and one generated
translation unit, ``pt_config.c``, holding the controller as a ``const pt_config_t PT_CONFIG``:

* ``law``: :func:`pneutune.control.law.layout.pack` of the controller, slot by slot, each slot
  named in a comment from :data:`~pneutune.control.law.layout.SLOTS`;
* ``sup``: :func:`pneutune.control.rig.supervisor_pack.pack_supervisor` (the thresholds of the
  deploy runtime's supervisor, its start tolerance included), named from
  :data:`~pneutune.control.rig.supervisor_pack.SUP_SLOTS`;
* ``fail_safe``: the duties of the fail-safe mode
  (:data:`~pneutune.control.rig.supervisor.FAIL_SAFE_MODES`);
* ``sha256``: the controller.yaml's sha256 (its bytes; for a config given in memory, the sha256
  of its canonical JSON, as ``deploy`` logs it), and a one-line ``provenance``.

Every value is printed with ``%.17g``, which reads back as the same double: a double build holds
``pack(controller)`` bit for bit, and a float build (``-DPT_REAL_FLOAT``) rounds each value once
to the nearest float, as ``numpy.float32`` does. The folder also gets a ``Makefile`` and a
``README.txt`` with the one build line, ``cc -std=c99 -O2 -c *.c``, linked with ``-lm``.

Checks, each a :class:`~pneutune.control.errors.PneutuneError` (exit status 2 at the command
line), before anything is written:

* the controller validates exactly as ``deploy`` loads it
  (:func:`~pneutune.control.contracts.controller.load_controller`);
* the C can run it: the copied layout headers are what the installed Python generates
  (:func:`~pneutune.control.law.c_header.layout_header`,
  :func:`~pneutune.control.rig.supervisor_pack.sup_layout_header`), and each enum code of the
  packed vector (variant, position feedback, original_darc acceleration, dead-zone mode) is one
  ``pt_layout.h`` defines and ``ptlaw.c`` handles (:func:`c_support`);
* with ``real="float"``, every value is representable in single precision;
* ``fail_safe`` and ``real`` are known;
* ``out`` is new, empty, or holds only what an earlier emit put there (its files and the build
  products of its Makefile); anything else is refused, nothing is deleted.

The folder is written atomically where the file system allows: into a temporary folder beside
``out``, then renamed onto it (a previous emit is moved aside first and removed after).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pneutune.control.constants import VERSION
from pneutune.control.contracts.controller import (
    DEAD_ZONE_MODES,
    ORIGINAL_DARC_ACCEL,
    POSITION_FEEDBACK,
    VARIANTS,
    ControllerConfig,
)
from pneutune.control.errors import ConfigError, ExperimentError, argument_error
from pneutune.control.law import c_header
from pneutune.control.law.cbuild import REALS, SOURCE_DIR
from pneutune.control.law.layout import (
    CFG_DZ_MODE,
    CFG_ORIG_ACCEL,
    CFG_POS_FB,
    CFG_SIZE,
    CFG_VARIANT,
    SLOTS,
    pack,
)

from . import supervisor_pack as sp
from .deploy import controller_source
from .supervisor import FAIL_SAFE_MODES

#: The C sources a target compiles, copied from :data:`~pneutune.control.law.cbuild.SOURCE_DIR`.
SOURCES: tuple[str, ...] = ("ptlaw.c", "pt_supervisor.c", "pt_controller.c")
#: Their headers (the two layouts are generated from the Python tables).
HEADERS: tuple[str, ...] = ("ptlaw.h", "pt_layout.h", "pt_supervisor.h", "pt_sup_layout.h",
                            "pt_controller.h")
#: What the emitter generates.
GENERATED: tuple[str, ...] = ("pt_config.h", "pt_config.c", "Makefile", "README.txt")
#: Every file of an emitted folder.
FILES: tuple[str, ...] = (*SOURCES, *HEADERS, *GENERATED)
#: The static library the Makefile builds.
LIBRARY = "libptcontroller.a"
#: What the Makefile leaves in the folder; a folder holding only these and :data:`FILES` is an
#: earlier emit, which a new one replaces.
BUILD_PRODUCTS: tuple[str, ...] = (*(Path(s).with_suffix(".o").name for s in
                                     (*SOURCES, "pt_config.c")), LIBRARY)
#: Output formats of ``deploy --emit``.
EMIT_FORMATS: tuple[str, ...] = ("c",)
#: The one documented build line (README.txt, docs/embedded.md).
BUILD_LINE = "cc -std=c99 -O2 -c *.c"
#: And the link of a program ``app.o`` with it.
LINK_LINE = "cc -o app app.o " + " ".join(BUILD_PRODUCTS[:-1]) + " -lm"

#: The enum slots of the packed law vector: (slot, name in SLOTS, C macro prefix,
#: controller.yaml key, names in code order).
_ENUM_SLOTS: tuple[tuple[int, str, str, str, tuple[str, ...]], ...] = (
    (CFG_VARIANT, "CFG_VARIANT", "PT_VARIANT_", "variant", VARIANTS),
    (CFG_POS_FB, "CFG_POS_FB", "PT_POS_FB_", "position_feedback", POSITION_FEEDBACK),
    (CFG_ORIG_ACCEL, "CFG_ORIG_ACCEL", "PT_ORIG_ACCEL_", "original_darc_accel",
     ORIGINAL_DARC_ACCEL),
    (CFG_DZ_MODE, "CFG_DZ_MODE", "PT_DZ_", "dead_zone", DEAD_ZONE_MODES),
)


@dataclass(frozen=True, repr=False)
class EmitResult:
    """What :func:`emit_c` wrote.

    Attributes
    ----------
    out : Path
        The folder.
    files : tuple of str
        The files in it (:data:`FILES`).
    controller : str
        The controller's file, or ``<controller>`` for one given in memory.
    sha256 : str
        The sha256 written into ``PT_CONFIG.sha256``.
    variant : str
    fail_safe : str
        The fail-safe mode (``hold`` or ``exhaust``).
    real : str
        The precision the Makefile builds by default (``double`` or ``float``); the sources
        build either way (``-DPT_REAL_FLOAT``).
    provenance : str
        ``PT_CONFIG.provenance``.
    """

    out: Path
    files: tuple[str, ...]
    controller: str
    sha256: str
    variant: str
    fail_safe: str
    real: str
    provenance: str

    @property
    def build_line(self) -> str:
        """The compile line of README.txt for this precision."""
        return BUILD_LINE.replace(" -c", " -DPT_REAL_FLOAT -c") if self.real == "float" \
            else BUILD_LINE

    def summary(self) -> dict[str, Any]:
        """The object ``deploy --emit c --json`` prints."""
        return {"emit": "c", "out": str(self.out), "files": list(self.files),
                "controller": self.controller, "sha256": self.sha256, "variant": self.variant,
                "fail_safe": self.fail_safe, "real": self.real, "provenance": self.provenance,
                "build": {"compile": self.build_line, "link": LINK_LINE}}

    def __repr__(self) -> str:
        return (f"EmitResult(out={str(self.out)!r}, controller={self.controller!r} "
                f"({self.variant}), fail_safe={self.fail_safe!r}, real={self.real!r}, "
                f"sha256={self.sha256[:12]}…, {len(self.files)} files)")


# -- checks ---------------------------------------------------------------------------------


def _strip_comments(c_text: str) -> str:
    return re.sub(r"/\*.*?\*/", " ", c_text, flags=re.DOTALL)


def c_support(law: np.ndarray, layout_h: str, law_c: str) -> list[tuple[str, str]]:
    """What of a packed law vector the C cannot run.

    Each enum slot (:data:`_ENUM_SLOTS`) must hold a code that ``pt_layout.h`` defines (as
    ``PT_<PREFIX><NAME>``) and that ``ptlaw.c`` handles: its code tests the macro, or the code
    is 0, the branch the C takes when no test matches (``measured``, ``filtered``, ``up``).
    A variant code of no test would run a law with no dF_pd term, silently.

    Parameters
    ----------
    law : (CFG_SIZE,) float64
        :func:`~pneutune.control.law.layout.pack` of the controller.
    layout_h, law_c : str
        The text of ``pt_layout.h`` and of ``ptlaw.c``.

    Returns
    -------
    list of (key, rule)
        The controller.yaml key and what is wrong with it; empty when the C runs it all.
    """
    code_text = _strip_comments(law_c)
    problems: list[tuple[str, str]] = []
    for slot, slot_name, prefix, key, names in _ENUM_SLOTS:
        defined = {int(v): n for n, v in re.findall(
            rf"^#define ({prefix}[A-Z0-9_]+) (\d+)\s*(?:/\*.*)?$", layout_h, flags=re.MULTILINE)}
        handled = {v: n for v, n in defined.items()
                   if v == 0 or re.search(rf"\b{n}\b", code_text)}
        value = float(law[slot])
        code = int(value) if math.isfinite(value) and value == int(value) else None
        known = ", ".join(names[v] if v < len(names) else n for v, n in sorted(handled.items()))
        shown = (repr(names[code]) if code is not None and 0 <= code < len(names)
                 else "the value")
        if code not in handled:
            where = ("ptlaw.c does not handle it" if code in defined
                     else "pt_layout.h defines no such code")
            problems.append((key, f"{shown} (code {value!r} in {slot_name}) cannot run on "
                                  f"the C law: {where}; it runs {known}"))
    return problems


def _check_layouts() -> None:
    """The C headers in SOURCE_DIR are what the installed Python tables generate."""
    for name, text in (("pt_layout.h", c_header.layout_header()),
                       ("pt_sup_layout.h", sp.sup_layout_header())):
        path = SOURCE_DIR / name
        current = path.read_text(encoding="ascii") if path.is_file() else None
        if current != text:
            raise ExperimentError(f"{path} is {'missing' if current is None else 'out of date'}"
                                  f": the C sources do not match the installed pneutune's "
                                  f"layout (reinstall pneutune)")


def _slot_names(slots: tuple[tuple[str, int, str], ...]) -> list[str]:
    out = []
    for name, width, _ in slots:
        out += [name] if width == 1 else [f"{name}[{i}]" for i in range(width)]
    return out


def _check_float(law: np.ndarray, sup: np.ndarray, name: str) -> None:
    """Every finite non-zero double must round to a finite, normal float (a subnormal loses
    digits, and many single-precision FPUs flush it to zero)."""
    tiny = float(np.finfo(np.float32).tiny)
    for vec, slots in ((law, SLOTS), (sup, sp.SUP_SLOTS)):
        with np.errstate(over="ignore", under="ignore"):
            f32 = vec.astype(np.float32)
        mag = np.abs(f32.astype(np.float64))
        bad = np.isfinite(vec) & (vec != 0.0) & ~(np.isfinite(mag) & (mag >= tiny))
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            what = "overflows" if not np.isfinite(f32[i]) else "underflows"
            raise argument_error(ExperimentError, "real", f"'float' cannot hold "
                                 f"{_slot_names(slots)[i]} = {float(vec[i])!r} of {name} (it "
                                 f"{what} in single precision): emit for double")


def _check_out(out: Path) -> bool:
    """Whether ``out`` exists (then holding only an earlier emit); raises for anything else."""
    if out.resolve() == SOURCE_DIR.resolve():
        raise argument_error(ExperimentError, "out", f"{out} is pneutune's own C sources")
    if not out.exists() and not out.is_symlink():
        return False
    if not out.is_dir() or out.is_symlink():
        raise argument_error(ExperimentError, "out", f"{out} exists and is not a folder")
    allowed = {*FILES, *BUILD_PRODUCTS}
    foreign = sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir()
                     if p.name not in allowed or not p.is_file() or p.is_symlink())
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5
                                          else "")
        raise argument_error(ExperimentError, "out", f"{out} holds files an emit did not write "
                             f"({shown}): give a new or empty folder (one holding only an "
                             f"earlier emit, and its build products, is replaced)")
    return True


# -- the generated files --------------------------------------------------------------------


def _ascii(text: str) -> str:
    """``text`` for a C comment or string: ASCII, Greek letters spelt out, no ``*/``, no ``??``
    (which could start a trigraph)."""
    out = c_header.ascii_comment(text)
    while "??" in out:
        out = out.replace("??", "?_?")
    return out


def _c_string(text: str) -> str:
    """A C string literal of ``text`` (printable ASCII; no trigraph can form)."""
    body = "".join(ch if " " <= ch <= "~" else "?" for ch in _ascii(text))
    body = body.replace("\\", "\\\\").replace('"', '\\"').replace("?", "\\?")
    return f'"{body}"'


def _c_literal(value: float) -> str:
    """A C double constant that reads back as exactly ``value`` (``%.17g``)."""
    if math.isnan(value):
        raise ValueError("a NaN cannot be emitted")
    if math.isinf(value):
        return "HUGE_VAL" if value > 0 else "-HUGE_VAL"
    text = f"{value:.17g}"
    if float(text) != value:  # pragma: no cover - %.17g always round-trips a double
        raise RuntimeError(f"{value!r} printed as {text} does not read back")
    return text if any(c in text for c in ".e") else text + ".0"


def _vector_lines(vec: np.ndarray, slots: tuple[tuple[str, int, str], ...],
                  indent: str = "        ") -> list[str]:
    """Initialiser lines of a packed vector: every slot with its offset, name and meaning."""
    lines: list[str] = []
    at = 0
    for name, width, meaning in slots:
        values = [f"PT_V({_c_literal(float(v))})" for v in vec[at:at + width]]
        if width == 1:
            lines.append(f"{indent}{values[0]}, /* [{at}] {name}: {_ascii(meaning)} */")
        else:
            lines.append(f"{indent}/* [{at}..{at + width - 1}] {name}: {_ascii(meaning)} */")
            for i in range(0, width, 4):
                chunk = values[i:i + 4]
                lines.append(f"{indent}{', '.join(chunk)}, /* {name}[{i}"
                             f"{f'..{i + len(chunk) - 1}' if len(chunk) > 1 else ''}] */")
        at += width
    if at != vec.size:  # pragma: no cover - the tables define the sizes
        raise RuntimeError(f"slots cover {at} values of a vector of {vec.size}")
    return lines


def _provenance(cfg: ControllerConfig, name: str, fail_safe: str) -> str:
    """One line: the file, variant, fail-safe and tune provenance, and the emitter."""
    parts = [Path(name).name if name != "<controller>" else name, f"variant {cfg.variant}",
             f"fail-safe {fail_safe}"]
    p = cfg.provenance
    tuned = [] if p is None else [f"{k} {getattr(p, k)}" for k in ("study", "trial", "created")
                                  if getattr(p, k) is not None]
    parts.append("tune " + ", ".join(tuned) if tuned else "no tune provenance")
    parts.append(f"pneutune {VERSION}")
    return "; ".join(parts)


def _config_h(name: str, sha: str) -> str:
    return f"""\
/* pt_config.h: the deployed controller PT_CONFIG, generated by `deploy --emit c` from
 * {_ascii(Path(name).name)}; do not edit, emit again.
 * sha256 {sha}
 *
 * Pass &PT_CONFIG to pt_controller_init, pt_controller_step and pt_controller_trip
 * (pt_controller.h). Build: {BUILD_LINE} (README.txt).
 */
#ifndef PT_CONFIG_H
#define PT_CONFIG_H

#include "pt_controller.h"

#ifdef __cplusplus
extern "C" {{
#endif

/* The controller: law and supervisor vectors, fail-safe duties, sha256, provenance. */
extern const pt_config_t PT_CONFIG;

#ifdef __cplusplus
}}
#endif

#endif /* PT_CONFIG_H */
"""


def _config_c(law: np.ndarray, sup: np.ndarray, fail_safe: str, name: str, sha: str,
              provenance: str) -> str:
    duties = [f"PT_V({_c_literal(v)})" for v in FAIL_SAFE_MODES[fail_safe]]
    needs_math = not (np.all(np.isfinite(law)) and np.all(np.isfinite(sup)))
    lines = [
        "/* pt_config.c: the deployed controller (pt_config.h), generated by `deploy --emit c`",
        f" * from {_ascii(Path(name).name)}; do not edit, emit again.",
        " *",
        " * law: pneutune.control.law.layout.pack(controller), slot by slot (pt_layout.h);",
        " * sup: pneutune.control.rig.supervisor_pack.pack_supervisor(controller), the deploy",
        " *      runtime's thresholds (pt_sup_layout.h).",
        " * Each value is printed with %.17g and reads back as the same double; a float build",
        " * (-DPT_REAL_FLOAT) rounds each once to the nearest float (PT_V: the explicit cast).",
        " */",
        *(["#include <math.h>", ""] if needs_math else []),
        '#include "pt_config.h"',
        "",
        f"#if PT_CFG_SIZE != {law.size} || PT_SUP_SIZE != {sup.size}",
        '#error "pt_config.c was emitted for another layout than pt_layout.h, pt_sup_layout.h"',
        "#endif",
        "",
        "#define PT_V(x) ((pt_real)(x))",
        "",
        "const pt_config_t PT_CONFIG = {",
        "    .law = {",
        *_vector_lines(law, SLOTS),
        "    },",
        "    .sup = {",
        *_vector_lines(sup, sp.SUP_SLOTS),
        "    },",
        f"    /* fail-safe {fail_safe}: a_in, a_out, b_in, b_out */",
        f"    .fail_safe = {{{', '.join(duties)}}},",
        f"    .sha256 = {_c_string(sha)},",
        f"    .provenance = {_c_string(provenance)},",
        "};",
        "",
        "#undef PT_V",
        "",
    ]
    return "\n".join(lines)


def _makefile(name: str, real: str) -> str:
    objs = " ".join(BUILD_PRODUCTS[:-1])
    rules = "\n".join(f"{Path(c).with_suffix('.o').name}: {c} $(HEADERS)\n"
                      f"\t$(CC) $(CFLAGS) $(PT_DEFS) -c {c}\n"
                      for c in (*SOURCES, "pt_config.c"))
    return f"""\
# Makefile of the pneutune controller emitted from {_ascii(Path(name).name)} by `deploy --emit c`.
# `make` builds {LIBRARY}; link it into the target program with the math library:
#     cc -o app main.o {LIBRARY} -lm
# The same without make: {BUILD_LINE}, then link the objects with -lm (README.txt).
# Precision: PT_DEFS = -DPT_REAL_FLOAT builds in float (`make PT_DEFS=-DPT_REAL_FLOAT`), empty
# in double; build every file the same way.

CC = cc
CFLAGS = -std=c99 -O2
PT_DEFS ={" -DPT_REAL_FLOAT" if real == "float" else ""}
AR = ar
OBJS = {objs}
HEADERS = {" ".join(("pt_config.h", *HEADERS))}

{LIBRARY}: $(OBJS)
\t$(AR) rcs {LIBRARY} $(OBJS)

{rules}
clean:
\trm -f $(OBJS) {LIBRARY}
"""


def _readme(result: EmitResult, law_size: int, sup_size: int, start_tol: float) -> str:
    start = (f"{start_tol * 1e3:g} mm" if math.isfinite(start_tol) else "any distance")
    emitted_for = ("; this folder was emitted for float: its Makefile builds float by default"
                   if result.real == "float" else "")
    return f"""\
pneutune controller for a target (PLC, microcontroller), emitted by `deploy --emit c`

controller  {_ascii(result.controller)}
sha256      {result.sha256}
provenance  {_ascii(result.provenance)}
fail-safe   {result.fail_safe} (duties written on a fault: a_in, a_out, b_in, b_out)

Build (C99, no other library than libm; no dynamic memory, no recursion, no YAML parser):

    {BUILD_LINE}
    {LINK_LINE}

-DPT_REAL_FLOAT on the first line builds in float instead of double (a target without a
double FPU). Build every file with the same flags: the precision is part of every function's
arguments. `make` does the same into {LIBRARY} (`make PT_DEFS=-DPT_REAL_FLOAT` for
float{emitted_for}). Keep -std=c99 (or pass -ffp-contract=off with -std=gnu*) and never
-ffast-math: the double build then computes exactly what pneutune's deploy runtime computes.

Files
    ptlaw.c/.h            the control law (modified DARC and its variants)
    pt_supervisor.c/.h    the safety supervisor (faults and warnings of deploy)
    pt_controller.c/.h    the API a timer interrupt calls
    pt_layout.h           slots of the law's vectors (generated, do not edit)
    pt_sup_layout.h       slots of the supervisor's vectors, status bits (generated)
    pt_config.h/.c        PT_CONFIG: this controller ({law_size} + {sup_size} values, do not edit)

Every Ts (rig.Ts of the controller) from the timer interrupt:

    static pt_controller_t ctl;                    /* pt_controller_init(&ctl, &PT_CONFIG, NULL) */
    pt_sensors_t s = {{x, p_a, p_b, p_s}};          /* m, Pa abs */
    pt_reference_t r = {{x_r, v_r, a_r}};           /* m, m/s, m/s^2 */
    pt_real d[4];
    uint32_t st = pt_controller_step(&ctl, &PT_CONFIG, &s, &r, k * Ts, d);
    write the four duties d[0..3] (a_in, a_out, b_in, b_out) to the valves' PWM;
    st & PT_FAULT_MASK: latched fault, d is the fail-safe from now on (pt_fault_name);
    st & PT_WARN_MASK:  run identify again (the run goes on).

A sensor read or a valve write that failed: pt_controller_trip(&ctl, &PT_CONFIG,
PT_FAULT_RIG_IO, d). The first sample must be within {start} of x_r(0) (else the fault
start_position): move the piston there first, or start the reference at the first reading.
The watchdog that cuts the coil power, and the relief valve, remain the installation's.
pneutune's docs/embedded.md has the details: the call sequence, the memory, the numerics and a
bare-metal example (docs/examples/baremetal).
"""


# -- writing --------------------------------------------------------------------------------


def _write(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _install(tmp: Path, out: Path, existed: bool) -> None:
    """Rename the finished ``tmp`` onto ``out`` (an earlier emit moved aside first)."""
    if not existed:
        os.replace(tmp, out)  # one atomic rename
        return
    if not any(out.iterdir()):
        with contextlib.suppress(OSError):  # onto an empty folder: atomic where allowed
            os.replace(tmp, out)
            return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
    os.rmdir(old)
    os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


def emit_c(controller: ControllerConfig | str | os.PathLike[str], out: str | os.PathLike[str],
           fail_safe: str = "hold", real: str = "double") -> EmitResult:
    """Write a controller as the C99 folder a target compiles (module docstring).

    Parameters
    ----------
    controller : ControllerConfig or path-like
        controller.yaml (contract 4) or the config itself.
    out : path-like
        The folder to write: new, empty, or an earlier emit (replaced). Its parent is made if
        missing.
    fail_safe : str
        Valve state on a fault, as ``deploy --fail-safe``: ``hold`` (all closed) or
        ``exhaust``.
    real : str
        ``double`` or ``float``: the precision the Makefile builds by default (``PT_DEFS``);
        ``float`` also checks that every value survives single precision. The sources build in
        either precision whatever this says (``-DPT_REAL_FLOAT``).

    Returns
    -------
    EmitResult

    Raises
    ------
    ConfigError
        An invalid controller.yaml (as ``deploy`` refuses it), or a setting the C law cannot
        run, naming the file and the key.
    ExperimentError
        An unknown ``fail_safe`` or ``real``, a value ``float`` cannot hold, C sources out of
        date with the installed pneutune, or an ``out`` that exists and holds anything but an
        earlier emit.
    """
    if fail_safe not in FAIL_SAFE_MODES:
        raise argument_error(ExperimentError, "fail_safe", "must be one of "
                             f"{', '.join(sorted(FAIL_SAFE_MODES))}, got {fail_safe!r}")
    if real not in REALS:
        raise argument_error(ExperimentError, "real", f"must be one of {', '.join(REALS)}, "
                             f"got {real!r}")
    cfg, name, sha = controller_source(controller)
    _check_layouts()
    law = pack(cfg)
    sup = sp.pack_supervisor(cfg)
    if law.size != CFG_SIZE:  # pragma: no cover - pack writes CFG_SIZE values
        raise RuntimeError(f"pack gave {law.size} values, the layout has {CFG_SIZE}")
    layout_h = (SOURCE_DIR / "pt_layout.h").read_text(encoding="ascii")
    law_c = (SOURCE_DIR / "ptlaw.c").read_text(encoding="ascii")
    problems = c_support(law, layout_h, law_c)
    if problems:
        key, rule = problems[0]
        raise ConfigError(name, key, rule)
    if real == "float":
        _check_float(law, sup, name)
    target = Path(out)
    existed = _check_out(target)

    provenance = _provenance(cfg, name, fail_safe)
    result = EmitResult(target, FILES, name, sha, cfg.variant, fail_safe, real, provenance)
    generated = {
        "pt_config.h": _config_h(name, sha),
        "pt_config.c": _config_c(law, sup, fail_safe, name, sha, provenance),
        "Makefile": _makefile(name, real),
        "README.txt": _readme(result, law.size, sup.size, float(sup[sp.SUP_START_TOL])),
    }
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700; a normal folder honours umask
        for f in (*SOURCES, *HEADERS):
            _write(tmp / f, (SOURCE_DIR / f).read_bytes())
        for f, text in generated.items():
            _write(tmp / f, text.encode("ascii"))
        for f in FILES:
            os.chmod(tmp / f, 0o666 & ~_umask())
        _install(tmp, target, existed)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return result


__all__ = ["BUILD_LINE", "BUILD_PRODUCTS", "EMIT_FORMATS", "FILES", "GENERATED", "HEADERS",
           "LIBRARY", "LINK_LINE", "SOURCES", "EmitResult", "c_support", "emit_c"]
