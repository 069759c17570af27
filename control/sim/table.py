"""The text table of closed-loop metrics beside the paper's Table 1, for every report.

``simulate`` and ``deploy`` print it, tune's report.md embeds it; it lives here, below all three,
so that none of them imports another's command-line module.
"""

from __future__ import annotations

from typing import Any


def format_table(rows: list[tuple[str, dict[str, Any], tuple[float, float] | None]],
                 title: str, scale: float = 1.0) -> str:
    """A text table of the metrics beside the paper's Table 1 (rig) figures; ``scale`` is the
    references' amplitude against the paper's when they were scaled to a short stroke (the
    figures in ``rows`` are then Table 1's times it, and the footnote says so)."""
    head = (f"{'scenario':<19}{'E_p [mm]':>9}{'E_rms [mm]':>11}{'paper E_p':>10}"
            f"{'paper E_rms':>12}{'switch/s':>9}{'p_a max':>9}{'p_b max':>9}  status")
    lines = [title, head, "-" * len(head)]
    for name, m, paper in rows:
        pe = f"{paper[0]:.2f}" if paper else "-"
        pr = f"{paper[1]:.2f}" if paper else "-"
        lines.append(f"{name:<19}{m['E_p_mm']:>9.3f}{m['E_rms_mm']:>11.3f}{pe:>10}{pr:>12}"
                     f"{m['switches_per_s']:>9.1f}{m['p_a_max_Pa'] / 1e5:>8.2f}b"
                     f"{m['p_b_max_Pa'] / 1e5:>8.2f}b  {m['status']}"
                     f"{'' if m['theta_in_bounds'] else ' (theta out of bounds!)'}")
    scaled = "" if scale == 1.0 else (f", times {scale:.3f} with the references scaled to a "
                                      "short stroke")
    lines.append(f"paper: Table 1 of Qian et al. (2014), measured on their rig{scaled}; the "
                 "rest is this simulation.")
    return "\n".join(lines)


__all__ = ["format_table"]
