"""Figures like the paper's Figs. 4-17: tracking and error, chamber pressures, θ̂, duties."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from matplotlib.figure import Figure

from pneutune.control.constants import THETA_NAMES, THETA_UNITS, VALVES
from pneutune.control.contracts.atomic import save_figure

if TYPE_CHECKING:  # the annotation only: plotting does not load the compiled simulator
    from pneutune.control.sim.closed_loop import ClosedLoopResult


def plot_closed_loop(result: ClosedLoopResult, folder: str | os.PathLike[str]) -> list[Path]:
    """Write the four figures of a closed-loop run as PNG files into ``folder``.

    Returns
    -------
    list of Path
        ``<scenario>-tracking.png``, ``-pressures.png``, ``-theta.png``, ``-duties.png``.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    name = result.scenario.name
    t = result.t
    n = t.shape[0]
    ref = result.reference[:n]
    x = result.sensors[:, 0]
    files = []

    fig = Figure(figsize=(8, 5.5))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t, ref[:, 0] * 1e3, "k--", lw=1.0, label="reference $x_r$")
    ax1.plot(t, x * 1e3, "C0", lw=1.0, label="measured $x$")
    ax1.set_ylabel("position [mm]")
    ax1.legend(loc="upper right", fontsize=8)
    ax2.plot(t, (x - ref[:, 0]) * 1e3, "C3", lw=0.8)
    m = result.metrics
    ax2.axvspan(max(0.0, t[-1] - 3.0 * result.scenario.period), t[-1], color="0.9", zorder=0)
    ax2.set_ylabel("error $e_1$ [mm]")
    ax2.set_xlabel("time [s]")
    ax2.set_title(f"last 3 periods (shaded): $E_p$ = {m.E_p_mm:.3f} mm, "
                  f"$E_{{rms}}$ = {m.E_rms_mm:.3f} mm", fontsize=9)
    fig.suptitle(f"{name}: tracking ({result.controller.variant})")
    fig.tight_layout()
    files.append(out / f"{name}-tracking.png")
    save_figure(fig, files[-1])

    fig = Figure(figsize=(8, 3.5))
    ax = fig.subplots()
    ax.plot(t, result.sensors[:, 1] / 1e5, label="$p_a$")
    ax.plot(t, result.sensors[:, 2] / 1e5, label="$p_b$")
    ax.plot(t, result.sensors[:, 3] / 1e5, "k:", lw=0.8, label="$p_s$")
    ax.set_ylabel("pressure [bar abs]")
    ax.set_xlabel("time [s]")
    ax.legend(fontsize=8)
    ax.set_title(f"{name}: chamber pressures")
    fig.tight_layout()
    files.append(out / f"{name}-pressures.png")
    save_figure(fig, files[-1])

    fig = Figure(figsize=(9, 6.5))
    axes = fig.subplots(3, 2, sharex=True)
    theta = result.control_state[:, -6:]
    a = result.controller.adaptation
    for i, ax in enumerate(axes.ravel()):
        ax.plot(t, theta[:, i], "C2")
        ax.axhline(a.theta_min[i], color="0.5", ls=":", lw=0.8)
        ax.axhline(a.theta_max[i], color="0.5", ls=":", lw=0.8)
        ax.set_ylabel(f"{THETA_NAMES[i]} [{THETA_UNITS[i]}]", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"{name}: parameter estimates θ̂ (dotted: bounds)")
    fig.tight_layout()
    files.append(out / f"{name}-theta.png")
    save_figure(fig, files[-1])

    fig = Figure(figsize=(8, 6))
    axes = fig.subplots(4, 1, sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, result.duties[:, i], lw=0.7)
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel(f"u_{VALVES[i]}", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{name}: commanded duties ({m.switches_per_s:.1f} mode switches/s)")
    fig.tight_layout()
    files.append(out / f"{name}-duties.png")
    save_figure(fig, files[-1])
    return files


__all__ = ["plot_closed_loop"]
