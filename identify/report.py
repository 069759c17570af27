"""report.md for ``identify``: what was fitted, how well, and the plots of each fit."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure

from pneutune.control.constants import THETA_NAMES, THETA_UNITS, VALVES
from pneutune.control.contracts.atomic import atomic_write_text, save_figure
from pneutune.control.physics.friction import smooth_sign_array as smooth_sign
from pneutune.control.physics.friction import stribeck
from pneutune.control.sim.model_box import uncertainty_box

from .pipeline import IdentifyResult


def _plot_valves(r: IdentifyResult, out: Path) -> Path:
    v = r.valves
    fig = Figure(figsize=(10, 4.2))
    axes = fig.subplots(1, 2)
    for ch, (ax, (meas, model, wt)) in enumerate(zip(axes, v.window_increments(), strict=True)):
        meas, model = meas / 1e3, model / 1e3
        # one RGBA row per point: matplotlib parses a colour name per point far slower
        colors = np.where((wt >= 1.0)[:, None], to_rgba("C0"), to_rgba("C1"))
        ax.scatter(meas, model, s=3, c=colors, alpha=0.5)
        lim = [min(meas.min(), model.min()), max(meas.max(), model.max())]
        ax.plot(lim, lim, "k--", lw=0.8)
        ax.set_xlabel(f"measured Δp_{'ab'[ch]} over {v.window_} samples [kPa]")
        ax.set_ylabel("model [kPa]")
        ax.set_title(f"chamber {'AB'[ch]}: rms residual {v.residual_std_[ch]:.0f} Pa "
                     f"(blue: valves fully open/shut, orange: partial duty)", fontsize=8)
    fig.suptitle("Valve fit: pressure increments, Eqs. (5)-(7)")
    fig.tight_layout()
    path = out / "valves.png"
    save_figure(fig, path)
    return path


def _plot_pwm(r: IdentifyResult, out: Path) -> Path:
    v = r.valves
    fig = Figure(figsize=(6, 4.5))
    ax = fig.subplots()
    for i, name in enumerate(VALVES):
        ax.plot(v.knots_, v.curves_[i], lw=0.8, label=f"{name} (valves.{name}.pwm)")
    ax.plot(v.knots_, v.curve_, "k", lw=2, label="mean (pwm)")
    ax.plot([0, 1], [0, 1], ":", color="0.5", lw=0.8)
    ax.set_xlabel("commanded duty")
    ax.set_ylabel("effective open fraction")
    sw = v.switching(1.0 / r.data.rig.pwm_hz)
    ax.set_title(f"PWM curve (QP, monotone): dead zone to {sw['dead_zone']:.3f}, "
                 f"offset {sw['offset']:+.3f}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "pwm.png"
    save_figure(fig, path)
    return path


def _plot_friction(r: IdentifyResult, out: Path) -> Path:
    f = r.friction
    d = r.data
    sl = f.sliding_
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    y = f.y_
    vs = d.v[sl] if len(y) == int(sl.sum()) else None
    if vs is not None:
        ax.scatter(vs * 1e3, y + f.F_n_, s=2, alpha=0.3, color="0.5", label="F_p - M a (+F_n)")
    vv = np.linspace(-0.25, 0.25, 1001)
    ax.plot(vv * 1e3, stribeck(vv, f.F_S_, f.F_C_, f.v_s_, f.alpha_, f.b_v_), "C3",
            label="Stribeck fit, Eq. (2)")
    _, bv, Af = f.smooth_
    ax.plot(vv * 1e3, bv * vv + Af * smooth_sign(vv), "C0--", label="smooth model, Eq. (3)")
    ax.set_xlabel("velocity [mm/s]")
    ax.set_ylabel("friction force [N]")
    ax.set_title(f"F_C = {f.F_C_:.1f} N, F_S = {f.F_S_:.1f} N, b_v = {f.b_v_:.0f} N s/m; "
                 f"A_f = {Af:.1f} N", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "friction.png"
    save_figure(fig, path)
    return path


def _plot_validation(r: IdentifyResult, out: Path) -> Path:
    val = r.validation
    fig = Figure(figsize=(9, 7))
    axes = fig.subplots(3, 1, sharex=True)
    scale = (1e3, 1e-5, 1e-5)
    ylabels = ("x [mm]", "p_a [bar]", "p_b [bar]")
    keys = ("x", "p_a", "p_b")
    # break the lines between held-out stretches
    gap = np.flatnonzero(np.diff(val.t) > 1.5 * r.data.Ts) + 1
    t = np.insert(val.t, gap, np.nan)
    meas = np.insert(val.measured, gap, np.nan, axis=0)
    sim = np.insert(val.simulated, gap, np.nan, axis=0)
    for i, ax in enumerate(axes):
        ax.plot(t, meas[:, i] * scale[i], "k", lw=0.8, label="measured")
        ax.plot(t, sim[:, i] * scale[i], "C1", lw=0.8, label="identified model")
        ax.set_ylabel(ylabels[i])
        ax.set_title(f"NRMSE {val.nrmse[keys[i]]:.3f}", fontsize=8)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("time [s] (held-out part, 2 s windows from the measured state)")
    fig.suptitle("Validation: the identified model driven by the logged duties")
    fig.tight_layout()
    path = out / "validation.png"
    save_figure(fig, path)
    return path


def summary_rows(r: IdentifyResult) -> list[tuple[str, str, str]]:
    """(parameter, value, range or bounds) rows of the on-screen summary."""
    m = r.model
    rows = []
    for name, v in zip(VALVES, m.valves.ordered(), strict=True):
        rows.append((f"C {name}", f"{v.C:.4g} m^3/(s Pa)", f"[{v.C_min:.4g}, {v.C_max:.4g}]"))
        rows.append((f"b {name}", f"{v.b:.4g}", f"[{v.b_min:.4g}, {v.b_max:.4g}]"))
    f = m.friction
    rows += [("F_C", f"{f.F_C:.2f} N", ""), ("F_S", f"{f.F_S:.2f} N", ""),
             ("b_v", f"{f.b_v:.1f} N s/m", ""), ("v_s", f"{f.v_s * 1e3:.2f} mm/s", ""),
             ("alpha", f"{f.alpha:.2f}", "")]
    for i, name in enumerate(THETA_NAMES):
        rows.append((f"θ{i + 1} {name}", f"{m.theta.nominal[i]:.4g} {THETA_UNITS[i]}",
                     f"[{m.theta.min[i]:.4g}, {m.theta.max[i]:.4g}]"))
    rows += [("F_max", f"{m.uncertainty.F_max:.3g} N", ""),
             ("D_a_max / D_b_max", f"{m.uncertainty.D_a_max:.3g} / {m.uncertainty.D_b_max:.3g}"
              " Pa/s", ""),
             ("fit NRMSE x / p_a / p_b", f"{m.fit.nrmse_x:.3f} / {m.fit.nrmse_p_a:.3f} / "
              f"{m.fit.nrmse_p_b:.3f}", "held-out part")]
    return rows


def format_summary(r: IdentifyResult) -> str:
    """The on-screen summary table."""
    rows = summary_rows(r)
    w0 = max(len(a) for a, _, _ in rows)
    w1 = max(len(b) for _, b, _ in rows)
    if len(r.logs) > 1:
        lines = [f"identify {len(r.logs)} logs of one rig, one model: " + ", ".join(
            f"{name} ({d.duration:.1f} s every {d.Ts * 1e3:g} ms)"
            for name, d in zip(r.names, r.logs, strict=True))]
    else:
        lines = [f"identify {r.data.path}: {r.data.duration:.1f} s, {r.data.n} samples"]
        if r.log is not None and r.log.n != r.data.n:
            lines[0] += (f" at the {r.data.Ts * 1e3:g} ms control instants ({r.log.n} logged "
                         f"every {r.log.Ts * 1e3:g} ms; the mass uses them all)")
    lines += [f"  {a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows]
    lines += [f"  note: {n}" for n in r.notes]
    return "\n".join(lines)


def _ranges_section(r: IdentifyResult) -> list[str]:
    """The ranges tune samples, their basis and what the cross-check against the log did."""
    m = r.model
    basis = m.basis or {}
    cc = r.crosscheck
    moved: dict[str, list[str]] = {}
    if cc is not None:
        for c in cc.checks:
            if c.shrunk and c.end != "corner":
                moved.setdefault(c.key, []).append(
                    f"{c.end} end {c.value:.4g} ruled out ({c.worst(cc.best)}), moved to "
                    f"{c.kept:.4g}")
        for key, keys in cc.corner_keys.items():
            for k in keys:
                moved.setdefault(k, []).append(f"narrowed for the {key.split(':')[1]} corner")
    out = ["## Ranges a tuner samples, and their basis", "",
           "Every coordinate of the plant draws of `tune` (`pneutune.control.sim.model_box`). "
           + ("Ends that are not a statistical fit were replayed on the held-out log: an end "
              f"whose NRMSE exceeds {cc.factor:g} times the best fit's (x {cc.best['x']:.3g}, "
              f"p_a {cc.best['p_a']:.3g}, p_b {cc.best['p_b']:.3g}) plus {cc.floor:g} is "
              "ruled out and moved toward the nominal value (identify/crosscheck.py)."
              if cc is not None else "The cross-check against the log was skipped."), "",
           "| coordinate | nominal | range | basis | cross-check |", "|---|---:|---|---|---|"]
    for c in uncertainty_box(m):
        note = "; ".join(moved.get(c.key, [])) or ("passed" if cc is not None else "-")
        out.append(f"| {c.key} | {c.nominal:.4g} | [{c.low:.4g}, {c.high:.4g}] | "
                   f"{basis.get(c.key, '-')} | {note} |")
    return [*out, ""]


def _sources_section(r: IdentifyResult) -> list[str]:
    """The log, or every log, the model came from."""
    m = r.model
    if len(m.sources) == 1:
        src = m.sources[0]
        return [f"Log: `{src.log}` (sha256 `{src.sha256[:16]}…`, {src.duration_s:.1f} s). "
                f"Fitted on {100 * (1.0 - len(r.validation.t) / r.data.n):.0f} % of the "
                f"samples; the end of every 10 s is held out for validation."]
    pl = r.pool
    pooled = set(pl.names) if pl is not None else set()
    n_valid = int(pl.valid.sum()) if pl is not None else r.data.n
    out = [f"Logs: one model fitted to {len(m.sources)} logs of one rig. The valve, friction "
           "and validation fits pool their samples at the control instants (no fit window "
           "straddles two logs), the mass's lag estimate pools the logs sampled fast enough, "
           "the stiction bounds come from each log at its own sampling period; each basis "
           f"below names the logs it came from. Fitted on "
           f"{100 * (1.0 - len(r.validation.t) / max(n_valid, 1)):.0f} % of the pooled samples; "
           "the end of every 10 s of each log is held out for validation.", "",
           "| log | sha256 | duration | sampled every | pooled fits |",
           "|---|---|---:|---:|---|"]
    for src, d, name in zip(m.sources, r.logs, r.names, strict=True):
        cut = (f"at the {r.data.Ts * 1e3:g} ms control instants" if name in pooled
               else "left out (see the notes)")
        out.append(f"| `{src.log}` | `{src.sha256[:16]}…` | {src.duration_s:.1f} s | "
                   f"{d.Ts * 1e3:g} ms | {cut} |")
    return out


def write_report(r: IdentifyResult, folder: str | os.PathLike[str]) -> Path:
    """Write report.md and its figures into ``folder``; returns the report's path."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    figs = {"valves": _plot_valves(r, out), "pwm": _plot_pwm(r, out),
            "friction": _plot_friction(r, out), "validation": _plot_validation(r, out)}
    m = r.model
    th = r.theta
    lines = ["# Identification report", "", *_sources_section(r), ""]
    lines += [
        "## θ and its bounds (Assumption 1)", "",
        "| θ | nominal | min | max | width | basis |", "|---|---:|---:|---:|---:|---|",
    ]
    mt = m.theta
    for i, name in enumerate(THETA_NAMES):
        lines.append(f"| θ{i + 1} {name} [{THETA_UNITS[i]}] | {mt.nominal[i]:.5g} | "
                     f"{mt.min[i]:.5g} | {mt.max[i]:.5g} | {mt.max[i] - mt.min[i]:.4g} | "
                     f"{th.basis[i]} |")
    lines += ["", f"F_max = {m.uncertainty.F_max:.3g} N (99.9th percentile of the friction "
              f"fit's residual force), D_a_max = {m.uncertainty.D_a_max:.3g} Pa/s, "
              f"D_b_max = {m.uncertainty.D_b_max:.3g} Pa/s (largest valve-fit window residual "
              f"per second).", "",
              "## Valves (ISO 6358, Eq. 7)", "",
              "| valve | C [m^3/(s Pa)] | C range | b | b range | delay_on | delay_off | "
              "min_pulse | min_pulse range |", "|---|---:|---|---:|---|---:|---:|---:|---|"]
    for name, v in zip(VALVES, m.valves.ordered(), strict=True):
        mp_range = ("-" if v.min_pulse_min is None or v.min_pulse_max is None
                    else f"[{v.min_pulse_min * 1e3:.2f}, {v.min_pulse_max * 1e3:.2f}] ms")
        lines.append(f"| {name} | {v.C:.5g} | [{v.C_min:.4g}, {v.C_max:.4g}] | {v.b:.4f} | "
                     f"[{v.b_min:.3f}, {v.b_max:.3f}] | {v.delay_on * 1e3:.2f} ms | "
                     f"{v.delay_off * 1e3:.2f} ms | {v.min_pulse * 1e3:.2f} ms | {mp_range} |")
    v = r.valves
    if v.timing_ is not None:
        timing = (f"Delays and minimum pulses from the exact opening of every valve in every "
                  f"sample (the PWM carrier at {v.phase_ * 1e3:.2f} ms at the log's start; "
                  f"residual {v.timing_rss_[0]:.3g} against {v.timing_rss_[1]:.3g} kPa² with "
                  f"the averaged PWM curve).")
    else:
        timing = ("Only the minimum pulse and the difference of the delays show in the PWM "
                  "curve; delay_on is set to the minimum pulse.")
    lines += ["", f"Leak A↔B: C = {m.leak.C:.3g} m^3/(s Pa). {timing}", "",
              f"![valve fit]({figs['valves'].name})", "",
              f"![PWM curve]({figs['pwm'].name})", "",
              "## Friction and mass (Eqs. 1-4)", "",
              f"Stribeck: F_S = {m.friction.F_S:.2f} N, F_C = {m.friction.F_C:.2f} N, "
              f"v_s = {m.friction.v_s * 1e3:.2f} mm/s, alpha = {m.friction.alpha:.2f}, "
              f"b_v = {m.friction.b_v:.1f} N s/m; smooth model A_f = {m.friction.A_f:.2f} N. "
              f"Mass {m.mass:.4g} kg, range {list(m.mass_range or ())} ({r.mass_basis}).", "",
              f"![friction]({figs['friction'].name})", "",
              "## Validation (held-out part)", "",
              f"NRMSE x = {m.fit.nrmse_x:.4f}, p_a = {m.fit.nrmse_p_a:.4f}, "
              f"p_b = {m.fit.nrmse_p_b:.4f}.", "",
              f"![validation]({figs['validation'].name})", ""]
    lines += _ranges_section(r)
    if r.notes:
        lines += ["## Not identifiable, or weakly", ""] + [f"- {n}" for n in r.notes] + [""]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path
