"""The seam between the controller runtime and a rig (hardware or simulation): one protocol.

:class:`Rig` is everything the deploy runtime (:mod:`pneutune.control.rig.runtime`) and the
excitation protocols (:mod:`pneutune.control.rig.identification_run`) call; a
:class:`SimulatedRig` also tells the truth a real rig cannot measure (``/sim/truth``).

Implementations shipped: :class:`pneutune.control.rig.simrig.SimRig` and its subclasses
:class:`~pneutune.control.rig.deploy_simrig.DeploySimRig` and
:class:`~pneutune.control.rig.faults.FaultySimRig` (in process),
:class:`~pneutune.control.rig.exec_rig.ExecRig` (any driver program speaking the pipe protocol
``pneutune.rig/1``) and :class:`~pneutune.control.rig.exec_rig.PipeRig` (the example simulated
rig in a child process).

The contract (docs/deploy.md has the long form)
-----------------------------------------------
Units: SI. Positions in m, pressures in Pa *absolute*, duties 0..1 in the valve order
``a_in, a_out, b_in, b_out``, times in s on the rig's clock, which starts at 0.

``Ts``
    The sampling period [s]; it must equal the controller's ``rig.Ts`` (``deploy`` checks it).
``t``
    Time of the current sample, ``k Ts`` after ``k`` calls of :meth:`Rig.advance`.
``read()``
    The sensors at the current sample ``[x, p_a, p_b, p_s]``: the latest value of each
    channel, taken as close to the tick as the hardware allows; call once per sample. A channel
    that has never delivered reads NaN. Must not block longer than ~Ts/10.
``sample_times()``
    Rig time at which each channel last delivered a *new* value, or None when the rig cannot
    tell. The supervisor's staleness rule uses it; without it a frozen position cannot be told
    from a piston at rest.
``write(duties)``
    Command the four duties from now on. Non-blocking. How a new duty takes effect within the
    running PWM period is the rig's ``pwm_update`` (``immediate``: at once, comparator;
    ``latched``: at the next period start). Duties outside [0, 1] are a programming error.
``advance()``
    Return when the next sample is due (hardware: block until the tick; simulation: integrate
    to it). **Missed deadline**: if it is called after the next tick has passed, it returns at
    once and the sample is *late*, never skipped (skipping would break the controller's fixed
    Ts); the driver counts it. The runtime reports overruns and jitter; a rig that stops
    ticking is caught by ``limits.sensor_timeout_s``.
``rig_metadata()``
    The ``rig`` block of the rig (:data:`~pneutune.control.constants.RIG_KEYS`), written to
    the run log so that ``identify`` knows the geometry and timing.
``close()``
    Write the fail-safe duties (all valves closed,
    :data:`pneutune.control.rig.supervisor.FAIL_SAFE_DUTIES`) and release the hardware;
    idempotent. A driver must reach the same state by itself when its client disappears (end
    of file on its input, a crash) and, on hardware, through a watchdog that cuts the coil
    power when no ``write`` came for ``sensor_timeout_s``: normally-closed valves are then
    all closed.
``truth()`` (:class:`SimulatedRig` only)
    ``[v, a, F_friction, F_ext, mdot_a, mdot_b]`` at the current sample, the ``/sim/truth``
    fields of contract 1.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Rig(Protocol):
    """What the runtime needs from a rig, hardware or simulation (module docstring)."""

    @property
    def Ts(self) -> float:
        """Sampling period [s]."""
        ...

    @property
    def t(self) -> float:
        """Time of the current sample [s] since the start of the run."""
        ...

    def read(self) -> np.ndarray:
        """Sensors at the current sample: [x [m], p_a, p_b, p_s [Pa abs]]."""
        ...

    def sample_times(self) -> np.ndarray | None:
        """Rig time each channel last delivered a new value [s], or None if unknown."""
        ...

    def write(self, duties: np.ndarray) -> None:
        """Command the duties [a_in, a_out, b_in, b_out] (0..1) from the current sample on."""
        ...

    def advance(self) -> None:
        """Return when the next sample is due (late, never skipped, on a missed deadline)."""
        ...

    def rig_metadata(self) -> dict[str, float | str]:
        """The ``rig`` block of this rig (every key of RIG_KEYS)."""
        ...

    def close(self) -> None:
        """Write the fail-safe duties (all valves closed) and release the rig; idempotent."""
        ...


@runtime_checkable
class SimulatedRig(Rig, Protocol):
    """A :class:`Rig` that also knows what a real rig cannot measure."""

    def truth(self) -> np.ndarray:
        """``[v, a, F_friction, F_ext, mdot_a, mdot_b]`` at the current sample (SI)."""
        ...


__all__ = ["Rig", "SimulatedRig"]
