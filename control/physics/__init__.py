"""The equations of the physics, once: ISO 6358 valve flow (Eq. 7), Stribeck friction (Eq. 2) and
the smooth
sign S_f (Eq. 4), the steady PWM curve. Scalar (numba) and vectorised (numpy) forms side by side.

Layer 1 of pneutune.control: imports only constants and errors.
"""
