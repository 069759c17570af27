"""What an excitation protocol run holds, and what a run cut short lacks.

The identification and commissioning runs (control/rig/identification_run.py,
control/rig/commissioning_run.py) label every segment on ``/experiment/segment``. A run that is
interrupted (Ctrl-C, a fault) leaves a log of the segments it got through. identify fits on the
samples alone, labels or not; the labels serve only to say, in the notes, which kinds of
excitation a run cut short lacks and what each fit then rests on (another log, a prior), and
to keep the mass's lag estimate off a run without its acceleration segments
(:func:`lacks_mass_segments`).
"""

from __future__ import annotations

from dataclasses import dataclass

from pneutune.control.constants import VALVES

from .dataset import Dataset

#: Segment kinds of each protocol, in the order they run.
PROTOCOL_KINDS: dict[str, tuple[str, ...]] = {
    "identification": ("rest", "prepare", "valve_charge", "valve_discharge", "hold",
                       "constant_speed", "acceleration"),
    "commissioning": ("rest", "prepare", "valve_charge", "valve_discharge", "hold",
                      "constant_speed", "burst", "brake", "coast"),
}
#: The kinds of each protocol that excite the moving mass.
MASS_KINDS: dict[str, tuple[str, ...]] = {"identification": ("acceleration",),
                                          "commissioning": ("burst", "brake", "coast")}
#: The ``record --segments`` group of each protocol that holds those kinds.
MASS_GROUPS: dict[str, str] = {"identification": "acceleration", "commissioning": "bursts"}
#: Both protocols end with this segment.
LAST_LABEL = "rest:end"
#: The words for each kind in the notes.
KIND_WORDS = {"valve_charge": "valve charges", "valve_discharge": "valve discharges",
              "constant_speed": "constant-speed", "acceleration": "acceleration",
              "burst": "burst", "brake": "brake", "coast": "coast", "rest": "rest",
              "prepare": "prepare", "hold": "hold"}


@dataclass(frozen=True)
class Coverage:
    """The segments of one protocol run.

    Attributes
    ----------
    name : str
        The log's short name.
    experiment : str
        ``identification`` or ``commissioning`` (the run record's, else from the kinds seen).
    missing : tuple of str
        Kinds of the protocol the log has no segment of.
    cut_short : bool
        A fault or an interrupt stopped the run (its run record's ``status``); for a log whose
        run record does not say, the log does not reach the protocol's last segment
        (:data:`LAST_LABEL`).
    last_label : str
        The segment the run stopped in (the run record's ``stopped_in``), else the last
        segment started.
    last_t, end_t : float
        When it started and the log's last sample [s].
    untested : tuple of str
        Valves with no valve test (charge or discharge) of their own.
    selection : str
        The ``record --segments`` selection the run was made of, or "".
    """

    name: str
    experiment: str
    missing: tuple[str, ...]
    cut_short: bool
    last_label: str
    last_t: float
    end_t: float
    untested: tuple[str, ...]
    selection: str = ""

    @property
    def partial(self) -> bool:
        """Whether the run is cut short or lacks a kind of segment."""
        return self.cut_short or bool(self.missing)

    def lacks(self, *kinds: str) -> bool:
        """Whether the run has no segment of any of ``kinds`` (kinds of its protocol only)."""
        return any(k in self.missing for k in kinds)

    def summary(self) -> str:
        """One note: what the run holds and lacks."""
        what = (f"log {self.name}: an {self.experiment} run" if self.experiment[0] in "aeiou"
                else f"log {self.name}: a {self.experiment} run")
        if self.selection:
            what += f" of the segments '{self.selection}'"
        if self.cut_short:
            what += (f" cut short in segment '{self.last_label}' (the log ends at "
                     f"{self.end_t:.1f} s)")
        if self.missing:
            words = ", ".join(KIND_WORDS.get(k, k) for k in self.missing)
            what += f"; it has no {words} segments"
        return what


def coverage(data: Dataset, name: str) -> Coverage | None:
    """The protocol coverage of a labelled log; None for a log without segment labels or
    one that is no protocol run (a closed-loop log labels its scenario).

    Parameters
    ----------
    data : Dataset
        The log (its ``segments`` and ``experiment``).
    name : str
        Its short name.
    """
    if not data.segments:
        return None
    kinds = {k for _, _, k in data.segments}
    exp = data.experiment
    if exp not in PROTOCOL_KINDS:
        # no protocol named: a protocol run if its segments are of a protocol's kinds (a
        # closed-loop log labels its scenario, kind "scenario")
        if "scenario" in kinds or not kinds & {k for ks in PROTOCOL_KINDS.values() for k in ks}:
            return None
        exp = ("commissioning" if kinds & set(MASS_KINDS["commissioning"])
               else "identification")
    missing = tuple(k for k in PROTOCOL_KINDS[exp] if k not in kinds)
    tested = set()
    for _, label, kind in data.segments:
        parts = label.split(":")
        if kind in ("valve_charge", "valve_discharge") and len(parts) > 1 and parts[1] in VALVES:
            tested.add(parts[1])
    t_last, label_last, _ = data.segments[-1]
    if data.run_status:
        cut_short = data.run_status != "ok"
    else:  # a log whose run record does not say how it ended
        cut_short = label_last != LAST_LABEL and not data.selection
    return Coverage(name=name, experiment=exp, missing=missing, cut_short=cut_short,
                    last_label=data.stopped_in or label_last,
                    last_t=t_last, end_t=float(data.t[-1]) if data.n else 0.0,
                    untested=tuple(v for v in VALVES if v not in tested),
                    selection=data.selection)


def lacks_mass_segments(cov: Coverage | None) -> bool:
    """Whether a protocol run has none of the segments that excite the mass.

    The lag estimate of the mass (:mod:`.mass`) then rests on the constant-speed ramps alone,
    whose force barely changes: on data/run.mcap cut before its sines (seed 1, default plant,
    M = 1.05 kg) it gave 0.956 kg in [0.829, 1.035] kg, an interval that misses the truth.
    Such a run does not enter the mass estimate.
    """
    return cov is not None and cov.lacks(*MASS_KINDS[cov.experiment])


__all__ = ["KIND_WORDS", "LAST_LABEL", "MASS_GROUPS", "MASS_KINDS", "PROTOCOL_KINDS", "Coverage",
           "coverage", "lacks_mass_segments"]
