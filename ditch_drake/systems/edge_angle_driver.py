"""A scripted driver that crosses a ditch holding an angle to the local edge."""

import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.common.config_yaml import WRITTEN_WHEN_SET
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw, wrap_to_pi
from ditch_drake.world.crossing import approach_side
from ditch_drake.world.terrain import DitchTerrain


@dataclass
class EdgeAngleDriverConfig:
    """How the scripted driver crosses (angles in degrees, lengths in m).

    Attributes:
        wall_angle_deg: heading angle to the local edge going down a wall and in
            the approach zone; 90 drives head-on, perpendicular to the edge.
        climb_angle_deg: heading angle to the local edge going up a wall; on a
            steep wall the wheels slip sideways, so climbing needs a steeper
            heading than descending to gain height (docs/concepts/physics.md). None: the
            same as `wall_angle_deg`.
        bottom_angle_deg: angle to the edge while crossing the interior of a wide bottom.
        approach_margin_m: how far before the hinge line the driver is already
            holding `wall_angle_deg`, so that it turns on flat ground.
        bottom_margin_m: distance from the toe within which the bottom counts as wall.
        heading_gain: yaw-rate command per radian of heading error (1/s).
        speed_mps: forward speed.
        straight_across_deg: when the goal lies within this angle of straight across
            the ditch, the driver always turns right along the edge (a convention);
            otherwise toward the goal's side. Turning to a random side where the goal
            gives no reason would teach a behavioural clone two opposite answers to the
            same observation, whose average (straight on, head-on down the wall) is the
            one thing it must not do.
        replan_each_step: False latches the plan (the side along the edge, chosen
            before the wall, and the phase: descend, climb, exited) as a driver who
            committed to it would. True decides both afresh from the current pose at
            every step: the side along the edge is the one the robot already faces
            once it is on a wall, and the phase follows from which side of the ditch's
            course the robot and the goal are on (a robot facing the edge within
            `straight_across_deg` of square on takes the approach convention's side).
            For labelling a learner's states (DAgger): a learner off the latched plan's
            line gets the answer to where it is, not a U-turn back to the plan on a
            steep wall.
        keep_facing_side: in the approach zone, before the hinge, cross on the side along the
            edge the robot already faces, wherever it faces more than `straight_across_deg` off
            square on (else the side chosen so far, or the approach convention's). For a driver
            that takes over from another one (the shared-control fallback): handed a robot that
            approaches on one side, a driver latched on the other turns through head-on at the
            hinge to reach it. Driving alone it changes little, since it turns to the side it
            chose as it enters the zone and then faces it.
        lead_in: make room for the crossing first. Down the wall at `wall_angle_deg`
            and up at the climb angle the robot travels a long way along the ditch, in
            the narrow ditch more than a 30 m ditch leaves from its middle, and a
            crossing from there ends in the ditch's rounded end. With
            `lead_in`, on the flat before the approach zone, when the course ahead in
            the chosen direction along the edge is shorter than the crossing needs
            (`crossing_length_m`), the driver first heads for a lead-in point on the
            flat that leaves `lead_in_extra_m` more than that, `lead_in_offset_m`
            beyond the approach zone, and turns into the approach from there.
        lead_in_extra_m: course kept beyond the crossing's need at the lead-in point (m).
        lead_in_offset_m: how far outside the approach zone the lead-in point lies (m).
    """

    wall_angle_deg: float = 20.0
    climb_angle_deg: float | None = 35.0
    bottom_angle_deg: float = 60.0
    approach_margin_m: float = 2.5
    bottom_margin_m: float = 1.0
    heading_gain: float = 1.5
    speed_mps: float = robot.MAX_SPEED_MPS
    straight_across_deg: float = 15.0
    replan_each_step: bool = False
    keep_facing_side: bool = field(default=False, metadata=WRITTEN_WHEN_SET)
    lead_in: bool = False
    lead_in_extra_m: float = 1.5
    lead_in_offset_m: float = 1.0


DESCEND, CLIMB, EXITED = 0, 1, 2


class EdgeAngleDriver(LeafSystem):
    """Drives to a goal across a ditch, holding an angle to the local edge.

    Knows the terrain analytically. On flat ground it heads for the goal; within
    `approach_margin_m` of the hinge, on the walls and near the toe it heads at
    `wall_angle_deg` to the local edge (the edge direction changes along curved
    ditches, so the angle is held relative to the edge nearby), downhill while the
    goal lies beyond the ditch's course and uphill after; across a wide bottom it
    uses the steeper `bottom_angle_deg`. The direction along the edge is chosen
    toward the goal on flat ground and held while on a wall.

    .. pydrake_system::

        name: EdgeAngleDriver
        input_ports:
        - body_poses
        output_ports:
        - command

    Ports:
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        command: [v (m/s), w (rad/s)], updated at the control rate.
    """

    def __init__(self, terrain: DitchTerrain, goal_xy, chassis_body_index,
                 config: EdgeAngleDriverConfig | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        super().__init__()
        self._terrain = terrain
        self._goal_xy = np.asarray(goal_xy, dtype=float)
        # Which side of the course the goal lies on, for replanning (`desired_heading`).
        self._goal_away = terrain.distance_and_away(self._goal_xy)[1]
        self._chassis_index = int(chassis_body_index)
        self._config = config or EdgeAngleDriverConfig()
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._command_index = self.DeclareDiscreteState(2)
        # [along-edge direction sign (0 until chosen), phase (DESCEND, CLIMB, EXITED)].
        self._plan_index = self.DeclareDiscreteState(2)
        # The angles, margin and replanning are numeric parameters, so one built diagram
        # can drive each demonstration in its own style (`set_style`).
        self._style_index = self.DeclareNumericParameter(BasicVector(self._style_vector(self._config)))
        self.DeclareStateOutputPort("command", self._command_index)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    @staticmethod
    def _style_vector(config: EdgeAngleDriverConfig) -> np.ndarray:
        climb = np.nan if config.climb_angle_deg is None else config.climb_angle_deg
        return np.array([config.wall_angle_deg, climb, config.approach_margin_m, float(config.replan_each_step),
                         float(config.lead_in), float(config.keep_facing_side)])

    def set_style(self, context, config: EdgeAngleDriverConfig) -> None:
        """Sets the wall and climb angles, the approach margin, `replan_each_step`, `lead_in`
        and `keep_facing_side` in this system's `context`."""
        context.get_mutable_numeric_parameter(self._style_index).SetFromVector(self._style_vector(config))

    def _path_is_clear(self, xy: np.ndarray) -> bool:
        """Whether the straight line to the goal stays on the flat, off the ditch."""
        samples = np.linspace(xy, self._goal_xy, 50)
        return bool(np.all(self._terrain.nearest_on_course(samples)[0] > self._terrain.hinge_distance_m + 0.5))

    def crossing_length_m(self, wall_angle_deg: float, climb_angle_deg: float, approach_margin_m: float) -> float:
        """About how far (m) a crossing travels along the ditch from where it enters the
        approach zone to where it leaves the far wall: down the wall at the wall angle,
        across a wide bottom at `bottom_angle_deg`, up at the climb angle. Only about half
        of the approach zone counts: the robot turns into it from the goal's heading."""
        terrain, config = self._terrain, self._config
        wall_m = terrain.hinge_distance_m - terrain.toe_distance_m
        bottom_m = max(2.0 * (terrain.toe_distance_m - config.bottom_margin_m), 0.0)
        climb = wall_angle_deg if math.isnan(climb_angle_deg) else climb_angle_deg
        return ((wall_m + approach_margin_m / 2) / math.tan(math.radians(wall_angle_deg))
                + bottom_m / math.tan(math.radians(config.bottom_angle_deg))
                + wall_m / math.tan(math.radians(climb)))

    def _lead_in_heading(self, xy: np.ndarray, distance: float, away: np.ndarray, tangent: np.ndarray,
                         needed_m: float) -> float | None:
        """The heading to the lead-in point (rad) when the course ahead is too short for the
        crossing from here; None when it is long enough (see `EdgeAngleDriverConfig.lead_in`)."""
        side = approach_side(self._goal_xy - xy, -away, tangent, self._config.straight_across_deg)
        ahead = self._terrain.course_left_ahead(xy, side * tangent)
        if ahead >= needed_m:
            return None
        config = self._config
        back_m = needed_m + config.lead_in_extra_m - ahead
        target = xy - back_m * side * tangent + (
            self._terrain.hinge_distance_m + config.approach_margin_m + config.lead_in_offset_m - distance) * away
        return math.atan2(target[1] - xy[1], target[0] - xy[0])

    def desired_heading(self, xy: np.ndarray, along_sign: float, phase: int,
                        style: np.ndarray | None = None, heading: float = 0.0) -> tuple[float, float, int]:
        """Desired heading (rad) at xy, and the along-edge sign and phase to keep.

        `style` is [wall angle deg, climb angle deg (NaN: the wall angle), approach
        margin m, replan each step (0 or 1), lead in (0 or 1), keep facing side (0 or 1)];
        None uses the constructor's config.
        `heading` (rad), the robot's current yaw, is read only when replanning or keeping
        the facing side.

        Phases: DESCEND until the robot reaches the bottom, then CLIMB, then EXITED
        once it is back on the flat. Holding the phase keeps a curved edge from
        turning the robot uphill on the near wall, or back into the ditch after it
        has climbed out somewhere other than across from the goal (it then follows
        the rim).
        """
        config, terrain = self._config, self._terrain
        wall_angle_deg, climb_angle_deg, approach_margin_m, replan, lead_in, keep_facing_side = (
            self._style_vector(config) if style is None else np.asarray(style, dtype=float))
        to_goal = self._goal_xy - xy
        goal_heading = math.atan2(to_goal[1], to_goal[0])
        distance, away = terrain.distance_and_away(xy)
        distance = float(distance)
        toward = -away
        tangent = np.array([-away[1], away[0]])
        if replan:
            # The goal lies across the course from the robot, or on its own side.
            goal_beyond = float(self._goal_away @ away) < 0.0
            phase = DESCEND if goal_beyond and distance > terrain.toe_distance_m else (
                CLIMB if distance <= terrain.hinge_distance_m else EXITED)
            # On a wall, keep to the side the robot already faces, unless it faces the edge
            # nearly square on: then the approach convention, so that one observation
            # never gets both sides as labels (see `straight_across_deg`).
            along_sign = self._facing_side(heading, tangent) if distance <= terrain.hinge_distance_m else 0.0
        if keep_facing_side and phase == DESCEND and (
                terrain.hinge_distance_m < distance <= terrain.hinge_distance_m + approach_margin_m):
            along_sign = self._facing_side(heading, tangent) or along_sign
        if phase == CLIMB and distance > terrain.hinge_distance_m:
            phase = EXITED
        if phase == EXITED:
            if self._path_is_clear(xy):
                return goal_heading, 0.0, phase
            rim_sign = 1.0 if float(to_goal @ tangent) >= 0.0 else -1.0
            rim = math.cos(math.radians(10)) * rim_sign * tangent + math.sin(math.radians(10)) * away
            return math.atan2(rim[1], rim[0]), 0.0, phase
        if distance > terrain.hinge_distance_m + approach_margin_m:
            if lead_in and phase == DESCEND:
                needed_m = self.crossing_length_m(wall_angle_deg, climb_angle_deg, approach_margin_m)
                lead_in_heading = self._lead_in_heading(xy, distance, away, tangent, needed_m)
                if lead_in_heading is not None:
                    return lead_in_heading, 0.0, phase
            return goal_heading, 0.0, phase
        if distance <= terrain.toe_distance_m:
            phase = CLIMB
        on_flat_bottom = distance < terrain.toe_distance_m - config.bottom_margin_m
        if on_flat_bottom:
            along_sign = 1.0 if float(to_goal @ tangent) >= 0.0 else -1.0
        elif along_sign == 0.0:
            along_sign = approach_side(to_goal, toward, tangent, self._config.straight_across_deg)
        # Down toward the course; from the bottom on, across toward the goal's side and up.
        cross_sign = 1.0 if phase == DESCEND or float(to_goal @ toward) > 0.0 else -1.0
        if on_flat_bottom:
            angle = config.bottom_angle_deg
        elif phase == CLIMB and not math.isnan(climb_angle_deg):
            angle = climb_angle_deg
        else:
            angle = wall_angle_deg
        angle = math.radians(angle)
        direction = math.cos(angle) * along_sign * tangent + math.sin(angle) * cross_sign * toward
        return math.atan2(direction[1], direction[0]), along_sign, phase

    def _facing_side(self, heading: float, tangent: np.ndarray) -> float:
        """+1 or -1: the side along the edge (`tangent`) that `heading` (rad) faces; 0 within
        `straight_across_deg` of square on, where it faces neither decisively."""
        facing_along = math.cos(heading) * tangent[0] + math.sin(heading) * tangent[1]
        if abs(facing_along) <= math.sin(math.radians(self._config.straight_across_deg)):
            return 0.0
        return 1.0 if facing_along >= 0.0 else -1.0

    def _update(self, context, discrete_state) -> None:
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        heading = planar_yaw(X_WB)
        along_sign, phase = context.get_discrete_state(self._plan_index).get_value()
        style = context.get_numeric_parameter(self._style_index).get_value()
        desired, along_sign, phase = self.desired_heading(X_WB.translation()[:2], float(along_sign), int(phase), style,
                                                          heading)
        w = np.clip(self._config.heading_gain * wrap_to_pi(desired - heading),
                    -robot.MAX_ANGULAR_RATE_RADPS, robot.MAX_ANGULAR_RATE_RADPS)
        discrete_state.set_value(self._command_index, [self._config.speed_mps, w])
        discrete_state.set_value(self._plan_index, [along_sign, float(phase)])
