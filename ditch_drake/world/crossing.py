"""A task's crossing: how far its straight line from start to goal turns from square across the ditch.

The expert turns along the edge toward the goal's side, unless the goal lies within
`EdgeAngleDriverConfig.straight_across_deg` of straight across, where it turns right by
convention; so which way a crossing turns decides which way it is demonstrated
(`ditch_drake.benchmark.generalist` reflects only crossings the convention does not touch,
the benchmark's report bins success by it).
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


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The z component of the planar cross product u x v (over the last axis)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
