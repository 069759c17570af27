"""Everything that runs against a rig: the Rig protocol, the simulated rig, the pipe protocol and
its
example driver, fault injection, the safety supervisor, the deploy runtime and the excitation
protocols (identification and commissioning runs).

Layer 7: imports every layer below.
"""
