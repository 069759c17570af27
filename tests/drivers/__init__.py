"""Rig drivers speaking ``pneutune.rig/1``, run as programs by path (``--rig exec:``).

Each is a standalone script. ``other_sim_driver`` is also imported by tests/test_other_sim.py,
which checks its physics on its simulator directly; ``benchmarks/other_sim.py`` runs it by path
and never imports it.
"""
