"""The seam between the controller runtime and a rig (hardware or simulation)."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Rig(Protocol):
    """What the runtime needs from a rig (hardware or simulation).

    Attributes
    ----------
    Ts : float
        Sampling period [s].
    t : float
        Time of the current sample [s] since the start of the run.
    """

    Ts: float
    t: float

    def read(self) -> np.ndarray:
        """Sensors at the current sample: [x [m], p_a, p_b, p_s [Pa abs]]."""
        ...

    def write(self, duties: np.ndarray) -> None:
        """Command the duties [a_in, a_out, b_in, b_out] (0..1) from the current sample on."""
        ...

    def advance(self) -> None:
        """Move to the next sample (simulation: integrate; hardware: wait for the tick)."""
        ...


__all__ = ["Rig"]
