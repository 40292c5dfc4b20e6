"""Goal sensor: planar distance and bearing from the chassis to the goal."""

import math

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec.observation_layout import BEARING_SIZE, DISTANCE_SIZE
from ditch_drake.spec.planar import planar_yaw, wrap_to_pi


def distance_bearing(X_WB: RigidTransform, goal_xy) -> tuple[float, float]:
    """Planar distance (m) and bearing (rad, in (-pi, pi]) from the chassis origin to `goal_xy`.

    The bearing is the goal direction minus `planar_yaw(X_WB)`: positive when the goal
    lies to the robot's left. At zero distance the goal direction reads 0.
    """
    p_WB = X_WB.translation()
    dx, dy = float(goal_xy[0]) - float(p_WB[0]), float(goal_xy[1]) - float(p_WB[1])
    return math.hypot(dx, dy), wrap_to_pi(math.atan2(dy, dx) - planar_yaw(X_WB))


class GoalSensor(LeafSystem):
    """Reads the planar distance and bearing from the chassis origin to a goal (or to a target
    given at its `goal_xy` input).

    distance = |p_goal - p_WB| in the x-y plane; bearing = atan2 of that
    difference minus the chassis's planar yaw (the heading of its x-axis projected
    on the ground), wrapped to (-pi, pi]: 0 straight ahead, positive to the left.

    The outputs are computed from the current body poses (direct feedthrough,
    cheap), so a system sampling them at a control tick sees the pose at that tick.
    The same numbers come as one 2-vector and as two 1-vectors; the separate
    `distance` and `bearing` ports connect straight to `FrameStacker`'s inputs.

    .. pydrake_system::

        name: GoalSensor
        input_ports:
        - body_poses
        - goal_xy (optional)
        output_ports:
        - distance_bearing
        - distance
        - bearing

    Ports:
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        goal_xy: (only with `goal_input`) the planar point (m, W) read in place of the fixed
            goal: a route-level target such as `WindowSearch`'s.
        distance_bearing: [distance (m), bearing (rad)].
        distance: [distance (m)].
        bearing: [bearing (rad)].
    """

    def __init__(self, chassis_body_index, goal_xy, goal_input: bool = False):
        """Args:
            chassis_body_index: the chassis's BodyIndex in the plant.
            goal_xy: the goal's (x, y) in the world (m).
            goal_input: with it, a `goal_xy` input that the outputs are read to in place of `goal_xy`.
        """
        super().__init__()
        self._chassis_index = int(chassis_body_index)
        self._goal_xy = (float(goal_xy[0]), float(goal_xy[1]))
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._goal_port = self.DeclareVectorInputPort("goal_xy", 2) if goal_input else None
        tickets = {self.input_port_ticket(port.get_index()) for port in (self._poses_port, self._goal_port)
                   if port is not None}
        self.DeclareVectorOutputPort(
            "distance_bearing", DISTANCE_SIZE + BEARING_SIZE, self._calc_distance_bearing,
            prerequisites_of_calc=tickets)
        self.DeclareVectorOutputPort("distance", DISTANCE_SIZE, self._calc_distance, prerequisites_of_calc=tickets)
        self.DeclareVectorOutputPort("bearing", BEARING_SIZE, self._calc_bearing, prerequisites_of_calc=tickets)

    @property
    def goal_xy(self) -> tuple[float, float]:
        """The fixed goal's (x, y) in the world (m); with a `goal_xy` input, the input is read instead."""
        return self._goal_xy

    def _read(self, context) -> tuple[float, float]:
        goal_xy = self._goal_xy if self._goal_port is None else self._goal_port.Eval(context)
        return distance_bearing(self._poses_port.Eval(context)[self._chassis_index], goal_xy)

    def _calc_distance_bearing(self, context, output: BasicVector) -> None:
        output.SetFromVector(np.array(self._read(context)))

    def _calc_distance(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self._read(context)[0])

    def _calc_bearing(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self._read(context)[1])
