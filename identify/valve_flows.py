"""Fully open ISO 6358 flows through the valve ports over a log's samples, computed once each.

The valve fit (:class:`~pneutune.identify.valves.ValveIdentifier`) evaluates the flow of each
port (:func:`pneutune.control.physics.flow.signed_flow_array`) for every residual, and most of
those evaluations repeat one made before: a finite-difference Jacobian moves the parameters of
one valve per chamber at a time, and the timing search uses one set of flows for hundreds of
candidates. :class:`PortFlows` keeps the flows of the last parameter values per port and hands
the same array back for the same floats (read-only, so that no caller changes it).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from pneutune.control.physics.flow import signed_flow_array

#: Port indices: the four valves (their upstream and downstream pressures) and the seal leak.
A_IN, A_OUT, B_IN, B_OUT, LEAK = range(5)


class PortFlows:
    """``signed_flow_array(C, b, p_1, p_2, T0)`` per port, looked up for repeated ``C, b``.

    Parameters
    ----------
    ports : sequence of (ndarray or float, ndarray or float)
        Per port index (:data:`A_IN` .. :data:`LEAK`), the pressures on its two sides [Pa]:
        the flow is positive from the first to the second.
    T0 : float
        Supply temperature [K].
    keep : int
        Flows kept (least recently used dropped).
    """

    def __init__(self, ports: Sequence[tuple[np.ndarray | float, np.ndarray | float]],
                 T0: float, keep: int = 32) -> None:
        self._ports = list(ports)
        self._T0 = T0
        self._keep = keep
        self._flows: OrderedDict[tuple[int, str, str], np.ndarray] = OrderedDict()

    def __call__(self, port: int, C: float, b: float) -> np.ndarray:
        """Mass flow per sample through ``port`` fully open [kg/s] (a read-only array).

        Parameters
        ----------
        port : int
            Port index.
        C : float
            Sonic conductance [m^3/(s Pa)].
        b : float
            Critical pressure ratio [-].

        Returns
        -------
        ndarray
            The flow of :func:`~pneutune.control.physics.flow.signed_flow_array`, the same
            floats; the same array for the same ``port``, ``C`` and ``b``.
        """
        key = (port, float(C).hex(), float(b).hex())  # hex: tells 0.0 from -0.0
        flow = self._flows.get(key)
        if flow is not None:
            self._flows.move_to_end(key)
            return flow
        p_1, p_2 = self._ports[port]
        flow = signed_flow_array(C, b, p_1, p_2, self._T0)
        flow.flags.writeable = False
        self._flows[key] = flow
        if len(self._flows) > self._keep:
            self._flows.popitem(last=False)
        return flow


__all__ = ["A_IN", "A_OUT", "B_IN", "B_OUT", "LEAK", "PortFlows"]
