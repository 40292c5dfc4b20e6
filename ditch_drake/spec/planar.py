"""Planar angles shared by drivers and sensors."""

import math

from pydrake.math import RigidTransform


def wrap_to_pi(angle: float) -> float:
    """Wraps an angle (rad) to (-pi, pi]."""
    wrapped = math.remainder(angle, 2 * math.pi)
    return math.pi if wrapped <= -math.pi else wrapped


def planar_yaw(X_WB: RigidTransform) -> float:
    """Heading (rad) of the chassis x-axis projected on the ground plane.

    Unlike the yaw of `RollPitchYaw`, this stays the direction the robot drives in
    when the chassis is pitched or rolled. A vertical x-axis reads 0.
    """
    R_WB = X_WB.rotation().matrix()
    return math.atan2(R_WB[1, 0], R_WB[0, 0])
