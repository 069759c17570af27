"""report.md of a tuning run: Table-1 comparison, robustness, history and importance plots.

The tuned controller and the paper's (``data/controller-paper.yaml``) are both scored by the
same :class:`~pneutune.tune.objective.TuneObjective` (same scenarios, plant draws and sensor
noise; every run, no early stop), and compared on the nominal plant (draw 0) and on the worst
draw (the draw where the tuned controller's mean cost over the scenarios is highest). Plots:
the optimisation history (complete trials, best so far, pruned trials at their last reported
value) and the parameter importances by Optuna's PED-ANOVA evaluator (no plotly, no sklearn).
Images are written atomically (``control/contracts/atomic.py``) with matplotlib's Agg backend.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import optuna
from matplotlib.figure import Figure
from optuna.trial import FrozenTrial, TrialState

from pneutune.control.contracts.atomic import atomic_write_text, save_figure
from pneutune.control.contracts.controller import ControllerConfig
from pneutune.control.sim.closed_loop import FULL_OPEN_SUSTAIN
from pneutune.control.sim.table import format_table

from .objective import FAIL_VALUE, Evaluation, TuneObjective
from .space import RANGE_END_SHARE, params_from_controller

#: The held-out plants and noise are drawn with ``seed + HELDOUT_SEED_OFFSET`` (:func:`compare`).
HELDOUT_SEED_OFFSET = 1_000_003
#: report.md says the valves' flow limits a scenario when the tuned controller keeps a valve
#: fully open, in openings of at least 0.1 s, for at least this share of the metric window
#: (Metrics.flow_limited); and that the gains chatter when it opens them fully for this share in
#: shorter bursts and tracks worse than the paper's gains (Metrics.full_open) [-].
FLOW_LIMITED = 0.10


@dataclass
class HeldOut:
    """Both controllers on plant draws and sensor noise the study never saw.

    Attributes
    ----------
    seed : int
        Seed of the held-out draws (the study's seed + :data:`HELDOUT_SEED_OFFSET`).
    objective : TuneObjective
        The objective on the held-out draws (same scenarios, settings and θ box).
    tuned, paper : Evaluation
    """

    seed: int
    objective: TuneObjective
    tuned: Evaluation
    paper: Evaluation

    def mean_e_p(self, which: str) -> dict[str, float]:
        """Per scenario, the mean E_p [mm] of ``which`` over the held-out draws."""
        ev = self.tuned if which == "tuned" else self.paper
        acc: dict[str, list[float]] = {}
        for (s, _), rc in ev.runs.items():
            acc.setdefault(s, []).append(rc.metrics.E_p_mm)
        return {s: float(np.mean(v)) for s, v in acc.items()}

    def overfit(self, study_tuned: float | None, study_paper: float | None) -> float | None:
        """How much worse the tuned controller does on held-out draws than on the study's,
        relative to how much worse the paper's does (which was not fitted to either set):
        ``(tuned_heldout / tuned_study) / (paper_heldout / paper_study) - 1``. 0: no
        overfitting; 0.1: the tuned controller's advantage shrinks by 10 % on new plants.
        None when a value is missing."""
        vals = (self.tuned.value, study_tuned, self.paper.value, study_paper)
        if any(v is None or not np.isfinite(v) or v <= 0.0 for v in vals):
            return None
        th, ts, ph, ps = vals  # type: ignore[misc]
        return float((th / ts) / (ph / ps) - 1.0)


@dataclass
class Comparison:
    """Tuned and paper controllers scored on every scenario and draw.

    Attributes
    ----------
    tuned, paper : Evaluation
    worst_draw : int
        Index of the draw where the tuned controller does worst.
    heldout : HeldOut or None
        Both controllers on held-out draws (:func:`compare` with ``heldout=True``).
    """

    tuned: Evaluation
    paper: Evaluation
    worst_draw: int
    heldout: HeldOut | None = None

    def table(self, which: str, draw: int) -> dict[str, dict[str, Any]]:
        """Per scenario, the metrics of ``which`` (``tuned`` or ``paper``) on ``draw``."""
        ev = self.tuned if which == "tuned" else self.paper
        return {s: rc.metrics.as_dict() for (s, d), rc in ev.runs.items() if d == draw}

    def summary(self) -> dict[str, Any]:
        """Plain data for ``--json``."""
        held: dict[str, Any] | None = None
        if self.heldout is not None:
            h = self.heldout
            held = {"seed": h.seed,
                    "objective": {"tuned": h.tuned.value, "paper": h.paper.value},
                    "mean_E_p_mm": {"tuned": h.mean_e_p("tuned"), "paper": h.mean_e_p("paper")},
                    "overfit": h.overfit(self.tuned.value, self.paper.value)}
        return {
            "heldout": held,
            "objective": {"tuned": self.tuned.value, "paper": self.paper.value},
            "worst_draw": self.worst_draw,
            "nominal": {"tuned": self.table("tuned", 0), "paper": self.table("paper", 0)},
            "worst": {"tuned": self.table("tuned", self.worst_draw),
                      "paper": self.table("paper", self.worst_draw)},
        }


def compare(objective: TuneObjective, tuned: ControllerConfig,
            paper: ControllerConfig, heldout: bool = True) -> Comparison:
    """Score both controllers on every scenario and draw (no early stop).

    Parameters
    ----------
    objective : TuneObjective
        The study's objective (its draws and noise).
    tuned, paper : ControllerConfig
    heldout : bool
        Also score both on held-out draws: a :class:`TuneObjective` with the same model,
        settings and θ box but the seed ``objective.seed + HELDOUT_SEED_OFFSET``, so new sensor
        noise on every draw and new Latin-hypercube plants (the nominal plant and the two
        corners are the same plants, with new noise).

    Returns
    -------
    Comparison
    """
    ev_t = objective.evaluate(tuned, stop_on_failure=False)
    ev_p = objective.evaluate(paper, stop_on_failure=False)
    totals = ev_t.draw_totals()
    worst = max(totals, key=lambda d: totals[d]) if totals else 0
    held = None
    if heldout:
        seed = objective.seed + HELDOUT_SEED_OFFSET
        obj_h = TuneObjective(objective.model, seed, objective.settings, jobs=objective.jobs)
        held = HeldOut(seed, obj_h, obj_h.evaluate(tuned, stop_on_failure=False),
                       obj_h.evaluate(paper, stop_on_failure=False))
    return Comparison(ev_t, ev_p, worst, held)


def _heldout(comp: Comparison) -> list[str]:
    """The generalisation section of report.md (nothing without held-out draws)."""
    h = comp.heldout
    if h is None:
        return []
    over = h.overfit(comp.tuned.value, comp.paper.value)
    t_e, p_e = h.mean_e_p("tuned"), h.mean_e_p("paper")
    lines = ["## Generalisation: held-out plants and noise", "",
             f"Both controllers on {len(h.objective.draws)} draws the study never saw (seed "
             f"{h.seed}: new sensor noise on every draw"
             + ("; new Latin-hypercube plants, while the nominal plant and the two corners are "
                "the same plants" if len(h.objective.draws) > 3 else
                "; with 3 draws or fewer these are the same plants (nominal and corners)")
             + ").", "",
             "| | study draws | held-out draws |", "|---|---|---|",
             f"| objective, tuned | {_fmt(comp.tuned.value, 4)} | {_fmt(h.tuned.value, 4)} |",
             f"| objective, paper | {_fmt(comp.paper.value, 4)} | {_fmt(h.paper.value, 4)} |",
             "", "| scenario | mean E_p held-out, paper [mm] | tuned [mm] |", "|---|---|---|"]
    lines += [f"| {s} | {_fmt(p_e.get(s))} | {_fmt(t_e.get(s))} |" for s in t_e]
    if over is None:
        verdict = "not computed (a run failed)"
    else:
        verdict = f"{over:+.1%} (" + ("the advantage holds on new plants" if over <= 0.1 else
                                      "the tuned gains fit the study's draws noticeably better "
                                      "than new ones") + ")."
    lines += ["", "Overfitting to the study's draws, (tuned held-out / tuned study) / "
              "(paper held-out / paper study) - 1: " + verdict, ""]
    return lines


def _moved(info: dict[str, Any]) -> str:
    """What report.md adds to the paper's file name when its rig and limits were the model's
    (:func:`~pneutune.tune.api.paper_on_rig`)."""
    return " with this model's rig and limits blocks" if info.get("paper_moved") else ""


def plot_history(study: optuna.Study, path: Path) -> Path:
    """Objective of each trial and the best so far (PNG).

    A pruned trial is drawn at its last reported value; one the pruner stopped on a lower bound
    of a scenario (``user_attrs["pruned_on_bound"]``) with its own marker, since its objective
    would have been at least that value.
    """
    trials = study.get_trials(deepcopy=False)
    fig = Figure(figsize=(8, 4))
    ax = fig.subplots()
    done = [t for t in trials if t.state == TrialState.COMPLETE]
    pruned = [(t.number, t.intermediate_values[max(t.intermediate_values)],
               "pruned_on_bound" in t.user_attrs)
              for t in trials if t.state == TrialState.PRUNED and t.intermediate_values]
    for on_bound, marker, label in ((False, "x", "pruned (last reported value)"),
                                    (True, "^", "pruned on a lower bound (value at least)")):
        pts = [(n, v) for n, v, b in pruned if v < FAIL_VALUE and b == on_bound]
        if pts:
            ax.scatter(*zip(*pts, strict=True), s=10, marker=marker, color="0.6", label=label)
    if done:
        x = [t.number for t in done]
        y = [t.value for t in done]
        ax.scatter(x, y, s=14, color="C0", label="complete")
        order = np.argsort(x)
        best = np.minimum.accumulate(np.asarray(y)[order])
        ax.step(np.asarray(x)[order], best, where="post", color="C3", label="best so far")
    n_fail = sum(1 for _, v, _ in pruned if v >= FAIL_VALUE)
    ax.set_xlabel("trial")
    ax.set_ylabel("objective (1 = the paper's Table 1)")
    ax.set_yscale("log")
    ax.set_title(f"optimisation history ({len(done)} complete, {len(pruned)} pruned of which "
                 f"{n_fail} unstable/aborted)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return path


def importances(study: optuna.Study) -> dict[str, float] | None:
    """PED-ANOVA parameter importances (normalised), or None with fewer than 2 complete trials
    or when the evaluator cannot run."""
    if len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))) < 2:
        return None
    try:
        return optuna.importance.get_param_importances(
            study, evaluator=optuna.importance.PedAnovaImportanceEvaluator())
    except (ValueError, RuntimeError, ZeroDivisionError):
        return None


def plot_importance(imp: dict[str, float] | None, path: Path) -> Path:
    """Horizontal bar chart of the importances (PNG)."""
    fig = Figure(figsize=(8, 4.5))
    ax = fig.subplots()
    if imp:
        names = list(imp)[::-1]
        ax.barh(names, [imp[n] for n in names], color="C0")
        ax.set_xlabel("importance (PED-ANOVA, normalised)")
    else:
        ax.text(0.5, 0.5, "not enough complete trials", ha="center", va="center")
    ax.set_title("parameter importance", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
    return path


def _fmt(x: float | None, digits: int = 3) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.{digits}f}"


def _side_by_side(comp: Comparison, objective: TuneObjective, draw: int) -> list[str]:
    lines = ["| scenario | Table 1 (rig) E_p / E_rms | paper gains E_p / E_rms | tuned E_p / E_rms "
             "| switches/s paper / tuned | valves fully open paper / tuned "
             "| status paper / tuned |",
             "|---|---|---|---|---|---|---|"]
    tuned = comp.table("tuned", draw)
    paper = comp.table("paper", draw)
    limited, chatter = [], []
    for sc in objective.scenarios:
        t, p = tuned[sc.name], paper[sc.name]
        rig = f"{sc.paper[0]:.2f} / {sc.paper[1]:.2f}" if sc.paper else "-"
        lines.append(f"| {sc.name} | {rig} | {_fmt(p['E_p_mm'])} / {_fmt(p['E_rms_mm'])} "
                     f"| {_fmt(t['E_p_mm'])} / {_fmt(t['E_rms_mm'])} "
                     f"| {_fmt(p['switches_per_s'], 1)} / {_fmt(t['switches_per_s'], 1)} "
                     f"| {_pct(p.get('full_open'))} / {_pct(t.get('full_open'))} "
                     f"| {p['status']} / {t['status']} |")
        verdict = valve_verdict(t, p)
        if verdict == "flow-limited":
            limited.append(f"{sc.name} ({t['flow_limited'] * 100:.0f} %)")
        elif verdict == "chatter":
            chatter.append(f"{sc.name} ({t['full_open'] * 100:.0f} %)")
    if limited:
        lines += ["", f"Valve flow limits the tracking on {', '.join(limited)}: the tuned "
                  f"controller holds a valve fully open, in openings of {FULL_OPEN_SUSTAIN:g} s "
                  "or more, for that "
                  "share of the metric window, so there the valves pass all they can; other "
                  "gains can do better only by opening them earlier, and larger valves or a "
                  "slower reference by more (docs/tuning.md, \"What limits E_p\")."]
    if chatter:
        lines += ["", f"The tuned gains chatter on {', '.join(chatter)}: the controller opens "
                  "the valves fully for that share of the metric window in bursts shorter than "
                  f"{FULL_OPEN_SUSTAIN:g} s and tracks worse than the paper's gains. That is the "
                  "gains, not the "
                  "valves: a study with another --seed or more trials may find better ones "
                  "(docs/tuning.md, \"What limits E_p\")."]
    return lines


def valve_verdict(tuned: dict[str, Any], paper: dict[str, Any]) -> str | None:
    """What report.md says about the valves on one scenario.

    Parameters
    ----------
    tuned, paper : dict
        :meth:`Metrics.as_dict` of the tuned and the paper's controller on the same run.

    Returns
    -------
    str or None
        ``"flow-limited"``: a valve held fully open, 0.1 s or more at a time, for at least
        :data:`FLOW_LIMITED` of the window; ``"chatter"``: fully open that long only in shorter
        bursts, and a larger E_p than the paper's gains; else None.
    """
    if _at_least(tuned.get("flow_limited"), FLOW_LIMITED):
        return "flow-limited"
    if (_at_least(tuned.get("full_open"), FLOW_LIMITED)
            and tuned.get("E_p_mm", np.nan) > paper.get("E_p_mm", np.inf)):
        return "chatter"
    return None


def _at_least(x: float | None, level: float) -> bool:
    return x is not None and bool(np.isfinite(x)) and x >= level


def _pct(x: float | None) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x * 100:.0f} %"


def _feasibility(notes: list[str]) -> list[str]:
    """The section on what the feasibility check changed (nothing when the box was kept)."""
    if not notes:
        return []
    return ["## What tune had to change", "",
            "Before the study, the reference controller was run on every plant draw "
            "(`pneutune.tune.feasibility`). Where a draw defeated it, the ranges that made the "
            "draw infeasible were narrowed toward the model's nominal values:", "",
            *[f"- {n}" for n in notes], ""]


def _guard(notes: list[str]) -> list[str]:
    """The section on the held-out guard (nothing when the study's best passed it)."""
    if not notes:
        return []
    return ["## Held-out guard", "",
            "The best trials were run, best first, on plants and noise the study never saw "
            "(`pneutune.tune.guard`), to keep the first that completes every run:", "",
            *[f"- {n}" for n in notes], ""]


def _restarts(rows: list[dict[str, Any]] | None) -> list[str]:
    """The section on the restarts (nothing with one study)."""
    if not rows:
        return []
    lines = ["## Restarts", "",
             f"{len(rows)} independent studies; each one's guarded best trial was scored on "
             "the same selection draws (`pneutune.tune.restarts`: new sensor noise and new "
             "Latin-hypercube plants beside the nominal plant and the corners), and the one "
             "with the fewest failed runs, then the lowest score, kept (the score is the "
             "objective over the runs every study's trial completed). A study's own objective "
             "is on its own draws, so it does not compare across studies; the selection score "
             "does.", "",
             "| seed | study | trials (this run) | trial | study objective | failed runs | "
             "selection score | kept |",
             "|---:|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        score = "n/a" if r["score"] is None else f"{r['score']:.4f}"
        failed = f"{r['failed']} ({r['failure']})" if r["failed"] else "0"
        lines.append(f"| {r['seed']} | `{r['study']}` | {r['finished']} ({r['this_run']}) | "
                     f"#{r['trial']} | {r['objective']:.4f} | {failed} | {score} | "
                     f"{'yes' if r['kept'] else ''} |")
    return [*lines, ""]


def render(objective: TuneObjective, study: optuna.Study, best: FrozenTrial,
           tuned: ControllerConfig, paper: ControllerConfig, comp: Comparison,
           imp: dict[str, float] | None, info: dict[str, Any]) -> str:
    """The text of report.md."""
    st = objective.settings
    counts = info["counts"]
    first = study.get_trials(deepcopy=False)[:1]
    paper_trial = (first[0].value if first and first[0].state == TrialState.COMPLETE
                   else None)
    draws = objective.draws
    wd = draws[comp.worst_draw]
    out = [
        "# tune report",
        "",
        f"- model: `{info['model']}` (sha256 `{info['model_sha256']}`)",
        f"- study: `{study.study_name}` in `{info['storage']}`; seed {objective.seed}"
        + (f"; sampler: {info['sampler']}" if info.get("sampler") else ""),
        f"- trials: {counts['COMPLETE']} complete, {counts['PRUNED']} pruned, "
        f"{counts['FAIL']} failed (wanted {info['n_trials']} complete + pruned)",
        f"- {'trial kept by the held-out guard' if info.get('guard_moved') else 'best trial'}: "
        f"#{best.number}, objective {best.value:.4f}; "
        f"`{info['paper_path']}`{_moved(info)} on the same plants: {_fmt(comp.paper.value, 4)}"
        + (f"; trial #0 (the paper's gains with the model's θ box): {paper_trial:.4f}"
           if paper_trial is not None else ""),
        f"- objective: mean over {len(objective.scenarios)} scenarios of the CVaR "
        f"(α = {st.cvar_alpha}) over {len(draws)} plant draws of "
        "½(E_p/E_p\\* + E_rms/E_rms\\*) + penalties (chattering above "
        f"{st.switches_free:g} switches/s, pressure outside [{st.p_low_fraction:g} p0, p_max], "
        "end-stop contact); 1 = the paper's Table 1 on every scenario. docs/tuning.md.",
        f"- controller: `{info['controller']}`; baseline: `{info['paper_path']}`{_moved(info)}",
        "",
        *([f"**Short stroke.** {info['stroke']}", ""] if info.get("stroke") else []),
        *_feasibility(info.get("feasibility") or []),
        *_guard(info.get("guard") or []),
        *_restarts(info.get("restarts")),
        *([f"**{info['behind_paper']}**", ""] if info.get("behind_paper") else []),
        *(info.get("log_check") or []),
        "## Table 1 on the nominal plant",
        "",
        "Simulated on the model's nominal plant (draw 0, sensor-noise seed "
        f"{draws[0].noise_seed}); reproduce with "
        f"`simulate --controller {info['controller']} --plant {info['plant_nominal']} "
        "--scenario all`.",
        "",
        *_side_by_side(comp, objective, 0),
        "",
        "```",
        format_table([(s.name, comp.table("tuned", 0)[s.name], s.paper)
                      for s in objective.scenarios], "tuned, nominal plant",
                     objective.settings.amplitude_scale),
        "",
        format_table([(s.name, comp.table("paper", 0)[s.name], s.paper)
                      for s in objective.scenarios], "paper gains, nominal plant",
                     objective.settings.amplitude_scale),
        "```",
        "",
        f"## Table 1 on the worst draw (#{wd.index}, {wd.label})",
        "",
        "The draw where the tuned controller's mean cost over the scenarios is highest; "
        f"plant in `{info['plant_worst']}`.",
        "",
        *_side_by_side(comp, objective, comp.worst_draw),
        "",
        "| draw | " + " | ".join(f"{k}" for k in wd.values) + " |",
        "|---|" + "---|" * len(wd.values),
        f"| #{wd.index} {wd.label} | " + " | ".join(f"{v:.4g}" for v in wd.values.values())
        + " |",
        "",
        "## Robustness: cost per scenario over the draws",
        "",
        "| scenario | tuned CVaR | tuned worst | paper CVaR | paper worst |",
        "|---|---|---|---|---|",
    ]
    for sc in objective.scenarios:
        out.append(f"| {sc.name} | {_fmt(comp.tuned.scenario_cvar.get(sc.name))} "
                   f"| {_fmt(comp.tuned.scenario_worst.get(sc.name))} "
                   f"| {_fmt(comp.paper.scenario_cvar.get(sc.name))} "
                   f"| {_fmt(comp.paper.scenario_worst.get(sc.name))} |")
    if comp.paper.failure:
        out += ["", f"The paper's gains fail a run: {comp.paper.failure}."]
    if comp.tuned.failure:
        out += ["", f"The tuned gains fail a run: {comp.tuned.failure}."]
    out += ["", *_heldout(comp)]
    tp = params_from_controller(tuned)
    pp = params_from_controller(paper)
    out += ["## Parameters", "",
            "| parameter | unit | range | paper | tuned | importance |",
            "|---|---|---|---|---|---|"]
    for p in objective.space.params:
        imp_s = f"{imp[p.name]:.3f}" if imp and p.name in imp else "-"
        out.append(f"| {p.name} | {p.unit} | [{p.low:.3g}, {p.high:.3g}]{' log' if p.log else ''}"
                   f" | {pp.get(p.name, p.paper):.4g} | {tp[p.name]:.4g} | {imp_s} |")
    ends = objective.space.at_ends(tp)
    if ends:
        out += ["", "**At a range end:** " + ", ".join(f"{n} ({e})" for n, e in ends)
                + f" (within {RANGE_END_SHARE:.0%} of the range's span). The search may have "
                "wanted a value beyond it, which more trials will not reach: the ranges are "
                "fixed (docs/tuning.md, \"The search space\", says why each is where it is)."]
    out += ["",
            f"Fixed: eps2 = {tuned.gains.eps2:g}, eps3 = {tuned.gains.eps3:g}, "
            f"r2 = {tuned.gains.r2:g}, motion R = {tuned.kalman.motion.R:.3g} m², "
            f"force R = {tuned.kalman.force.R:.3g} N², rate_max = "
            f"{list(tuned.adaptation.rate_max)}, θ box and θ_0 from the model.",
            "",
            "## Plots",
            "",
            f"![optimisation history]({info['history_png']})",
            "",
            f"![parameter importance]({info['importance_png']})",
            ""]
    return "\n".join(out)


def write_report(out_dir: str | os.PathLike[str], objective: TuneObjective,
                 study: optuna.Study, best: FrozenTrial, tuned: ControllerConfig,
                 paper: ControllerConfig, comp: Comparison, info: dict[str, Any]) -> Path:
    """Write ``report.md``, ``history.png`` and ``importance.png`` into ``out_dir``.

    Parameters
    ----------
    out_dir : path-like
    objective : TuneObjective
    study : optuna.Study
    best : FrozenTrial
    tuned, paper : ControllerConfig
    comp : Comparison
        From :func:`compare`.
    info : dict
        ``model``, ``model_sha256``, ``storage``, ``n_trials``, ``counts``, ``controller``,
        ``paper_path``, ``plant_nominal``, ``plant_worst`` (strings for the text).

    Returns
    -------
    Path
        The report.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plot_history(study, out / "history.png")
    imp = importances(study)
    plot_importance(imp, out / "importance.png")
    text = render(objective, study, best, tuned, paper, comp, imp,
                  {**info, "history_png": "history.png", "importance_png": "importance.png"})
    path = out / "report.md"
    atomic_write_text(path, text)
    return path


__all__ = ["HELDOUT_SEED_OFFSET", "Comparison", "HeldOut", "compare", "importances", "plot_history",
           "plot_importance", "render", "write_report"]
