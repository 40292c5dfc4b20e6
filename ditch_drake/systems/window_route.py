"""The scripted driver's route through the windows of a ditch crossable only in places."""

import math
from dataclasses import dataclass

import numpy as np

from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw, wrap_to_pi
from ditch_drake.systems.edge_angle_driver import CLIMB, DESCEND, EXITED, EdgeAngleDriver, EdgeAngleDriverConfig
from ditch_drake.world.terrain import DitchTerrain
from ditch_drake.world.windows import CourseFrame, Window, course_frame, crossable_windows

# The phase after DESCEND on a route through windows: on the floor, driving along it to where the
# climb ends inside the exit window.
ALONG_FLOOR = 3
# How far the robot reaches along the course from its centre at any heading (m): half its
# footprint's diagonal.
HALF_REACH_M = float(np.hypot(*robot.CHASSIS_SIZE_M[:2]) / 2)
# The radius of the robot's tightest turn at full speed (m).
TURN_RADIUS_M = robot.MAX_SPEED_MPS / robot.MAX_ANGULAR_RATE_RADPS


@dataclass
class WindowRouteConfig:
    """How the route keeps inside the windows (m).

    Attributes:
        window_margin_m: kept between the robot's reach (`HALF_REACH_M`) and a window's ends,
            going down and coming up.
        exit_slack_m: the climb is aimed this much further inside the exit window than the
            margin, where the window leaves room: the turn off the floor is the least certain part.
        run_up_m: how far before the approach zone the robot should be on the line of its
            descent, to have turned onto it.
        lookahead_m: how far ahead along a line the robot aims while joining it.
        max_slope_deg: the steepest wall section a window may hold (None: the robot's smallest
            tip-over angle, `windows.smallest_tip_angle_deg`).
        narrow_room_m: in a window too narrow for the style's angle to the edge (down the wall
            at the wall angle the robot travels some 10 m along it), the run down or up the
            wall is steepened until this much of the window, within the margins, is left over.
        steepest_run_deg: the steepest angle to the edge a run is steepened to.
        climb_correction_deg: how far the climb's heading may turn from its angle to the edge
            to reach the planned exit (`WindowRouteDriver._climb_heading`).
    """

    window_margin_m: float = 0.5
    exit_slack_m: float = 1.5
    run_up_m: float = 2.5
    lookahead_m: float = 2.5
    max_slope_deg: float | None = None
    narrow_room_m: float = 0.5
    steepest_run_deg: float = 30.0
    climb_correction_deg: float = 15.0


@dataclass(frozen=True)
class WindowRoute:
    """A crossing through one window on each wall (along-course positions in m from the course's
    start; signs +1 along the course, -1 against it).

    Attributes:
        entry: the window on the start's wall.
        exit: the window on the goal's wall.
        descend_sign: the way the descent runs along the course.
        descend_angle_deg: the descent's angle to the edge: the style's wall angle, steeper in a
            narrow window (`WindowRouteConfig.narrow_room_m`).
        descend_hinge_m: where the descent leaves the flat (the entry window's hinge line).
        descend_toe_m: where it reaches the toe.
        approach_xy: where it enters the approach zone, from which on it holds the wall angle.
        climb_sign: the way the climb runs along the course.
        climb_angle_deg: the climb's angle to the edge: the style's, steeper in a narrow window.
        climb_toe_m: where the climb leaves the toe.
        climb_hinge_m: where it reaches the hinge line, on the flat again.
        exit_range_m: where the climb may reach the hinge line (aimed with `exit_slack_m`).
    """

    entry: Window
    exit: Window
    descend_sign: float
    descend_angle_deg: float
    descend_hinge_m: float
    descend_toe_m: float
    approach_xy: tuple[float, float]
    climb_sign: float
    climb_angle_deg: float
    climb_toe_m: float
    climb_hinge_m: float
    exit_range_m: tuple[float, float]


def _placements(window: Window, sign: float, wall_along_m: float, margin_m: float) -> tuple[float, float]:
    """The range of where a stretch of wall `wall_along_m` long, run in direction `sign`, may
    end at the hinge (descending: begin) while keeping `margin_m` inside `window`; a window too
    short gives its middle (the best it can do)."""
    low, high = window.from_m + margin_m, window.to_m - margin_m
    low, high = (low + wall_along_m, high) if sign > 0 else (low, high - wall_along_m)
    if low > high:
        middle = window.middle_m + sign * wall_along_m / 2
        return middle, middle
    return low, high


class WindowRoutePlanner:
    """Plans a `WindowRoute` on the analytic terrain for one goal and the driver's angles."""

    def __init__(self, terrain: DitchTerrain, goal_xy, driver: EdgeAngleDriverConfig,
                 config: WindowRouteConfig | None = None):
        self.terrain = terrain
        self.frame: CourseFrame = course_frame(terrain)
        self.goal_xy = np.asarray(goal_xy, dtype=float)
        self.goal_side = self.frame.side_of(self.goal_xy)
        self.config = config or WindowRouteConfig()
        self.driver = driver
        self.margin_m = HALF_REACH_M + self.config.window_margin_m
        self.windows = {side: crossable_windows(terrain, side, self.config.max_slope_deg)
                        for side in ("right", "left")}

    def crossing_along_m(self, hinge_distance_m: float, offset_m: float, climb_angle_deg: float) -> float:
        """How far along the course the crossing runs from `offset_m` (signed distance from the
        course toward the exit wall) to the hinge line at `hinge_distance_m`: across the
        bottom at `bottom_angle_deg`, up the last `bottom_margin_m` and the wall at the climb angle."""
        toe, driver = self.terrain.toe_distance_m, self.driver
        bottom_end = toe - driver.bottom_margin_m
        across = max(bottom_end - offset_m, 0.0) / math.tan(math.radians(driver.bottom_angle_deg))
        return across + max(hinge_distance_m - max(offset_m, bottom_end), 0.0) / math.tan(math.radians(climb_angle_deg))

    def run_angle_deg(self, window: Window, angle_deg: float) -> float:
        """The angle to the edge (deg) of a run down or up `window`'s wall: `angle_deg`, or in a
        window too narrow for it, the shallowest steeper one that leaves
        `WindowRouteConfig.narrow_room_m` of the window within the margins (at most
        `steepest_run_deg`)."""
        config = self.config
        room = window.width_m - 2.0 * self.margin_m - config.narrow_room_m
        drop = window.hinge_distance_m - self.terrain.toe_distance_m
        fitting = math.degrees(math.atan2(drop, room)) if room > 0.0 else 90.0
        return max(angle_deg, min(fitting, config.steepest_run_deg))

    def plan(self, start_xy, wall_angle_deg: float, climb_angle_deg: float,
             approach_margin_m: float) -> WindowRoute | None:
        """The route from `start_xy`; None where the start and the goal share a side, or a
        wall on the way has no window."""
        start_xy = np.asarray(start_xy, dtype=float)
        start_side = self.frame.side_of(start_xy)
        if start_side == self.goal_side or not self.windows[start_side] or not self.windows[self.goal_side]:
            return None
        terrain, frame = self.terrain, self.frame
        toe = terrain.toe_distance_m
        start_along, start_offset = (float(v) for v in frame.along_and_offset(start_xy))
        start_distance = abs(start_offset)
        zone_m = terrain.hinge_distance_m + approach_margin_m
        best = None
        for window in self.windows[start_side]:
            angle_deg = self.run_angle_deg(window, wall_angle_deg)
            wall = math.radians(angle_deg)
            # Ahead of the approach point by less than this along the course, the robot has not the run-up to turn.
            run_up = (self.config.run_up_m - math.sin(wall) * (start_distance - zone_m)) / math.cos(wall)
            wall_along = (window.hinge_distance_m - toe) / math.tan(wall)
            flat_along = (zone_m - window.hinge_distance_m) / math.tan(wall)
            for sign in (-1.0, 1.0):
                low, high = _placements(window, -sign, wall_along, self.margin_m)
                middle = window.middle_m - sign * wall_along / 2
                reachable = start_along + sign * (run_up + flat_along)  # the nearest hinge with a run-up
                hinge = min(max(min(middle, reachable) if sign < 0 else max(middle, reachable), low), high)
                short_m = max(sign * (reachable - hinge), 0.0)
                approach_along = hinge - sign * flat_along
                cost = 5.0 * short_m + abs(approach_along - start_along)
                if best is None or cost < best[0]:
                    best = (cost, window, sign, angle_deg, hinge, approach_along)
        _, entry, descend_sign, descend_deg, hinge, approach_along = best
        toe_along = hinge + descend_sign * (entry.hinge_distance_m - toe) / math.tan(math.radians(descend_deg))
        side_sign = frame.side_sign(start_side)
        approach_xy = frame.point(approach_along, side_sign * zone_m)
        exit_window, climb_sign, climb_deg, climb_hinge, exit_range = self._exit(toe_along, climb_angle_deg)
        climb_toe = climb_hinge - climb_sign * (exit_window.hinge_distance_m - toe) / math.tan(math.radians(climb_deg))
        return WindowRoute(entry, exit_window, descend_sign, descend_deg, hinge, toe_along,
                           tuple(approach_xy.tolist()), climb_sign, climb_deg, climb_toe, climb_hinge, exit_range)

    def _exit(self, toe_along_m: float, climb_angle_deg: float) -> tuple[Window, float, float, float,
                                                                          tuple[float, float]]:
        """The exit window, the way the climb runs, its angle to the edge, where it reaches the
        hinge, and the range it may reach it in: the least driving along the floor and then
        along the rim to the goal."""
        toe = self.terrain.toe_distance_m
        goal_along = float(self.frame.along_and_offset(self.goal_xy)[0])
        best = None
        for window in self.windows[self.goal_side]:
            angle_deg = self.run_angle_deg(window, climb_angle_deg)
            wall_along = (window.hinge_distance_m - toe) / math.tan(math.radians(angle_deg))
            straight_on = self.crossing_along_m(window.hinge_distance_m, -toe, angle_deg)
            for sign in (-1.0, 1.0):
                low, high = _placements(window, sign, wall_along, self.margin_m)
                slack = min(self.config.exit_slack_m, (high - low) / 2)
                low, high = low + slack, high - slack
                natural = toe_along_m + sign * straight_on
                hinge = min(max(natural, low), high)
                back = sign * (hinge - natural) < 0.0
                cost = abs(hinge - natural) + 2.0 * back + abs(hinge - goal_along)
                if best is None or cost < best[0]:
                    best = (cost, window, sign, angle_deg, hinge, (low, high))
        return best[1:]


class WindowRouteDriver(EdgeAngleDriver):
    """`EdgeAngleDriver` that crosses through the windows of a ditch crossable only in places.

    Knows the terrain analytically (privileged): its windows (`world/windows.py`), runs of wall
    sections no steeper than the robot's tip-over angle. At the first step it plans a
    `WindowRoute` from where the robot stands (`WindowRoutePlanner`): it joins, on the flat,
    the line along which descending at the wall angle stays inside the entry window; holds the
    wall angle down from the approach zone; drives along the floor until crossing at the bottom
    angle and climbing at the climb angle ends inside the exit window (which may lie elsewhere
    along the ditch); climbs, steering toward the planned exit against the wheels' sideways slip;
    then goes to the goal as `EdgeAngleDriver` does, along the rim while
    the straight line is blocked. The angles and the approach margin are the style's
    (`set_style`; a window too narrow for an angle steepens its run there,
    `WindowRoutePlanner.run_angle_deg`); with `replan_each_step` the phase follows from the current pose (the route
    still from the start).

    .. pydrake_system::

        name: WindowRouteDriver
        input_ports:
        - body_poses
        output_ports:
        - command

    Ports: `EdgeAngleDriver`'s.
    """

    def __init__(self, terrain: DitchTerrain, goal_xy, chassis_body_index,
                 config: EdgeAngleDriverConfig | None = None, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = 0.0, route: WindowRouteConfig | None = None):
        super().__init__(terrain, goal_xy, chassis_body_index, config, period_s, offset_s)
        self._planner = WindowRoutePlanner(terrain, goal_xy, self._config, route)
        # [planned (0 or 1), start x (m), start y (m)]: the route follows from the start pose.
        self._start_index = self.DeclareDiscreteState(3)

    def route_heading(self, xy: np.ndarray, heading: float, phase: int, route: WindowRoute | None,
                      style: np.ndarray) -> tuple[float, int]:
        """Desired heading (rad) at xy on `route`, and the phase to keep (DESCEND, ALONG_FLOOR,
        CLIMB, EXITED). `style` as `EdgeAngleDriver.desired_heading`'s."""
        replan = float(np.asarray(style, dtype=float)[3])
        frame, terrain, driver = self._planner.frame, self._terrain, self._config
        along, offset = (float(v) for v in frame.along_and_offset(xy))
        far = frame.side_sign(route.exit.side)
        toward_far = far * frame.left
        across = far * offset  # signed distance from the course toward the exit wall
        toe = terrain.toe_distance_m
        if replan:
            phase = (DESCEND if across < -(toe - driver.bottom_margin_m / 2) else
                     ALONG_FLOOR if across <= toe - driver.bottom_margin_m else
                     CLIMB if across <= terrain.hinge_distance_m else EXITED)
        if phase == DESCEND and across >= -(toe - driver.bottom_margin_m / 2):
            phase = ALONG_FLOOR
        if phase == ALONG_FLOOR and self._climb_starts_here(along, across, heading, route):
            phase = CLIMB
        if phase == CLIMB and across > terrain.hinge_distance_m:
            phase = EXITED
        if phase == EXITED:
            return self.desired_heading(xy, 0.0, EXITED, style, heading)[::2]
        if phase == DESCEND:
            wall = math.radians(route.descend_angle_deg)
            down = math.cos(wall) * route.descend_sign * frame.tangent + math.sin(wall) * toward_far
            # On the flat, even inside the approach zone, keep to the line (a robot that starts near
            # the zone would otherwise enter it early, and descend the whole way too early).
            if -across > route.entry.hinge_distance_m:
                return _heading_to(xy, _along_line(xy, np.asarray(route.approach_xy), down,
                                                   self._planner.config.lookahead_m)), phase
            return math.atan2(down[1], down[0]), phase
        if phase == ALONG_FLOOR:
            way = 1.0 if self._predicted_exit_m(along, across, heading, route) < (
                route.climb_hinge_m) else -1.0
            target = frame.point(along + way * self._planner.config.lookahead_m, 0.0)
            return _heading_to(xy, target), phase
        if across < toe - driver.bottom_margin_m:
            angle = math.radians(driver.bottom_angle_deg)
            up = math.cos(angle) * route.climb_sign * frame.tangent + math.sin(angle) * toward_far
            return math.atan2(up[1], up[0]), phase
        return self._climb_heading(xy, route), phase

    def _climb_heading(self, xy: np.ndarray, route: WindowRoute) -> float:
        """Up the exit wall: toward the point `lookahead_m` beyond the planned exit on the climb's
        line, so that the wheels' sideways slip, which carries the robot further along the wall
        than its heading, is steered out (held within `climb_correction_deg` of the climb angle)."""
        frame, config = self._planner.frame, self._planner.config
        far = frame.side_sign(route.exit.side)
        angle = math.radians(route.climb_angle_deg)
        up = math.cos(angle) * route.climb_sign * frame.tangent + math.sin(angle) * far * frame.left
        aim = frame.point(route.climb_hinge_m, far * route.exit.hinge_distance_m) + config.lookahead_m * up
        to_aim = aim - xy
        # The aim's angle to the edge, measured from the climb's way along the course.
        aim_deg = math.degrees(math.atan2(float(to_aim @ (far * frame.left)),
                                          float(to_aim @ (route.climb_sign * frame.tangent))))
        held = math.radians(min(max(aim_deg, route.climb_angle_deg - config.climb_correction_deg),
                                route.climb_angle_deg + config.climb_correction_deg))
        heading = math.cos(held) * route.climb_sign * frame.tangent + math.sin(held) * far * frame.left
        return math.atan2(heading[1], heading[0])

    def _predicted_exit_m(self, along: float, across: float, heading: float, route: WindowRoute) -> float:
        """Where along the course a climb begun now reaches the exit window's hinge line: the
        turn onto the bottom angle at the tightest radius, then the crossing."""
        frame = self._planner.frame
        far = frame.side_sign(route.exit.side)
        forward = np.array([math.cos(heading), math.sin(heading)])
        now = math.atan2(float(forward @ (far * frame.left)), float(forward @ (route.climb_sign * frame.tangent)))
        then = math.radians(self._config.bottom_angle_deg)
        turn = 1.0 if wrap_to_pi(then - now) >= 0.0 else -1.0
        ahead = TURN_RADIUS_M * turn * (math.sin(then) - math.sin(now))
        aside = TURN_RADIUS_M * turn * (math.cos(now) - math.cos(then))
        return along + route.climb_sign * (ahead + self._planner.crossing_along_m(
            route.exit.hinge_distance_m, across + aside, route.climb_angle_deg))

    def _climb_starts_here(self, along: float, across: float, heading: float, route: WindowRoute) -> bool:
        low, high = route.exit_range_m
        exit_m = self._predicted_exit_m(along, across, heading, route)
        return low - 0.3 <= exit_m <= high + 0.3

    def _route(self, context, xy: np.ndarray, style: np.ndarray) -> WindowRoute | None:
        # Planned from the start even when replanning each step: the phase then follows from the
        # pose, but a route from a pose on the floor or beyond the course would lead nowhere.
        planned, x, y = context.get_discrete_state(self._start_index).get_value()
        start = np.array([x, y]) if planned else xy
        return self._planner.plan(start, style[0], style[0] if math.isnan(style[1]) else style[1], style[2])

    def _update(self, context, discrete_state) -> None:
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        xy = X_WB.translation()[:2]
        style = context.get_numeric_parameter(self._style_index).get_value()
        route = self._route(context, xy, style)
        if not context.get_discrete_state(self._start_index).get_value()[0]:
            discrete_state.set_value(self._start_index, [1.0, xy[0], xy[1]])
        if route is None:  # the start and the goal share a side, or a wall is closed: the plain driver
            super()._update(context, discrete_state)
            return
        heading = planar_yaw(X_WB)
        phase = context.get_discrete_state(self._plan_index).get_value()[1]
        desired, phase = self.route_heading(xy, heading, int(phase), route, style)
        w = np.clip(self._config.heading_gain * wrap_to_pi(desired - heading),
                    -robot.MAX_ANGULAR_RATE_RADPS, robot.MAX_ANGULAR_RATE_RADPS)
        discrete_state.set_value(self._command_index, [self._config.speed_mps, w])
        discrete_state.set_value(self._plan_index, [0.0, float(phase)])


def _heading_to(xy: np.ndarray, target: np.ndarray) -> float:
    return math.atan2(float(target[1] - xy[1]), float(target[0] - xy[0]))


def _along_line(xy: np.ndarray, point: np.ndarray, direction: np.ndarray, lookahead_m: float) -> np.ndarray:
    """The point to aim at to join the line through `point` along unit `direction` and follow
    it: `lookahead_m` ahead of xy's projection on it, and no farther back than twice that from
    `point` (a robot far behind goes there first)."""
    behind = float((xy - point) @ direction)
    return point + direction * max(behind + lookahead_m, -2.0 * lookahead_m)
