"""Contract 1, the MCAP run log: its topics, the writer and the typed-error reader, and the
per-sample recording of a run.

Layer 3: imports physics and contracts.
"""
