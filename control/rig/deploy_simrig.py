"""The simulated rig in process as deploy and the example driver server use it.

:class:`DeploySimRig` is the :class:`~pneutune.control.rig.simrig.SimRig` of ``deploy --rig
sim``, of the example server behind ``--rig pipe-sim``
(:mod:`pneutune.control.rig.pipe_server`) and the base of the fault-injecting rig
(:class:`pneutune.control.rig.faults.FaultySimRig`).
"""

from __future__ import annotations

import numpy as np

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.plant import dynamics as plant
from pneutune.control.plant.params import PlantParams
from pneutune.control.rig.simrig import SimRig


class DeploySimRig(SimRig):
    """The in-process simulated rig as deploy and the example server use it.

    A :class:`~pneutune.control.rig.simrig.SimRig` whose compiled calls are loaded before the
    first sample (so a paced run's first sample is on time) and which keeps the duties last
    written (:attr:`last_duties`). Every :meth:`read` is a new sample on every channel. The
    sensor noise is drawn four standard normals per read from ``default_rng(seed)``, the same
    sequence as :func:`pneutune.control.sim.closed_loop.simulate_scenario` draws as one
    ``(n, 4)`` block, so a deploy run and a ``simulate`` run with the same seed see the same
    noise.

    Parameters
    ----------
    plant_cfg : PlantConfig or PlantParams
        The plant (with any scenario changes already merged).
    x0 : float, optional
        Initial position [m]; default mid-stroke. At rest, pressures in force balance.
    pressures0 : (float, float), optional
        Initial (p_a, p_b) [Pa abs].
    seed : int, optional
        Sensor-noise seed; default the plant's ``sim.seed``.
    sample_period : float, optional
        Sample period [s], dividing the plant's ``rig.Ts`` (:class:`SimRig`).
    """

    def __init__(self, plant_cfg: PlantConfig | PlantParams, x0: float | None = None,
                 pressures0: tuple[float, float] | None = None, seed: int | None = None,
                 sample_period: float | None = None) -> None:
        super().__init__(plant_cfg, x0=x0, pressures0=pressures0, seed=seed,
                         sample_period=sample_period)
        self.last_duties = np.zeros(4)
        self._warm_up()

    def _warm_up(self) -> None:
        """Run every compiled plant call once on a copy of the state (no noise drawn, no
        change to the rig), so that loading the compiled code does not delay the first
        sample of a paced run."""
        p = self.params
        s = self.state.copy()
        out = np.zeros(4)
        plant.measure(p.vec, s, self.supply, np.zeros(4), out)
        plant.truth(p.vec, s, self.supply, p.force_steps, np.zeros(6))
        plant.set_duties(p.vec, s, 0.0, np.zeros(4))
        plant.advance(p.vec, s, self.Ts, self.supply, p.force_steps)

    def write(self, duties: np.ndarray) -> None:
        """Command the four duties from now on (kept in :attr:`last_duties`)."""
        d = np.ascontiguousarray(duties, dtype=np.float64)
        self.last_duties = d.copy()
        super().write(d)


__all__ = ["DeploySimRig"]
