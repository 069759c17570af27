"""Fault injection through the simulated rig, for the supervisor's tests and demonstrations.

:class:`FaultySimRig` is the in-process simulated rig
(:class:`~pneutune.control.rig.deploy_simrig.DeploySimRig`) with a list of :class:`Fault`
records, each active from its time ``t`` on. The plant and its noise are untouched (the same
noise draws happen every sample), so a faulty run equals the clean run up to the first fault.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError
from pneutune.control.plant.params import PlantParams
from pneutune.control.rig.deploy_simrig import DeploySimRig
from pneutune.control.rig.supervisor import CHANNELS

FaultKind = Literal["nan", "stale", "value", "offset", "supply"]
FAULT_KINDS: tuple[str, ...] = ("nan", "stale", "value", "offset", "supply")


@dataclass(frozen=True, slots=True)
class Fault:
    """One injected fault.

    Attributes
    ----------
    kind : str
        ``nan``: the channel reads NaN. ``stale``: the channel repeats its last reading and
        (unless ``stamp`` is False) its sample time stops (no new sample). ``value``: the
        channel reads ``value``. ``offset``: ``value`` is added to the channel's reading.
        ``supply``: the simulated supply pressure (the plant's, so the physics sees it too)
        becomes ``value`` [Pa abs].
    t : float
        From this rig time on [s].
    channel : str
        ``x``, ``p_a``, ``p_b`` or ``p_s`` (ignored by ``supply``).
    value : float
        See ``kind`` (SI units).
    stamp : bool
        ``stale`` only: whether the sample time freezes too. False models a rig that keeps
        delivering a frozen value as if new (seen only by the value-repetition rule).
    """

    kind: FaultKind
    t: float
    channel: str = "x"
    value: float = math.nan
    stamp: bool = True

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ExperimentError(f"fault kind must be one of {FAULT_KINDS}, got {self.kind!r}")
        if self.channel not in CHANNELS:
            raise ExperimentError(f"fault channel must be one of {CHANNELS}, "
                                  f"got {self.channel!r}")
        if not self.t >= 0.0:
            raise ExperimentError(f"fault time must be >= 0 s, got {self.t}")
        if self.kind in ("value", "offset", "supply") and not math.isfinite(self.value):
            raise ExperimentError(f"a {self.kind} fault needs a finite value, got {self.value}")


class FaultySimRig(DeploySimRig):
    """The simulated rig with injected faults.

    Parameters
    ----------
    plant_cfg : PlantConfig or PlantParams
        The plant.
    faults : sequence of Fault
        What goes wrong, and when: on the rig's clock from its start, a homing move included
        (unlike the plant's force steps, which follow the scenario's start).
    x0, pressures0, seed
        As :class:`~pneutune.control.rig.deploy_simrig.DeploySimRig`.
    report_sample_times : bool
        False: :meth:`sample_times` returns None (a rig that cannot tell a new sample from an
        old one; the supervisor then judges staleness on the values).
    """

    def __init__(self, plant_cfg: PlantConfig | PlantParams, faults: Sequence[Fault] = (),
                 x0: float | None = None, pressures0: tuple[float, float] | None = None,
                 seed: int | None = None, report_sample_times: bool = True) -> None:
        super().__init__(plant_cfg, x0=x0, pressures0=pressures0, seed=seed)
        self.faults = tuple(faults)
        self.report_sample_times = report_sample_times
        self._prev = np.full(4, np.nan)
        self._stamps = np.zeros(4)
        self._nominal_supply = self.supply

    def _active(self, fault: Fault) -> bool:
        return self.t >= fault.t - 1e-12

    def read(self) -> np.ndarray:
        """Sensors at the current sample, with the active faults applied."""
        for f in self.faults:
            if f.kind == "supply" and self._active(f):
                self.supply = f.value
        vals = super().read()
        fresh = np.ones(4, dtype=bool)
        for f in self.faults:
            if f.kind == "supply" or not self._active(f):
                continue
            i = CHANNELS.index(f.channel)
            if f.kind == "nan":
                vals[i] = np.nan
            elif f.kind == "value":
                vals[i] = f.value
            elif f.kind == "offset":
                vals[i] += f.value
            elif f.kind == "stale":
                vals[i] = self._prev[i]
                if f.stamp:
                    fresh[i] = False
        self._stamps[fresh] = self.t
        self._prev = vals.copy()
        return vals

    def sample_times(self) -> np.ndarray | None:
        """Time each channel last delivered a new value (a stale channel's stops)."""
        return self._stamps.copy() if self.report_sample_times else None


__all__ = ["FAULT_KINDS", "Fault", "FaultySimRig"]
