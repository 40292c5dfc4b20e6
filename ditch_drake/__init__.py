"""ditch_drake: negative-obstacle traversal by behavioural cloning, built on Drake."""

import sys

__version__ = "0.1.0"

if "gymnasium" in sys.modules:
    # Registers the "DitchDrake-v0" environment (`ditch_drake.gym`) for a program that uses
    # Gymnasium, without making the command line pay for importing it.
    from ditch_drake.gym import register as _register_gym_env

    _register_gym_env()
