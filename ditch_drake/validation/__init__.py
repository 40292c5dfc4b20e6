"""Validation of the simulation against physics and of the MPPI's attitude model: the calibration
benchmark (`ditch-drake calibrate`) and the MPPI's predicted attitude against the plant's."""
