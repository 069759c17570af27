"""The end-stop contacts of an excitation run, measured from its recording.

Every approach onto an end stop (a segment of kind ``approach`` naming its stop in
:attr:`~pneutune.control.rig.identification_run.Segment.contacts`) is measured: the speed of the
piston over the :data:`CONTACT_WINDOW` before it reached the stop (:func:`measure_contacts`).
The supervised runner (:func:`~pneutune.control.rig.excitation.execute_protocol`) logs each as
an ``end_stop_contact`` event, or a ``contact_speed`` warning when it exceeds
:data:`CONTACT_WARN_FACTOR` times the planned speed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pneutune.control.logs.recording import Recording
from pneutune.control.rig.identification_run import STOP_SIDES, Segment

#: Window of the contact speed [s] before the piston reached the stop.
CONTACT_WINDOW: float = 0.004
#: The piston has reached the stop when it is this close to where it came to rest [m].
CONTACT_BAND: float = 3.0e-4
#: A contact faster than this multiple of the planned speed is a ``contact_speed`` warning.
#: The position loop tracks the approach ramp with a lag; a piston that sticks first and then
#: breaks away catches up faster than the ramp (1.5 times it on the paper's rig).
CONTACT_WARN_FACTOR: float = 2.0


@dataclass(frozen=True)
class Contact:
    """One measured approach onto an end stop.

    Attributes
    ----------
    stop : str
        ``x_min`` or ``x_max``.
    segment : str
        Label of the approach segment.
    t : float
        Time the piston reached the stop [s].
    speed : float
        Its speed toward the stop over :data:`CONTACT_WINDOW` before [m/s].
    planned : float
        The approach's planned speed [m/s].
    """

    stop: str
    segment: str
    t: float
    speed: float
    planned: float

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (JSON)."""
        return dataclasses.asdict(self)


def measure_contacts(rec: Recording, segments: Sequence[Segment]) -> list[Contact]:
    """The end-stop contacts of the approach segments in a recording.

    The piston comes to rest on the stop during the approach or the segment after it; it has
    reached the stop at the first sample within :data:`CONTACT_BAND` of that resting position,
    and its speed is the position's change over the :data:`CONTACT_WINDOW` before.

    Parameters
    ----------
    rec : Recording
        The run; ``rec.segments_`` starts the segments.
    segments : sequence of Segment
        The segments of the recording, in order.

    Returns
    -------
    list of Contact
    """
    starts = [round(t / rec.Ts) for t, *_ in rec.segments_] + [rec.n]
    w = max(1, round(CONTACT_WINDOW / rec.Ts))
    out: list[Contact] = []
    for i, seg in enumerate(segments):
        if seg.kind != "approach" or not seg.contacts or i + 1 >= len(starts):
            continue
        stop = seg.contacts[0]
        side = STOP_SIDES[stop]
        k0 = starts[i]
        k1 = starts[min(i + 2, len(starts) - 1)]  # the approach and the segment after it
        x = rec.sensors_[k0:k1, 0]
        rest_n = max(2, round(0.2 / rec.Ts))
        if x.size < rest_n + w + 1:
            continue
        x_end = float(np.median(x[-rest_n:]))
        near = np.nonzero(side * (x - x_end) >= -CONTACT_BAND)[0]
        if near.size == 0 or near[0] < w:
            continue
        kc = int(near[0])
        speed = side * (x[kc] - x[kc - w]) / (w * rec.Ts)
        out.append(Contact(stop, seg.label, (k0 + kc) * rec.Ts, float(speed),
                           float(seg.params.get("speed", math.nan))))
    return out


__all__ = [
    "CONTACT_BAND",
    "CONTACT_WARN_FACTOR",
    "CONTACT_WINDOW",
    "Contact",
    "measure_contacts",
]
