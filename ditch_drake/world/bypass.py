"""Proof that a fenced field leaves no way round its ditch: a planar search on a grid.

A walled environment (`TerrainParams.walls`) is meant to make every route from a task's
start to its goal cross the ditch, so that a planner cannot pass the test by driving round
the obstacle. `check_no_bypass` proves it on the analytic terrain:

- the whole field (the flat ground around the ditch, `DitchTerrain.bounds_xy`, and the walls)
  is rasterized into square cells of `resolution_m`; beyond its border the ground ends;
- a cell is blocked when a wall lies within `clearance_m` of its centre (the robot's half
  width: a gap narrower than the robot is closed), and, for the bypass search, also when
  the ground within `clearance_m` slopes more than `max_slope_deg` (the ditch's sides);
- 8-connected components of the free cells (`scipy.ndimage.label`) answer the questions.
  With the walls and the slopes blocked, the start's and the goal's components must differ
  (else there is a bypass) and must not reach the grid's border (else the robot can leave
  the fenced field without entering the ditch: the point is outside the walls, or they leave
  a gap). With only the walls blocked they must be one component (else the walls shut the
  goal off, even through the ditch). Diagonal steps
  between two blocked cells count as open, so the search finds more routes than a robot
  could drive: "no route" is a safe answer.

Where there is a route, a breadth-first search (`scipy.sparse.csgraph.breadth_first_order`)
gives one, and the error names a point on it.
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order
from scipy.spatial import cKDTree

from ditch_drake.common.errors import ConfigError
from ditch_drake.spec import robot
from ditch_drake.world.terrain import DitchTerrain


@dataclass
class BypassConfig:
    """The search's settings (m, degrees).

    Attributes:
        max_slope_deg: ground steeper than this is the ditch (a route may not use it).
            15 deg is where the project's results call a rollout one that entered the ditch.
        clearance_m: obstacles grow by this much: the robot's half width.
        resolution_m: the grid's cell side.
        margin_m: the grid reaches this far beyond the walls, and the field, on every side.
    """

    max_slope_deg: float = 15.0
    clearance_m: float = float(robot.CHASSIS_SIZE_M[1] / 2)
    resolution_m: float = 0.2
    margin_m: float = 1.0


@dataclass
class FieldGrid:
    """The rasterized field of one walled terrain.

    Attributes:
        origin: world xy (m) of cell (0, 0)'s centre.
        resolution_m: the cell side.
        walls_only: labels of the free components with only the walls blocked (0: blocked).
        walls_and_slopes: labels with the walls and the ditch's sides blocked (0: blocked).
        border_labels: the `walls_and_slopes` labels that touch the grid's border: ground
            outside the walls, or connected to it on level ground.
    """

    origin: np.ndarray
    resolution_m: float
    walls_only: np.ndarray
    walls_and_slopes: np.ndarray
    border_labels: frozenset

    def cell(self, xy) -> tuple[int, int] | None:
        """(iy, ix) of the cell holding xy, or None outside the grid."""
        ix, iy = (int(v) for v in np.round((np.asarray(xy, dtype=float) - self.origin) / self.resolution_m))
        ny, nx = self.walls_only.shape
        return (iy, ix) if 0 <= iy < ny and 0 <= ix < nx else None

    def center(self, iy: int, ix: int) -> np.ndarray:
        return self.origin + self.resolution_m * np.array([ix, iy], dtype=float)


def rasterize_field(terrain: DitchTerrain, config: BypassConfig | None = None) -> FieldGrid:
    """The labelled grid of a walled terrain's field (see the module docstring)."""
    config = config or BypassConfig()
    starts, ends, _ = terrain.wall_segments()
    if len(starts) == 0:
        raise ConfigError("the terrain has no walls: there is no fenced field to search")
    r = config.resolution_m
    field_low, field_high = terrain.bounds_xy()
    low = np.minimum.reduce([starts.min(axis=0), ends.min(axis=0), field_low]) - config.margin_m
    high = np.maximum.reduce([starts.max(axis=0), ends.max(axis=0), field_high]) + config.margin_m
    nx, ny = (int(v) + 1 for v in np.ceil((high - low) / r))
    xs, ys = low[0] + r * np.arange(nx), low[1] + r * np.arange(ny)
    grid = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1).reshape(-1, 2)
    walls = terrain.distance_to_walls(grid).reshape(ny, nx) <= config.clearance_m
    normal_z = np.ones(len(grid))
    near = _near_course(terrain, grid, terrain.half_width_m + r)
    if near.any():
        normal_z[near] = np.concatenate([terrain.normal(chunk)[:, 2]
                                         for chunk in np.array_split(grid[near], max(1, near.sum() // 20000))])
    steep = (normal_z < math.cos(math.radians(config.max_slope_deg))).reshape(ny, nx)
    grow = max(1, math.ceil(config.clearance_m / r))
    disk = np.hypot(*np.mgrid[-grow:grow + 1, -grow:grow + 1]) * r <= config.clearance_m
    steep = ndimage.binary_dilation(steep, structure=disk)
    eight = np.ones((3, 3), dtype=bool)
    walls_only, _ = ndimage.label(~walls, structure=eight)
    walls_and_slopes, _ = ndimage.label(~(walls | steep), structure=eight)
    border = np.concatenate([walls_and_slopes[0], walls_and_slopes[-1], walls_and_slopes[:, 0],
                             walls_and_slopes[:, -1]])
    return FieldGrid(low, r, walls_only, walls_and_slopes, frozenset(int(v) for v in border if v))


def _near_course(terrain: DitchTerrain, xy: np.ndarray, distance_m: float) -> np.ndarray:
    """Which points (N, 2) may lie within `distance_m` of the course: all that do, and some
    others. The ground is level beyond the hinge, so only these need the terrain's (points x
    course segments) query."""
    spacing = distance_m / 4
    samples = [terrain.course_xy[:1]]
    for a, b in zip(terrain.course_xy[:-1], terrain.course_xy[1:]):
        count = max(1, math.ceil(np.linalg.norm(b - a) / spacing))
        samples.append(a + np.outer(np.arange(1, count + 1) / count, b - a))
    # Every course point lies within spacing / 2 of a sample.
    gap, _ = cKDTree(np.concatenate(samples)).query(xy, distance_upper_bound=distance_m + spacing)
    return gap <= distance_m + spacing / 2


def route_between(labels: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> np.ndarray:
    """The cells (K, 2) [iy, ix] of a shortest 8-connected route through the nonzero cells of
    `labels` from `start` to `goal` (both in one component)."""
    ny, nx = labels.shape
    free = labels > 0
    index = np.arange(ny * nx).reshape(ny, nx)
    rows, cols = [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # Each undirected neighbour pair once.
        here = (slice(max(0, -dy), ny - max(0, dy)), slice(max(0, -dx), nx - max(0, dx)))
        there = (slice(here[0].start + dy, here[0].stop + dy), slice(here[1].start + dx, here[1].stop + dx))
        both = free[here] & free[there]
        rows.append(index[here][both])
        cols.append(index[there][both])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(ny * nx, ny * nx)).tocsr()
    _, predecessors = breadth_first_order(graph, index[start], directed=False, return_predecessors=True)
    path, node = [], index[goal]
    while node >= 0:
        path.append(node)
        node = predecessors[node]
    return np.stack(np.unravel_index(np.array(path[::-1]), (ny, nx)), axis=1)


def check_no_bypass(terrain: DitchTerrain, start_xy, goal_xy, grid: FieldGrid | None = None,
                    config: BypassConfig | None = None) -> None:
    """Raises ConfigError unless the walls enclose start and goal and every route between
    them crosses the ditch (see the module docstring). `grid`: `rasterize_field(terrain,
    config)` if already made (one grid serves every task of a terrain)."""
    grid = grid if grid is not None else rasterize_field(terrain, config)
    cells = {}
    for label, xy in (("start", start_xy), ("goal", goal_xy)):
        cell = grid.cell(xy)
        if cell is None or grid.walls_and_slopes[cell] == 0:
            raise ConfigError(f"{label} {list(xy)} is not on level ground clear of the walls")
        cells[label] = cell
    if grid.walls_and_slopes[cells["start"]] == grid.walls_and_slopes[cells["goal"]]:
        route = route_between(grid.walls_and_slopes, cells["start"], cells["goal"])
        # The route's point farthest from the straight line between them shows the way round.
        points = np.array([grid.center(*cell) for cell in route])
        start, goal = (np.asarray(v, dtype=float) for v in (start_xy, goal_xy))
        along = np.clip((points - start) @ (goal - start) / max(float((goal - start) @ (goal - start)), 1e-12), 0, 1)
        away = np.linalg.norm(points - (start + along[:, None] * (goal - start)), axis=1)
        x, y = points[int(np.argmax(away))]
        raise ConfigError(f"the walls leave a bypass: a route from the start {list(start_xy)} to the goal "
                          f"{list(goal_xy)} avoids the ditch's sides (it passes ({x:.1f}, {y:.1f})); expected "
                          "walls that close every way round the ditch")
    for label, xy in (("start", start_xy), ("goal", goal_xy)):
        if grid.walls_and_slopes[cells[label]] in grid.border_labels:
            raise ConfigError(f"{label} {list(xy)} is outside the walls: the robot can leave the fenced field "
                              "from it without entering the ditch; expected walls that enclose it")
    if grid.walls_only[cells["start"]] != grid.walls_only[cells["goal"]]:
        raise ConfigError(f"the walls shut the goal {list(goal_xy)} off from the start {list(start_xy)}: expected "
                          "a way between them through the ditch")
