"""Searching a ditch's edge for a way in, and its floor for a way out, in the elevation map."""

import enum
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.common.config_yaml import WRITTEN_WHEN_SET
from ditch_drake.common.errors import ConfigError
from ditch_drake.planning import crossing_windows as windows
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw


class SearchPhase(enum.IntEnum):
    """The `phase` output."""

    APPROACH = 0  # Toward the goal until an edge is seen ahead.
    SEARCH_IN = 1  # Along the edge, off it by a standoff, until a crossable section is seen.
    GOING_IN = 2  # Committed to a way in (or, with none found, the goal: the controller's own way).
    SEARCH_OUT = 3  # On the floor, along it, until a crossable section of the far wall is seen.
    GOING_OUT = 4  # Committed to a way out (or, with none found, the goal).
    OUT = 5  # Back at the top's height beyond the far wall's foot: the goal.


@dataclass
class WindowSearchConfig:
    """The search for a way in and out (m, deg, s).

    Attributes:
        crossable_slope_deg: a wall no steeper than this is crossable: below the robot's
            smallest static tip-over angle (59.6 deg about the axles,
            `ditch_drake.world.ingress.smallest_tip_angle_deg`), and above the steepest
            window (55 deg) by a margin for the fit's error (a 54 deg window must not read
            as steep in places).
        min_window_m: the shortest crossable section taken: the robot's width and a margin.
        bin_m: the wall's slope is estimated in bins this long along the edge.
        memory_m: the bins remembered span this much along the edge each side of where it was found.
        edge_standoff_m: the search drives this far short of the edge line.
        lookahead_m: a search's target lies this far ahead along the edge (or the floor); the
            ditch's end seen ahead counts once the robot has gone this far along its side.
        first_leg_m: the search goes first toward the goal's along and this far beyond it,
            then turns back and goes twice as far past its start the other way, and so on,
            each turn twice as far out (a way near either side is found before one far off).
        max_search_m: a side is done once the search is this far along it from the start;
            with both sides done it gives up and heads for the goal.
        stall_s: a side is done (the search turns back, or gives up) after this long without
            `stall_progress_m` of progress along (a fence, the ditch's end).
        stall_progress_m: see `stall_s`.
        entry_across_m: a way in aims this far across the edge line (into the ditch).
        descent_lead_m: a way in aims this far ahead along (an oblique descent travels along).
        ascent_lead_m: a way out aims this far ahead along.
        window_margin_m: a crossing aims this far inside a window's ends.
        floor_drop_m: on the floor: this far below the top and ...
        floor_tilt_deg: ... tilted less than this.
        floor_drift_m: on the floor, while the far wall is unseen, the target lies this far
            across from the robot (toward the far wall).
        far_band_m: the far wall is read within this across beyond the robot.
        far_standoff_m: the floor search keeps this far short of the far wall's foot.
        exit_across_m: a way out aims this far across beyond the far wall's foot.
        out_rise_m: out once within this of the top's height beyond the far wall's foot.
        near_band_m: the near wall is read within this each side of the edge line (a gentle
            wall's hinge lies set back from a steep one's).
        keep_off_seen_drops: the targets along the top keep `edge_standoff_m` short of the
            nearest drop seen near them too, not only of the edge line: a gentle window's hinge
            lies set back from the steep wall's edge, by up to a few metres, and the robot
            following the edge line at the standoff drove onto the window's wall sideways
            where it came to one (off by default, as measured before).
        hold_way_m: where set, a crossing's way along, once chosen on a level, is held until the
            window leaves less than this ahead (then back into it). Unset, it is chosen anew at
            every update, turning back wherever the window leaves less than the lead and the
            margin ahead: a robot that had not yet climbed there turned about every few metres
            along a window and used up its time on the floor.
    """

    crossable_slope_deg: float = 58.0
    min_window_m: float = 1.5
    bin_m: float = 0.5
    memory_m: float = 50.0
    edge_standoff_m: float = 0.8
    lookahead_m: float = 3.0
    first_leg_m: float = 8.0
    max_search_m: float = 60.0
    stall_s: float = 10.0
    stall_progress_m: float = 0.5
    entry_across_m: float = 4.0
    descent_lead_m: float = 5.0
    ascent_lead_m: float = 3.0
    window_margin_m: float = 0.5
    floor_drop_m: float = 2.0
    floor_tilt_deg: float = 12.0
    floor_drift_m: float = 2.0
    far_band_m: float = 5.0
    far_standoff_m: float = 1.0
    exit_across_m: float = 6.0
    out_rise_m: float = 0.5
    near_band_m: float = 3.0
    keep_off_seen_drops: bool = field(default=False, metadata=WRITTEN_WHEN_SET)
    hold_way_m: float | None = field(default=None, metadata=WRITTEN_WHEN_SET)

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of range."""
        for name, value in vars(self).items():
            if value is None and name == "hold_way_m":  # Left unset.
                continue
            if name == "keep_off_seen_drops":
                if not isinstance(value, bool):
                    raise ConfigError(f"window search {name}={value!r}: expected true or false")
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"window search {name}={value!r}: expected a positive number")
        if not self.crossable_slope_deg < 90:
            raise ConfigError(f"window search crossable_slope_deg={self.crossable_slope_deg!r}: expected < 90")


@dataclass(frozen=True)
class _View:
    """What one update sees: the chassis's planar position (m) and yaw (rad), its tilt from
    upright (deg), the map's height under it (m, NaN unmapped), and the map as
    (heights, origin_xy, resolution) for `crossing_windows`."""

    xy: np.ndarray
    yaw: float
    tilt_deg: float
    ground_z: float
    map_args: tuple


# Layout of the bookkeeping state.
(_PHASE, _DIRECTION, _FRAME_X, _FRAME_Y, _FRAME_ANGLE, _TOP_Z, _FLOOR_Z, _ORIGIN, _DONE_SIDES, _BEST, _STALL,
 _WINDOW_FROM, _WINDOW_TO, _FAR_FOOT, _REACH, _UNDER_WAY, _LEG_FROM) = range(17)
_STATE_SIZE = 17


class WindowSearch(LeafSystem):
    """The route-level target for a crossing controller: where to go in, where to come out.

    Every period one discrete update reads the elevation map (the `mppi` controller's
    `elevation_map` output: fused from the lidar) and the pose, and runs the phases of
    `SearchPhase`: toward the goal until an edge is seen ahead (`crossing_windows.find_edge`);
    then along the edge, `edge_standoff_m` short of it, toward the goal's side along it (to the
    left facing the ditch when the goal lies square across), estimating the near wall's slope
    in bins along the edge (`crossing_windows.wall_slopes`), remembered in the state while the
    map's window moves on; once a section no steeper than `crossable_slope_deg` and at least
    `min_window_m` long is seen, the target lies across the edge inside it; on the floor, the
    same along the floor for the far wall; up it, the target lies beyond the far wall's foot
    inside its window; back at the top's height, the goal. A search goes toward the goal's
    along and `first_leg_m` beyond, then turns back, each turn twice as far from its start; a side is done at
    `max_search_m`, a stall or where the ditch ends ahead (the ground across the edge seen
    level, or the floor rising ahead, once `lookahead_m` along that side: just after a turn at
    an end, the ground ahead is still that end's), and with both done it gives up for the goal. It reads the
    robot's sensors (the map), its pose and the goal: nothing privileged.

    .. pydrake_system::

        name: WindowSearch
        input_ports:
        - elevation_map
        - body_poses
        output_ports:
        - target_xy
        - phase

    Ports:
        elevation_map: [origin_x (m), origin_y (m), heights (m, NaN unknown) row-major] of `grid`.
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        target_xy: the planar point (m, W) to drive toward; the goal until the first update.
        phase: [`SearchPhase`].
    """

    def __init__(self, goal_xy, chassis_body_index, grid: ElevationGrid, config: WindowSearchConfig | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        super().__init__()
        self._config = config or WindowSearchConfig()
        self._config.validate()
        self._goal_xy = np.asarray(goal_xy, dtype=float)[:2]
        self._chassis_index = int(chassis_body_index)
        self._grid = grid
        half = math.ceil(self._config.memory_m / self._config.bin_m)
        self._bin_edges_m = np.arange(-half, half + 1) * self._config.bin_m
        bins = len(self._bin_edges_m) - 1
        self._map_port = self.DeclareVectorInputPort("elevation_map", 2 + grid.size)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._target_index = self.DeclareDiscreteState(self._goal_xy.copy())
        state = np.full(_STATE_SIZE, np.nan)
        state[[_PHASE, _DIRECTION, _DONE_SIDES, _STALL, _UNDER_WAY]] = [SearchPhase.APPROACH, 1.0, 0.0, 0.0, 0.0]
        self._state_index = self.DeclareDiscreteState(state)
        self._near_index = self.DeclareDiscreteState(np.full(bins, np.nan))
        self._far_index = self.DeclareDiscreteState(np.full(bins, np.nan))
        self.DeclareStateOutputPort("target_xy", self._target_index)
        self.DeclareVectorOutputPort("phase", BasicVector(1), self._calc_phase,
                                     prerequisites_of_calc={self.discrete_state_ticket(self._state_index)})
        self._period_s = float(period_s)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    @property
    def bin_edges_m(self) -> np.ndarray:
        """The bins' bounds along the edge (m, from where the edge was found)."""
        return self._bin_edges_m

    def wall_memory(self, context) -> tuple[np.ndarray, np.ndarray]:
        """The near and far walls' slopes (deg, NaN unseen) per bin remembered in `context`."""
        return (context.get_discrete_state(self._near_index).get_value().copy(),
                context.get_discrete_state(self._far_index).get_value().copy())

    def _calc_phase(self, context, output) -> None:
        output.SetFromVector([context.get_discrete_state(self._state_index).get_value()[_PHASE]])

    def _update(self, context, discrete_state) -> None:
        state = context.get_discrete_state(self._state_index).get_value().copy()
        near = context.get_discrete_state(self._near_index).get_value().copy()
        far = context.get_discrete_state(self._far_index).get_value().copy()
        target = context.get_discrete_state(self._target_index).get_value().copy()
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        origin_xy, heights = self._grid.unpack(self._map_port.Eval(context))
        xy = X_WB.translation()[:2]
        view = _View(xy=xy, yaw=planar_yaw(X_WB),
                     tilt_deg=math.degrees(math.acos(np.clip(X_WB.rotation().matrix()[2, 2], -1.0, 1.0))),
                     ground_z=windows.ground_height(heights, origin_xy, self._grid.resolution, xy),
                     map_args=(heights, origin_xy, self._grid.resolution))
        if math.isnan(view.ground_z):  # No map yet.
            return
        phase = SearchPhase(int(state[_PHASE]))
        if phase == SearchPhase.APPROACH:
            target, phase = self._goal_xy, self._approach(view, state)
        if phase in (SearchPhase.SEARCH_IN, SearchPhase.GOING_IN):
            phase, target = self._way_in(view, state, near, searching=phase == SearchPhase.SEARCH_IN)
        if phase in (SearchPhase.SEARCH_OUT, SearchPhase.GOING_OUT):
            phase, target = self._way_out(view, state, far, searching=phase == SearchPhase.SEARCH_OUT)
        if phase == SearchPhase.OUT:
            target = self._goal_xy
        state[_PHASE] = phase
        discrete_state.set_value(self._target_index, np.asarray(target, dtype=float))
        discrete_state.set_value(self._state_index, state)
        discrete_state.set_value(self._near_index, near)
        discrete_state.set_value(self._far_index, far)

    def _approach(self, view: _View, state: np.ndarray) -> SearchPhase:
        """Toward the goal until an edge is seen ahead; then the edge's frame is stored and the
        search along it starts."""
        frame = windows.find_edge(*view.map_args, view.xy, view.yaw, view.ground_z)
        if frame is None:
            return SearchPhase.APPROACH
        state[_FRAME_X:_FRAME_ANGLE + 1] = frame.to_vector()
        state[_TOP_Z] = view.ground_z
        self._start_search(state, frame.coordinates(view.xy)[0], frame.coordinates(self._goal_xy)[0])
        return SearchPhase.SEARCH_IN

    def _way_in(self, view: _View, state: np.ndarray, near: np.ndarray,
                searching: bool) -> tuple[SearchPhase, np.ndarray]:
        """Along the top for a way in while `searching` (`near`: the near wall's slopes, updated
        in place), then across through it; on the floor, the search for a way out starts."""
        c = self._config
        frame = windows.EdgeFrame.from_vector(state[_FRAME_X:_FRAME_ANGLE + 1])
        s_robot, _ = frame.coordinates(view.xy)
        bin_args = (*view.map_args, frame, self._bin_edges_m)
        seen = windows.wall_slopes(*bin_args, state[_TOP_Z], (-c.near_band_m, c.near_band_m), rising=False)
        near[:] = np.where(np.isfinite(seen), seen, near)
        ended = windows.edge_ended(*bin_args[:4], self._ahead(state, s_robot), (0.5, c.near_band_m), state[_TOP_Z])
        searching, window = self._search_step(near, state, s_robot, searching, ended)
        top_across = functools.partial(self._top_across, bin_args[:4], state[_TOP_Z], s_robot)
        if searching:
            s_target = s_robot + state[_DIRECTION] * c.lookahead_m
            return SearchPhase.SEARCH_IN, frame.point(s_target, top_across(s_target))
        on_top = view.ground_z > state[_TOP_Z] - c.out_rise_m
        target = self._goal_xy if window is None else self._crossing_target(
            frame, window, state, s_robot, view.yaw, c.descent_lead_m, c.entry_across_m, on_top, top_across)
        if view.ground_z < state[_TOP_Z] - c.floor_drop_m and view.tilt_deg < c.floor_tilt_deg:
            state[_FLOOR_Z] = view.ground_z
            self._start_search(state, s_robot, frame.coordinates(self._goal_xy)[0])
            return SearchPhase.SEARCH_OUT, target
        return SearchPhase.GOING_IN, target

    def _way_out(self, view: _View, state: np.ndarray, far: np.ndarray,
                 searching: bool) -> tuple[SearchPhase, np.ndarray]:
        """Along the floor for a way out while `searching` (`far`: the far wall's slopes, updated
        in place), then up through it; out once back at the top's height beyond the far wall's foot."""
        c = self._config
        frame = windows.EdgeFrame.from_vector(state[_FRAME_X:_FRAME_ANGLE + 1])
        s_robot, c_robot = frame.coordinates(view.xy)
        bin_args = (*view.map_args, frame, self._bin_edges_m)
        if view.ground_z < state[_FLOOR_Z] + c.out_rise_m:
            # Read from the floor only: from up the wall, the top beyond would pass for more wall.
            band = (c_robot + 0.5, c_robot + c.far_band_m)
            seen = windows.wall_slopes(*bin_args, state[_FLOOR_Z], band, rising=True)
            far[:] = np.where(np.isfinite(seen), seen, far)
            foot = windows.nearest_rise(*bin_args[:4], state[_FLOOR_Z], band)
            if np.isfinite(foot):
                state[_FAR_FOOT] = foot
        ended = windows.floor_ended(*bin_args[:4], self._ahead(state, s_robot), (c_robot - 0.5, c_robot + 0.5),
                                    state[_FLOOR_Z])
        searching, window = self._search_step(far, state, s_robot, searching, ended)
        across = state[_FAR_FOOT] - c.far_standoff_m if np.isfinite(state[_FAR_FOOT]) else c_robot + c.floor_drift_m
        if searching:
            return SearchPhase.SEARCH_OUT, frame.point(s_robot + state[_DIRECTION] * c.lookahead_m, across)
        on_floor = view.ground_z < state[_FLOOR_Z] + c.out_rise_m
        target = self._goal_xy if window is None else self._crossing_target(
            frame, window, state, s_robot, view.yaw, c.ascent_lead_m, state[_FAR_FOOT] + c.exit_across_m, on_floor,
            lambda _: across)
        if view.ground_z > state[_TOP_Z] - c.out_rise_m and c_robot > state[_FAR_FOOT]:
            return SearchPhase.OUT, target
        return SearchPhase.GOING_OUT, target

    def _top_across(self, map_args: tuple, top_z_m: float, s_robot: float, s_target: float) -> float:
        """Across (m) of a target along the top at `s_target`: `edge_standoff_m` short of the
        edge line and, with `keep_off_seen_drops`, of the nearest drop seen from the robot to 1 m
        past the target. `map_args`: (heights, origin, resolution, frame)."""
        c = self._config
        if not c.keep_off_seen_drops:
            return -c.edge_standoff_m
        drop = windows.nearest_drop(*map_args, (s_robot, s_target + math.copysign(1.0, s_target - s_robot)),
                                    (-c.near_band_m, c.near_band_m), top_z_m)
        return min(0.0, drop if np.isfinite(drop) else 0.0) - c.edge_standoff_m

    def _crossing_target(self, frame: windows.EdgeFrame, window: tuple[float, float], state: np.ndarray,
                         s_robot: float, yaw: float, lead_m: float, across_m: float, on_level: bool,
                         level_across: Callable[[float], float]) -> np.ndarray:
        """The target of a crossing through `window`: `across_m` across, `lead_m` ahead along on
        the way with room for it in the window (decided while `on_level`: turned back into the
        window where the robot has passed its end). While the robot on the level heads off that
        way by more than 60 deg, the target lies along the level (`level_across(s)` across at its s)
        ahead that way instead: the MPPI climbs or descends toward a target ahead of it, but
        drives away from one behind it up a wall beside it."""
        c = self._config
        if on_level:
            held = c.hold_way_m is not None and bool(state[_UNDER_WAY])
            state[_DIRECTION] = windows.crossing_direction(window, s_robot, state[_DIRECTION], lead_m + c.window_margin_m,
                                                           under_way=held, turn_m=c.hold_way_m or 0.0)
            state[_UNDER_WAY] = 1.0
            heading_along = frame.along @ np.array([math.cos(yaw), math.sin(yaw)])
            if state[_DIRECTION] * heading_along < 0.5:
                s_target = s_robot + state[_DIRECTION] * c.lookahead_m
                return frame.point(s_target, level_across(s_target))
        return frame.point(windows.along_target(window, s_robot, state[_DIRECTION], lead_m, c.window_margin_m),
                           across_m)

    def _ahead(self, state: np.ndarray, s_robot: float) -> tuple[float, float]:
        """The along range (m) where the search looks for the ditch's end: from 1 m to
        `lookahead_m` ahead."""
        return s_robot + state[_DIRECTION] * 1.0, s_robot + state[_DIRECTION] * self._config.lookahead_m

    def _search_step(self, slopes: np.ndarray, state: np.ndarray, s_robot: float, searching: bool,
                     ended: bool) -> tuple[bool, tuple[float, float] | None]:
        """(still searching, the window to cross by: None where none is seen or the search gave up);
        a window found is stored as the committed one. `ended`: the way along ends ahead."""
        window = self._window(slopes, state, s_robot, committed=not searching)
        if searching and window is None and self._continue_search(state, s_robot, ended):
            return True, None
        state[_WINDOW_FROM:_WINDOW_TO + 1] = window if window is not None else (np.nan, np.nan)
        return False, window

    def _window(self, slopes: np.ndarray, state: np.ndarray, s_robot: float,
                committed: bool) -> tuple[float, float] | None:
        """The window to cross by: once committed, the committed one grown by those seen
        overlapping it (a window seen later from further off, obliquely, may read shorter: it
        never shrinks); else the nearest seen."""
        found = windows.crossable_windows(self._bin_edges_m, slopes, self._config.crossable_slope_deg,
                                          self._config.min_window_m)
        if committed:
            if not np.isfinite(state[_WINDOW_FROM]):
                return None
            overlapping = [w for w in found if w[0] < state[_WINDOW_TO] and w[1] > state[_WINDOW_FROM]]
            return (min([float(state[_WINDOW_FROM]), *(w[0] for w in overlapping)]),
                    max([float(state[_WINDOW_TO]), *(w[1] for w in overlapping)]))
        return windows.nearest_window(found, s_robot)

    def _start_search(self, state: np.ndarray, s_robot: float, s_goal: float) -> None:
        """A new search from `s_robot`: first toward the goal's side along (the +s side where
        the goal lies square across), as far as the goal's along and `first_leg_m` beyond: a way
        short of the goal's along costs no detour."""
        state[_DIRECTION] = 1.0 if abs(s_goal - s_robot) <= 1.0 else math.copysign(1.0, s_goal - s_robot)
        state[_ORIGIN], state[_DONE_SIDES], state[_UNDER_WAY] = s_robot, 0.0, 0.0
        state[_REACH] = self._config.first_leg_m + abs(s_goal - s_robot)
        self._start_leg(state, s_robot)

    @staticmethod
    def _start_leg(state: np.ndarray, s_robot: float) -> None:
        state[_BEST] = state[_LEG_FROM] = state[_DIRECTION] * s_robot
        state[_STALL] = 0.0

    @staticmethod
    def _side_bit(direction: float) -> int:
        return 1 if direction > 0 else 2

    def _continue_search(self, state: np.ndarray, s_robot: float, ended: bool) -> bool:
        """Books the progress along; turns back at the leg's reach, or at `max_search_m`, a
        stall or the end of the way along (`ended`: then that side is done), doubling the reach
        each turn. False: both sides done."""
        c = self._config
        progress = state[_DIRECTION] * s_robot
        if progress > state[_BEST] + c.stall_progress_m:
            state[_BEST], state[_STALL] = progress, 0.0
        else:
            state[_STALL] += self._period_s
        out_m = state[_DIRECTION] * (s_robot - state[_ORIGIN])
        done = int(state[_DONE_SIDES])
        # Just after a turn at the ditch's end, the ground ahead is still that end's.
        ended = ended and progress >= state[_LEG_FROM] + c.lookahead_m
        if ended or state[_STALL] >= c.stall_s or out_m >= c.max_search_m:
            done |= self._side_bit(state[_DIRECTION])
        elif out_m < state[_REACH] or done & self._side_bit(-state[_DIRECTION]):
            return True
        state[_DONE_SIDES] = done
        if done & self._side_bit(-state[_DIRECTION]):
            return False
        state[_DIRECTION] = -state[_DIRECTION]
        state[_REACH] = 2.0 * state[_REACH] if done == 0 else c.max_search_m
        self._start_leg(state, s_robot)
        return True
