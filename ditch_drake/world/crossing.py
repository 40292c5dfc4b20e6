"""A task's crossing: how far its straight line from start to goal turns from square across the ditch.

The expert turns along the edge toward the goal's side, unless the goal lies within
`EdgeAngleDriverConfig.straight_across_deg` of straight across, where it turns right by
convention; so which way a crossing turns decides which way it is demonstrated
(`ditch_drake.pipelines.generalist` reflects only crossings the convention does not touch,
the benchmark's report bins success by it).

`approach_side` is that rule, and `crossing_sides` the side it gives along a path, held from
where the path enters the approach zone on: the side a clone trained in one side's frame is
told to cross on (`ditch_drake.systems.oracle_crossing_side`; `perceived_crossing_side` applies
the same rule to the edge it finds in the lidar's rays).
"""

import math

import numpy as np

from ditch_drake.world.environments import Environment
from ditch_drake.world.terrain import DitchTerrain


def crossing_turn_deg(environment: Environment, task: int) -> float:
    """How far task `task`'s line from start to goal turns from square across the ditch (deg),
    positive to the left: its angle from the course's normal where it crosses the course (the
    first crossing; from the direction to the centre for a crater).
    """
    chosen = environment.tasks[task]
    start, goal = np.asarray(chosen.start[:2], dtype=float), np.asarray(chosen.goal, dtype=float)
    line = goal - start
    terrain = DitchTerrain(environment.terrain)
    course = terrain.course_xy
    square = None
    if len(course) > 1:
        a, tangents = course[:-1], np.diff(course, axis=0)
        denominator = _cross(line, tangents)
        with np.errstate(divide="ignore", invalid="ignore"):
            along_line = _cross(a - start, tangents) / denominator
            along_course = _cross(a - start, line) / denominator
        crossed = np.flatnonzero((along_line >= 0) & (along_line <= 1) & (along_course >= 0) & (along_course <= 1))
        if len(crossed):
            tangent = tangents[crossed[np.argmin(along_line[crossed])]]
            square = np.array([-tangent[1], tangent[0]])
            square *= 1.0 if square @ line >= 0.0 else -1.0
    if square is None:
        _, nearest = terrain.nearest_on_course(start)
        square = nearest - start
    return math.degrees(math.atan2(_cross(square, line), float(square @ line)))


def approach_side(to_goal: np.ndarray, toward: np.ndarray, tangent: np.ndarray, straight_across_deg: float) -> float:
    """Which way along the edge to cross: +1 along `tangent` (to the right when facing the ditch
    along `toward`), -1 against it; toward the goal's side, or +1 by convention when the goal
    lies within `straight_across_deg` of straight across."""
    off_axis = math.degrees(math.atan2(abs(float(to_goal @ tangent)), float(to_goal @ toward)))
    if off_axis < straight_across_deg:
        return 1.0
    return 1.0 if float(to_goal @ tangent) >= 0.0 else -1.0


def crossing_side_step(terrain: DitchTerrain, xy: np.ndarray, goal_xy: np.ndarray, held: float,
                       approach_margin_m: float, straight_across_deg: float) -> tuple[float, float]:
    """The side (+1 right, -1 left) at `xy`, and the side held from here on (0: none yet).

    A side held already stays. Otherwise the side is `approach_side` toward the goal at the
    nearest edge, and it is held from where `xy` lies within `approach_margin_m` of the hinge
    line or inside it, where the expert commits to its side along the edge.
    """
    if held != 0.0:
        return held, held
    xy = np.asarray(xy, dtype=float)
    distance, away = terrain.distance_and_away(xy)
    side = approach_side(np.asarray(goal_xy, dtype=float) - xy, -away, np.array([-away[1], away[0]]),
                         straight_across_deg)
    return side, side if float(distance) <= terrain.hinge_distance_m + approach_margin_m else 0.0


def crossing_sides(terrain: DitchTerrain, path_xy: np.ndarray, goal_xy: np.ndarray, approach_margin_m: float,
                   straight_across_deg: float) -> np.ndarray:
    """The side (+1 right, -1 left) at each point of `path_xy` (T, 2), `crossing_side_step`
    along it."""
    sides = np.empty(len(path_xy))
    held = 0.0
    for index, xy in enumerate(np.asarray(path_xy, dtype=float)):
        sides[index], held = crossing_side_step(terrain, xy, goal_xy, held, approach_margin_m, straight_across_deg)
    return sides


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The z component of the planar cross product u x v (over the last axis)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
