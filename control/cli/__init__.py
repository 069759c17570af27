"""The commands simulate and deploy, the deploy summary and the closed-loop figures.

Layer 8, the top: imports every layer below; nothing in pneutune.control imports it.
"""
