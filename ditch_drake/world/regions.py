"""Where a point lies relative to a ditch, seen from a task's start: the regions of the rollout records.

The rollout records name the region where a failed rollout ended (`RolloutRecord.failure_region`)
and count the controller's halts per region (`RolloutRecord.halts_by_region`); both use this
one rule, so a halt and a failure on "up_wall" mean the same stretch of ground.
"""

import numpy as np

from ditch_drake.world.terrain import DitchTerrain

# In the order a crossing meets them.
REGIONS = ("approach", "down_wall", "floor", "up_wall", "beyond")

# Where a failure on a ditch crossable only in places (`DitchTerrain.sectioned`) ended when it
# ended near the edge on the start's side: a controller looking for a way in along the edge.
ALONG_EDGE = "along_edge"
# How far beyond the hinge line (m) "along_edge" reaches: a searching controller keeps a few
# metres off the edge, and one heading straight for the goal crosses this band in seconds.
ALONG_EDGE_BAND_M = 4.0


def ditch_region(terrain: DitchTerrain, start_xy, xy) -> str:
    """The region of planar point `xy` (m) for a robot that started at `start_xy` (m).

    "approach": outside the hinge line, on the start's side of the course; "down_wall":
    between hinge and toe on the start's side (the wall a crossing enters by); "floor":
    inside the toe line; "up_wall": between toe and hinge on the other side (the wall a
    crossing leaves by); "beyond": outside the hinge line on the other side.
    """
    distance, away = terrain.distance_and_away(np.asarray([start_xy, xy], dtype=float))
    # The side of the course: the directions away from it at the two points agree.
    same_side = float(np.dot(away[0], away[1])) > 0.0
    if distance[1] < terrain.toe_distance_m:
        return "floor"
    if distance[1] <= terrain.hinge_distance_m:
        return "down_wall" if same_side else "up_wall"
    return "approach" if same_side else "beyond"


def failure_region(terrain: DitchTerrain, start_xy, xy) -> str:
    """Where a failed rollout ended: `ditch_region`, except that on a ditch whose walls are
    crossable only in places (`DitchTerrain.sectioned`) the start's side within
    `ALONG_EDGE_BAND_M` of the hinge line is `ALONG_EDGE` ("searching along the edge")."""
    region = ditch_region(terrain, start_xy, xy)
    if region == "approach" and terrain.sectioned:
        distance = float(terrain.distance_and_away(np.asarray([xy], dtype=float))[0][0])
        if distance <= terrain.hinge_distance_m + ALONG_EDGE_BAND_M:
            return ALONG_EDGE
    return region
