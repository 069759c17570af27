"""The simulated rig's physics: packed parameters, the valves switching inside each PWM period, and
the
plant's dynamics (Sec. 2 of the paper, every term), compiled with numba.

Layer 4: imports physics, contracts and logs.
"""
