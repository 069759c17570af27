"""``reports/summary.md``: the paper's Table 1 beside the paper's and the tuned config, simulated.

:func:`write_summary` takes metrics as ``deploy --json`` (or ``simulate --json``) prints them
and writes one Markdown table: scenario, the paper's Table 1 (measured on their rig), the
paper's config in simulation, the tuned config in simulation (E_p / E_rms in mm, the paper's
Sec. 5.1 indices over the last three periods) and links to the figures. It is also a command:

    python -m pneutune.control.summary --paper paper.json --tuned tuned.json \\
        --figures reports/deploy/figures --out reports/summary.md
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pneutune.control.contracts.atomic import atomic_write_text
from pneutune.control.errors import ExperimentError
from pneutune.control.sim.scenarios import SCENARIOS

Metrics = Mapping[str, Mapping[str, Any]]


def _scenarios_of(obj: Mapping[str, Any] | None) -> dict[str, Mapping[str, Any]]:
    """The per-scenario metrics of a ``--json`` object (or already the inner mapping)."""
    if obj is None:
        return {}
    inner = obj.get("scenarios", obj)
    if not isinstance(inner, Mapping):
        raise ExperimentError(f"expected a mapping of scenario metrics, got {type(inner)}")
    return dict(inner)


def _cell(m: Mapping[str, Any] | None) -> str:
    if m is None:
        return "–"
    ep, er = m.get("E_p_mm"), m.get("E_rms_mm")
    if ep is None or er is None or not (math.isfinite(ep) and math.isfinite(er)):
        text = "–"
    else:
        text = f"{ep:.2f} / {er:.2f}"
    status = m.get("status", "ok")
    return text if status == "ok" else f"{text} ({status})"


def _figure_links(scenario: str, figures: Mapping[str, Sequence[str | os.PathLike[str]]]
                  | str | os.PathLike[str] | None, base: Path) -> str:
    if figures is None:
        return ""
    if isinstance(figures, Mapping):
        files = [Path(f) for f in figures.get(scenario, ())]
    else:
        # exact: "<scenario>-<figure>.png" where <figure> is not itself "<suffix>-<figure>" of a
        # longer scenario name (sine-0.5hz must not pick up sine-0.5hz-heavy-*.png)
        longer = [s for s in SCENARIOS if s != scenario and s.startswith(scenario + "-")]
        files = sorted(f for f in Path(figures).glob(f"{scenario}-*.png")
                       if not any(f.stem.startswith(s + "-") for s in longer))
    links = []
    for f in files:
        label = f.stem[len(scenario) + 1:] if f.stem.startswith(scenario + "-") else f.stem
        target = os.path.relpath(f.resolve(), base.resolve())
        links.append(f"[{label}]({Path(target).as_posix()})")
    return ", ".join(links)


def _rig_phrase(sim: Mapping[str, Any]) -> str:
    """Which simulated rig a ``deploy --json`` output ran on, as the summary says it."""
    rig = str(sim.get("rig", "sim"))
    kind, _, plant = rig.partition(":")
    if kind in ("sim", "pipe-sim") and plant:
        return f"the simulated rig of `{plant}`"
    if kind in ("sim", "pipe-sim"):
        return "the simulated rig (plant.yaml defaults, the paper's rig without real-rig effects)"
    return f"the rig `{rig}`"


def summary_markdown(paper_sim: Mapping[str, Any], tuned_sim: Mapping[str, Any] | None = None,
                     figures: Mapping[str, Sequence[str | os.PathLike[str]]] | str
                     | os.PathLike[str] | None = None, base: str | os.PathLike[str] = ".",
                     title: str = "pneutune: tracking on the simulated rig") -> str:
    """The summary as Markdown text (see :func:`write_summary`)."""
    paper = _scenarios_of(paper_sim)
    tuned = _scenarios_of(tuned_sim)
    names = [n for n in SCENARIOS if n in paper or n in tuned]
    names += sorted(n for n in {*paper, *tuned} if n not in SCENARIOS)
    lines = [
        f"# {title}",
        "",
        "E_p / E_rms in mm: peak and RMS of the tracking error e1 over the last three periods of",
        "the reference (the paper's Sec. 5.1 indices). Paper: Table 1 of Qian et al. (2014),",
        f"measured on their rig. Simulation: `deploy` on {_rig_phrase(paper_sim)}, with the",
        "paper's controller (data/controller-paper.yaml) and with the tuned one",
        "(reports/tune/controller.yaml).",
        "",
        "| scenario | paper, Table 1 (rig) | paper's config (sim) | tuned config (sim) | figures |",
        "|---|---|---|---|---|",
    ]
    base_path = Path(base)
    for name in names:
        sc = SCENARIOS.get(name)
        ref = f"{sc.paper[0]:.2f} / {sc.paper[1]:.2f}" if sc is not None and sc.paper else "–"
        lines.append(f"| {name} | {ref} | {_cell(paper.get(name))} | "
                     f"{_cell(tuned.get(name)) if tuned_sim is not None else '–'} | "
                     f"{_figure_links(name, figures, base_path)} |")
    lines.append("")
    return "\n".join(lines)


def write_summary(path: str | os.PathLike[str], paper_sim: Mapping[str, Any],
                  tuned_sim: Mapping[str, Any] | None = None,
                  figures: Mapping[str, Sequence[str | os.PathLike[str]]] | str
                  | os.PathLike[str] | None = None,
                  title: str = "pneutune: tracking on the simulated rig") -> Path:
    """Write ``reports/summary.md`` atomically.

    Parameters
    ----------
    path : path-like
        The Markdown file.
    paper_sim : mapping
        Metrics of the paper's config in simulation: the ``deploy --json`` object, or its
        ``scenarios`` mapping ``{scenario: {"E_p_mm": .., "E_rms_mm": .., "status": ..}}``.
    tuned_sim : mapping, optional
        The same for the tuned config.
    figures : mapping or folder, optional
        ``{scenario: [png paths]}``, or a folder holding ``<scenario>-*.png``; linked relative
        to the summary's folder.
    title : str
        Heading.

    Returns
    -------
    Path
        The file written.
    """
    out = Path(path)
    text = summary_markdown(paper_sim, tuned_sim, figures, base=out.parent, title=title)
    atomic_write_text(out, text)
    return out


def _load_json(path: str) -> dict[str, Any]:
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:
        raise ExperimentError(f"{path}: cannot read the metrics JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ExperimentError(f"{path}: expected a JSON object")
    return data


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pneutune.control.summary``: write the summary from ``--json`` outputs."""
    parser = argparse.ArgumentParser(prog="python -m pneutune.control.summary",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--paper", required=True, help="deploy --json of the paper's config")
    parser.add_argument("--tuned", help="deploy --json of the tuned config")
    parser.add_argument("--figures", help="folder with <scenario>-*.png")
    parser.add_argument("--out", default="reports/summary.md", help="the Markdown file")
    args = parser.parse_args(argv)
    paper = _load_json(args.paper)
    tuned = _load_json(args.tuned) if args.tuned else None
    out = write_summary(args.out, paper, tuned, args.figures)
    print(out)
    return 0


__all__ = ["summary_markdown", "write_summary"]

if __name__ == "__main__":  # pragma: no cover
    from pneutune.control.cli.common import run_cli

    run_cli(main)
