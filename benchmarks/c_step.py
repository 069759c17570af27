"""Step time of the emitted C controller (``deploy --emit c``), and its instruction count.

Emits the controller (default the paper's) into a temporary folder, builds it with the one
documented line (``cc -std=c99 -O2 -c *.c``, ``-DPT_REAL_FLOAT`` for float) and links a small
timing driver against it. The driver replays a recorded closed-loop sensor sequence, the
readings and reference of a deploy run on the simulated rig (sine-0.5hz, 12 s = 3000 samples,
seed 1), through ``pt_controller_init`` and ``pt_controller_step``, ``--passes`` times per run,
and reports the time per step of each run (the whole pass timed, divided by its steps) and the
distribution of single steps (each step timed alone, the clock's own cost included). It checks
that no step raised a fault and that every run wrote the same duties.

Prints, per precision: ns/step, median and range over ``--runs`` runs; single-step p50, p99 and
max. With ``--callgrind`` (valgrind installed): the instructions executed per call of
``pt_controller_step`` (everything it calls included, libm's atan and sqrt too), counted by
``valgrind --tool=callgrind --toggle-collect=pt_controller_step`` on one pass, and the
floating-point instructions among them executed in the emitted code (mapped from callgrind's
per-instruction counts to ``objdump``'s mnemonics; libm's are counted as calls).

Figures, not assertions; they depend on the machine, the compiler and the load.

    .venv/bin/python benchmarks/c_step.py [--runs 7] [--passes 10] [--real both] [--callgrind]
"""

from __future__ import annotations

import argparse
import re
import shutil
import statistics
import subprocess
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: The timing driver: reads the sequence (x, p_a, p_b, p_s, x_r, v_r, a_r per sample, float64),
#: runs the passes, prints "pass_ns <ns per step>" per pass, "step_ns p50 p99 max" and a checksum.
DRIVER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "pt_config.h"

#define MAX_SAMPLES 100000

static double seq[MAX_SAMPLES][7];
static pt_controller_t ctl;
static uint32_t step_ns[MAX_SAMPLES];

static uint64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static int cmp_u32(const void *a, const void *b)
{
    uint32_t x = *(const uint32_t *)a, y = *(const uint32_t *)b;
    return (x > y) - (x < y);
}

/* One pass over the sequence from pt_controller_init; timed per step when per_step. */
static int run_pass(size_t n, int per_step, double *checksum)
{
    size_t k;
    pt_real d[4];
    pt_real ts = PT_CONFIG.law[PT_CFG_TS];
    if (pt_controller_init(&ctl, &PT_CONFIG, NULL) != 0) {
        return 1;
    }
    for (k = 0; k < n; ++k) {
        pt_sensors_t s;
        pt_reference_t r;
        uint32_t st;
        uint64_t t0 = 0;
        s.x = (pt_real)seq[k][0];
        s.p_a = (pt_real)seq[k][1];
        s.p_b = (pt_real)seq[k][2];
        s.p_s = (pt_real)seq[k][3];
        r.x_r = (pt_real)seq[k][4];
        r.v_r = (pt_real)seq[k][5];
        r.a_r = (pt_real)seq[k][6];
        if (per_step) {
            t0 = now_ns();
        }
        st = pt_controller_step(&ctl, &PT_CONFIG, &s, &r, (pt_real)k * ts, d);
        if (per_step) {
            step_ns[k] = (uint32_t)(now_ns() - t0);
        }
        if (st & PT_FAULT_MASK) {
            fprintf(stderr, "fault %s at sample %lu\n", pt_fault_name(pt_first_fault(st)),
                    (unsigned long)k);
            return 1;
        }
        *checksum += (double)d[0] + 2.0 * (double)d[1] + 3.0 * (double)d[2] + 4.0 * (double)d[3];
    }
    return 0;
}

int main(int argc, char **argv)
{
    FILE *fh;
    size_t n;
    int p, passes;
    double checksum = 0.0;
    if (argc != 3) {
        fprintf(stderr, "usage: %s SEQ.bin PASSES\n", argv[0]);
        return 2;
    }
    passes = atoi(argv[2]);
    fh = fopen(argv[1], "rb");
    if (fh == NULL) {
        return 2;
    }
    n = fread(seq, sizeof seq[0], MAX_SAMPLES, fh);
    fclose(fh);
    for (p = 0; p < passes; ++p) {
        uint64_t t0 = now_ns();
        if (run_pass(n, 0, &checksum) != 0) {
            return 1;
        }
        printf("pass_ns %.3f\n", (double)(now_ns() - t0) / (double)n);
    }
    if (passes > 0) {
        double ignored = 0.0;
        if (run_pass(n, 1, &ignored) != 0) {
            return 1;
        }
        qsort(step_ns, n, sizeof step_ns[0], cmp_u32);
        printf("step_ns %lu %lu %lu\n", (unsigned long)step_ns[n / 2],
               (unsigned long)step_ns[(n * 99) / 100], (unsigned long)step_ns[n - 1]);
    } else {
        run_pass(n, 0, &checksum); /* one untimed pass (for callgrind) */
    }
    printf("samples %lu checksum %.17g\n", (unsigned long)n, checksum);
    return 0;
}
"""

#: x86-64 SSE/AVX scalar and packed floating-point arithmetic, by kind.
_FP_KINDS: tuple[tuple[str, str], ...] = (
    ("add/sub", r"^v?(add|sub)[sp][ds]$"), ("mul", r"^v?mul[sp][ds]$"),
    ("div", r"^v?div[sp][ds]$"), ("sqrt", r"^v?sqrt[sp][ds]$"),
    ("min/max", r"^v?(min|max)[sp][ds]$"), ("compare", r"^v?u?comis[ds]$|^v?cmp\w*[sp][ds]$"),
    ("convert", r"^v?cvt"), ("sign (and/xor)", r"^v?(and|andn|xor|or)p[ds]$"),
)


def _sequence(controller: str, scenario: str) -> np.ndarray:
    """The readings and reference of a deploy run on the simulated rig, (n, 7)."""
    from pneutune.control.rig.deploy import deploy

    run = deploy(controller, rig="sim", scenarios=scenario, seed=1)
    res = run.runs[0].result
    if res.fault is not None:
        raise SystemExit(f"the deploy run faulted: {res.fault}")
    rec = res.loop.recording
    return np.ascontiguousarray(np.column_stack([rec.sensors_, rec.reference_]),
                                dtype=np.float64)


def _build(cc: str, emitted: Path, work: Path, real: str) -> Path:
    """The documented build of the emitted folder plus the driver, linked; the executable."""
    from pneutune.control.rig.emit_c import BUILD_LINE

    objs = work / f"obj-{real}"
    objs.mkdir()
    defs = ["-DPT_REAL_FLOAT"] if real == "float" else []
    flags = BUILD_LINE.split()[1:-2]  # -std=c99 -O2
    subprocess.run([cc, *flags, *defs, "-c", *sorted(map(str, emitted.glob("*.c")))],
                   cwd=objs, check=True)
    driver = work / "driver.c"
    driver.write_text(DRIVER, encoding="ascii")
    exe = work / f"c_step-{real}"
    subprocess.run([cc, *flags, *defs, "-no-pie", "-I", str(emitted), "-o", str(exe),
                    str(driver), *sorted(map(str, objs.glob("*.o"))), "-lm"], check=True)
    return exe


def _time(exe: Path, seq_file: Path, runs: int, passes: int) -> dict[str, object]:
    per_run, checksums, steps = [], set(), []
    for _ in range(runs):
        out = subprocess.run([str(exe), str(seq_file), str(passes)], capture_output=True,
                             text=True, check=True).stdout
        pass_ns = [float(v) for v in re.findall(r"^pass_ns (\S+)$", out, flags=re.M)]
        per_run.append(statistics.median(pass_ns))
        checksums.add(re.search(r"checksum (\S+)", out).group(1))  # type: ignore[union-attr]
        steps.append([int(v) for v in re.search(r"^step_ns (\d+) (\d+) (\d+)$", out,
                                                flags=re.M).groups()])  # type: ignore[union-attr]
    if len(checksums) != 1:
        raise SystemExit(f"runs wrote different duties: {checksums}")
    s = np.array(steps)
    return {"median": statistics.median(per_run), "min": min(per_run), "max": max(per_run),
            "step_p50": int(np.median(s[:, 0])), "step_p99": int(np.median(s[:, 1])),
            "step_max": int(s[:, 2].max())}


def _callgrind(exe: Path, seq_file: Path, n: int, work: Path) -> dict[str, object]:
    """Instructions per step (callgrind), and the floating-point ones of the emitted code."""
    out = work / f"{exe.name}.callgrind"
    subprocess.run(["valgrind", "--tool=callgrind", "--toggle-collect=pt_controller_step",
                    "--dump-instr=yes", "--dump-line=no", f"--callgrind-out-file={out}",
                    str(exe), str(seq_file), "0"], capture_output=True, text=True, check=True)
    text = out.read_text()
    total = int(re.search(r"^(?:summary|totals): (\d+)", text, flags=re.M).group(1))  # type: ignore[union-attr]
    # per-instruction counts of the executable itself (built -no-pie: addresses are objdump's)
    counts: Counter[int] = Counter()
    obj = None
    names: dict[str, str] = {}
    last_addr = 0
    calls: Counter[str] = Counter()
    fn_names: dict[str, str] = {}
    cfn = None
    cobj = None
    pending_calls = 0
    for line in text.splitlines():
        m = re.match(r"^(c?ob)=\((\d+)\)(?: (.*))?$", line)
        if m:
            if m.group(3):
                names[m.group(2)] = m.group(3)
            if m.group(1) == "ob":
                obj = cobj = names.get(m.group(2))
            else:
                cobj = names.get(m.group(2))
            continue
        m = re.match(r"^cfn=\((\d+)\)(?: (.*))?$", line)
        if m:
            if m.group(2):
                fn_names[m.group(1)] = m.group(2)
            cfn = fn_names.get(m.group(1))
            continue
        m = re.match(r"^fn=\((\d+)\)(?: (.*))?$", line)
        if m:
            if m.group(2):
                fn_names[m.group(1)] = m.group(2)
            continue
        m = re.match(r"^calls=(\d+)", line)
        if m:
            pending_calls = int(m.group(1))
            continue
        m = re.match(r"^(0x[0-9a-f]+|[+-]\d+|\*)\s+(\d+)", line)
        if m:
            a = m.group(1)
            addr = (int(a, 16) if a.startswith("0x") else last_addr + int(a) if a[0] in "+-"
                    else last_addr)
            last_addr = addr
            if pending_calls:  # the line after calls= is the call's cost, not an Ir of obj
                mine = obj is not None and Path(obj).name == exe.name
                if cfn is not None and mine and cobj is not None and "libm" in Path(cobj).name:
                    calls[cfn.split("@")[0]] += pending_calls
                pending_calls = 0
                cobj = obj
                continue
            if obj is not None and Path(obj).name == exe.name:
                counts[addr] += int(m.group(2))
    mnemonics: dict[int, str] = {}
    dump = subprocess.run(["objdump", "-d", "--no-show-raw-insn", str(exe)], capture_output=True,
                          text=True, check=True).stdout
    for line in dump.splitlines():
        m = re.match(r"^\s+([0-9a-f]+):\s+(\S+)", line)
        if m:
            mnemonics[int(m.group(1), 16)] = m.group(2)
    fp: Counter[str] = Counter()
    for addr, c in counts.items():
        mn = mnemonics.get(addr, "")
        for kind, pattern in _FP_KINDS:
            if re.match(pattern, mn):
                fp[kind] += c
                break
    libm = {k: v / n for k, v in calls.items() if v >= 0.01 * n}
    law_out = work / f"{exe.name}.law.callgrind"
    subprocess.run(["valgrind", "--tool=callgrind", "--toggle-collect=pt_step_into",
                    f"--callgrind-out-file={law_out}", str(exe), str(seq_file), "0"],
                   capture_output=True, text=True, check=True)
    law = int(re.search(r"^(?:summary|totals): (\d+)", law_out.read_text(),
                        flags=re.M).group(1))  # type: ignore[union-attr]
    return {"instructions": total / n, "law": law / n, "fp": {k: v / n for k, v in fp.items()},
            "libm": libm}


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--controller", default=str(ROOT / "data" / "controller-paper.yaml"),
                        help="controller.yaml (default the paper's)")
    parser.add_argument("--scenario", default="sine-0.5hz", help="the recorded run's scenario")
    parser.add_argument("--runs", type=int, default=7, help="driver runs per precision")
    parser.add_argument("--passes", type=int, default=10, help="passes over the sequence per run")
    parser.add_argument("--real", choices=["double", "float", "both"], default="both")
    parser.add_argument("--callgrind", action="store_true",
                        help="also count instructions per step with valgrind's callgrind")
    parser.add_argument("--cc", default=shutil.which("cc") or "gcc", help="the C compiler")
    args = parser.parse_args()

    from pneutune.control.rig.emit_c import emit_c

    seq = _sequence(args.controller, args.scenario)
    reals = ["double", "float"] if args.real == "both" else [args.real]
    with tempfile.TemporaryDirectory(prefix="c_step-") as tmp:
        work = Path(tmp)
        emitted = emit_c(args.controller, work / "emitted").out
        seq_file = work / "seq.bin"
        seq_file.write_bytes(seq.tobytes())
        cc_version = subprocess.run([args.cc, "--version"], capture_output=True,
                                    text=True).stdout.splitlines()[0]
        print(f"{Path(args.controller).name}, {args.scenario}: {seq.shape[0]} recorded samples; "
              f"{cc_version}, -std=c99 -O2; {args.runs} runs x {args.passes} passes")
        for real in reals:
            exe = _build(args.cc, emitted, work, real)
            t = _time(exe, seq_file, args.runs, args.passes)
            print(f"{real:>6}: {t['median']:.0f} ns/step median over runs "
                  f"(range {t['min']:.0f}-{t['max']:.0f}); single steps p50 {t['step_p50']} ns, "
                  f"p99 {t['step_p99']} ns, max {t['step_max']} ns (clock included)")
            if args.callgrind:
                if shutil.which("valgrind") is None or shutil.which("objdump") is None:
                    print("        --callgrind: valgrind or objdump is not installed")
                    continue
                c = _callgrind(exe, seq_file, seq.shape[0], work)
                fp = ", ".join(f"{k} {v:.0f}" for k, v in sorted(c["fp"].items()))  # type: ignore[union-attr]
                libm = ", ".join(f"{k} {v:.2f}" for k, v in sorted(c["libm"].items()))  # type: ignore[union-attr]
                print(f"        callgrind: {c['instructions']:.0f} instructions per step "
                      f"(libm included), {c['law']:.0f} of them in the law's step "
                      f"(pt_step_into); floating-point instructions of the emitted code per "
                      f"step: {fp}; libm calls per step: {libm or 'none'}")


if __name__ == "__main__":
    main()
