"""The valve fit's table of port flows (identify/valve_flows.py): the floats of
:func:`~pneutune.control.physics.flow.signed_flow_array`, computed once per parameter value."""

from __future__ import annotations

import numpy as np
import pytest

from pneutune.control.physics.flow import signed_flow_array
from pneutune.identify.valve_flows import A_IN, A_OUT, LEAK, PortFlows


def _ports() -> list[tuple[np.ndarray | float, np.ndarray | float]]:
    rng = np.random.default_rng(1)
    pa, pb = rng.uniform(1.0e5, 6.0e5, 500), rng.uniform(1.0e5, 6.0e5, 500)
    ps = np.full(500, 6.0e5)
    return [(ps, pa), (pa, 101325.0), (ps, pb), (pb, 101325.0), (pa, pb)]


def test_flows_are_signed_flow_array_and_looked_up():
    """Each port's flow is signed_flow_array's, the same array again for the same C and b, a
    new one for another, and read-only."""
    ports = _ports()
    flows = PortFlows(ports, 293.15)
    for port, (C, b) in ((A_IN, (8e-9, 0.19)), (A_OUT, (7e-9, 0.3)), (LEAK, (2e-11, 0.0))):
        got = flows(port, C, b)
        assert np.array_equal(got, signed_flow_array(C, b, *ports[port], 293.15))
        assert flows(port, C, b) is got
        assert flows(port, C * (1.0 + 1e-15), b) is not got
        with pytest.raises(ValueError):
            got[0] = 0.0


def test_least_recently_used_flows_are_dropped():
    """Past ``keep`` flows the least recently used one is computed afresh."""
    flows = PortFlows(_ports(), 293.15, keep=2)
    first = flows(A_IN, 1e-9, 0.2)
    second = flows(A_IN, 2e-9, 0.2)
    assert flows(A_IN, 1e-9, 0.2) is first  # used again: now the most recent
    flows(A_IN, 3e-9, 0.2)  # drops the 2e-9 one
    assert flows(A_IN, 1e-9, 0.2) is first
    assert flows(A_IN, 2e-9, 0.2) is not second
