"""Closed-loop simulation: scenarios (Table 1), the compiled loop of plant and law with its metrics,
the model read as plants (its box and corners) and the truth model of a plant.

Layer 6: imports every layer below.
"""
