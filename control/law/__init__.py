"""The control law: the modified DARC (Eqs. 9-33), its Kalman filters (Sec. 4), the projection
(Eqs. 10-12), the duty logic (Eqs. 32-33) and the packed config vector the compiled step reads.

Layer 5: imports physics, contracts, logs and plant.
"""
