"""Proof that a ditch crossable only in places can still be crossed: a way in and a way out.

A ditch whose walls change slope along the course (`TerrainParams.wall_slopes`) may be steeper
than the robot can stand on in places and gentle enough in others (windows). For each task,
`check_ways_in_and_out` proves on the analytic terrain that a way leads from the start down
to the ditch's floor and one from the floor up to the goal:

- the field (the flat ground round the ditch, or the fenced field with a margin) is rasterized
  into square cells of `resolution_m`, each with the terrain's height at its centre;
- a cell is too steep when the height changes faster than tan(`max_traversable_slope_deg`)
  toward any of its 8 neighbours: a wall steeper than the limit, or a step where a wall
  changes slope (with 0.1 m cells, a step higher than 0.17 m, about a wheel's radius);
- a cell is blocked when it is too steep or a fence (`TerrainParams.walls`) lies within
  `clearance_m` of it, the steep cells grown by `clearance_m` as well (the robot's half width:
  a window narrower than the robot is closed);
- 8-connected components of the free cells (`scipy.ndimage.label`) answer: the start's
  component must hold cells of the ditch's floor (a way in), the goal's must too (a way out),
  and the two must be one (the floor joins them).

Diagonal steps between two blocked cells count as open, so the search finds a few more routes
than a robot could drive; the windows a packaged environment has are many times the robot's
width.

`check_windows` refuses, before any search, a window narrower than the robot: a run of
sections no steeper than the limit, shorter along the course than the robot is wide.
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ditch_drake.common.errors import ConfigError
from ditch_drake.spec import robot
from ditch_drake.world.bypass import _near_course
from ditch_drake.world.terrain import WALL_SIDES, DitchTerrain, _distance_to_segments
from ditch_drake.world.windows import crossable_windows, smallest_tip_angle_deg


@dataclass
class IngressConfig:
    """The proof's settings (m, degrees).

    Attributes:
        max_traversable_slope_deg: the steepest ground a way in or out may cross: the robot's
            smallest static tip-over angle (`smallest_tip_angle_deg`, 59.6 deg about the
            axles). On ground no steeper the centre of mass stays over the wheels at every
            heading, so the robot can turn there; past it only headings near the diagonal
            hold, and past 68.3 deg none (docs/concepts/terrain_family.md, "Ways in and out").
        clearance_m: steep cells and fences grow by this much: the robot's half width.
        resolution_m: the grid's cell side; at 0.1 m a step counts as too steep from
            tan(max_traversable_slope_deg) x 0.1 m = 0.17 m on, about a wheel's radius.
        margin_m: the grid reaches this far beyond the field (or the fences) on every side.
    """

    max_traversable_slope_deg: float = smallest_tip_angle_deg()
    clearance_m: float = float(robot.CHASSIS_SIZE_M[1] / 2)
    resolution_m: float = 0.1
    margin_m: float = 1.0


@dataclass
class TraversableGrid:
    """The rasterized field of one terrain, labelled by where the robot can drive.

    Attributes:
        origin: world xy (m) of cell (0, 0)'s centre.
        resolution_m: the cell side.
        labels: the 8-connected components of the free cells (0: blocked), (ny, nx).
        floor: which cells are free cells of the ditch's floor, (ny, nx).
    """

    origin: np.ndarray
    resolution_m: float
    labels: np.ndarray
    floor: np.ndarray

    def label_at(self, xy) -> int:
        """The component of the cell holding xy (0: blocked or off the grid)."""
        ix, iy = (int(v) for v in np.round((np.asarray(xy, dtype=float) - self.origin) / self.resolution_m))
        ny, nx = self.labels.shape
        return int(self.labels[iy, ix]) if 0 <= iy < ny and 0 <= ix < nx else 0

    def floor_labels(self) -> set[int]:
        """The components that reach the ditch's floor."""
        return {int(v) for v in np.unique(self.labels[self.floor]) if v}


def traversable_grid(terrain: DitchTerrain, config: IngressConfig | None = None) -> TraversableGrid:
    """The labelled grid of `terrain`'s field (see the module docstring)."""
    config = config or IngressConfig()
    r = config.resolution_m
    starts, ends, _ = terrain.wall_segments()
    if len(starts):  # the fenced field: nothing outside it matters
        low = np.minimum(starts.min(axis=0), ends.min(axis=0)) - config.margin_m
        high = np.maximum(starts.max(axis=0), ends.max(axis=0)) + config.margin_m
    else:
        low, high = terrain.bounds_xy()
        low, high = low - config.margin_m, high + config.margin_m
    nx, ny = (int(v) + 1 for v in np.ceil((high - low) / r))
    xs, ys = low[0] + r * np.arange(nx), low[1] + r * np.arange(ny)
    grid = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1).reshape(-1, 2)
    height = np.zeros(len(grid))
    distance = np.full(len(grid), np.inf)
    near = _near_course(terrain, grid, terrain.half_width_m + r)
    if near.any():
        height[near] = terrain.height(grid[near])
        distance[near] = terrain.nearest_on_course(grid[near])[0]
    height, distance = height.reshape(ny, nx), distance.reshape(ny, nx)
    steep = np.zeros((ny, nx), dtype=bool)
    rise = math.tan(math.radians(config.max_traversable_slope_deg))
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # each neighbour pair once
        here = (slice(max(0, -dy), ny - max(0, dy)), slice(max(0, -dx), nx - max(0, dx)))
        there = (slice(here[0].start + dy, here[0].stop + dy), slice(here[1].start + dx, here[1].stop + dx))
        too_steep = np.abs(height[there] - height[here]) > rise * r * math.hypot(dx, dy)
        steep[here] |= too_steep
        steep[there] |= too_steep
    grow = max(1, math.ceil(config.clearance_m / r))
    disk = np.hypot(*np.mgrid[-grow:grow + 1, -grow:grow + 1]) * r <= config.clearance_m
    blocked = ndimage.binary_dilation(steep, structure=disk)
    if len(starts):
        blocked |= _near_walls(terrain, low, r, (ny, nx), config.clearance_m)
    labels, _ = ndimage.label(~blocked, structure=np.ones((3, 3), dtype=bool))
    return TraversableGrid(low, r, labels, (distance <= terrain.toe_distance_m) & ~blocked)


def _near_walls(terrain: DitchTerrain, origin: np.ndarray, resolution_m: float, shape: tuple[int, int],
                clearance_m: float) -> np.ndarray:
    """Which cells of the grid (cell (0, 0)'s centre at `origin`) lie within `clearance_m` of a
    wall: each segment measured only over the cells of its own bounding box."""
    near = np.zeros(shape, dtype=bool)
    for start, end, half in zip(*terrain.wall_segments(), strict=True):
        reach = half + clearance_m
        low = np.floor((np.minimum(start, end) - reach - origin) / resolution_m).astype(int)
        high = np.ceil((np.maximum(start, end) + reach - origin) / resolution_m).astype(int) + 1
        (x0, y0), (x1, y1) = np.maximum(low, 0), np.minimum(high, [shape[1], shape[0]])
        if x1 <= x0 or y1 <= y0:
            continue
        xs, ys = origin[0] + resolution_m * np.arange(x0, x1), origin[1] + resolution_m * np.arange(y0, y1)
        cells = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1).reshape(-1, 2)
        gap = _distance_to_segments(cells, start[None], end[None], np.array([half]))
        near[y0:y1, x0:x1] |= gap.reshape(y1 - y0, x1 - x0) <= clearance_m
    return near


def check_ways_in_and_out(terrain: DitchTerrain, start_xy, goal_xy, grid: TraversableGrid | None = None,
                          config: IngressConfig | None = None) -> None:
    """Raises ConfigError unless a way leads from the start down to the ditch's floor and one from
    the floor up to the goal, through ground no steeper than `max_traversable_slope_deg` (see
    the module docstring). `grid`: `traversable_grid(terrain, config)` if already made (one
    grid serves every task of a terrain)."""
    config = config or IngressConfig()
    grid = grid if grid is not None else traversable_grid(terrain, config)
    limit = f"max_traversable_slope_deg={config.max_traversable_slope_deg:.1f}"
    labels = {}
    for label, xy in (("start", start_xy), ("goal", goal_xy)):
        labels[label] = grid.label_at(xy)
        if labels[label] == 0:
            raise ConfigError(f"{label} {list(xy)} is not on ground the robot can drive on (no steeper than {limit} "
                              f"deg, {config.clearance_m:.2f} m from anything steeper or a wall)")
    floor = grid.floor_labels()
    for label, way, toward in (("start", "in", "down to"), ("goal", "out", "up from")):
        if labels[label] not in floor:
            xy = start_xy if label == "start" else goal_xy
            side = _wall_side(terrain, xy)
            raise ConfigError(f"no way {way}: no route from the {label} {list(xy)} {toward} the ditch's floor keeps "
                              f"to ground no steeper than {limit} deg; expected a window on the walls (on the "
                              f"{label}'s side: wall_slopes.{side}), sections no steeper than that, wider than "
                              "the robot")
    if labels["start"] != labels["goal"]:
        raise ConfigError(f"the ditch's floor does not join the way in from the start {list(start_xy)} to the way "
                          f"out to the goal {list(goal_xy)}: expected a floor wider than the robot")


def _wall_side(terrain: DitchTerrain, xy) -> str:
    """The wall ("right" or "left" of the course) on the side of planar point `xy`."""
    a, vec = terrain.course_xy[0], terrain.course_xy[-1] - terrain.course_xy[0]
    rel = np.asarray(xy, dtype=float) - a
    return "left" if vec[0] * rel[1] - vec[1] * rel[0] > 0.0 else "right"


def check_windows(terrain: DitchTerrain, config: IngressConfig | None = None) -> None:
    """Raises ConfigError, naming the section (`terrain.wall_slopes.<side>[i]`), when a window
    (a run of sections no steeper than `max_traversable_slope_deg`) is narrower along the
    course than the robot is wide (`robot.CHASSIS_SIZE_M`)."""
    config = config or IngressConfig()
    width = float(robot.CHASSIS_SIZE_M[1])
    for side in WALL_SIDES:
        if not getattr(terrain.params.wall_slopes, side):
            continue
        for window in crossable_windows(terrain, side, config.max_traversable_slope_deg):
            if window.width_m < width:
                first, last = window.first_section, window.last_section
                keys = f"[{first}]" if last == first else f"[{first}..{last}]"
                raise ConfigError(f"terrain.wall_slopes.{side}{keys}: a window (no steeper than "
                                  f"max_traversable_slope_deg={config.max_traversable_slope_deg:.1f} deg) from "
                                  f"{window.from_m:g} to {window.to_m:g} m is {window.width_m:.2f} m wide; expected "
                                  f"at least the robot's width, {width:.2f} m")
