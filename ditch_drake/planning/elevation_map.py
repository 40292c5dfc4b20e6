"""A rolling 2.5-D elevation map in plain numpy: ground height (m) per cell, NaN where unknown.

Grid. As the slope costmap (`ditch_drake.planning.costmap`): a window of `n x n` square cells
of side `resolution_m`, its origin kept in whole cells of a world lattice, so cell (iy, ix)
covers x in [(ox + ix) r, (ox + ix + 1) r), y in [(oy + iy) r, (oy + iy + 1) r). Arrays are
indexed [iy, ix]. The window is re-centred on the robot every update, moving by whole cells:
cells in both windows keep their heights, cells that enter come in unknown (NaN), cells that
leave are forgotten. The map is a plain float ndarray and the origin two integers, so a Drake
LeafSystem keeps both in its discrete state (`ditch_drake.systems.mppi_controller`).

Fusion rule (a cell seen more than once). Each scan first reduces its points to one height
per cell: the *highest* point in the cell. Within one scan a cell's points spread in height
where the lidar grazes a steep wall (a 55 deg wall rises 0.14 m across a 0.1 m cell) or where
a wall top and the ground behind it share a cell; the wheels ride on the top of that spread,
so the maximum, not the mean, is what the attitude prediction needs, and a single low stray
return (a grazing ray slipping past an edge to the ditch's floor) cannot pull a cell down.
The scan's cell height then blends into the stored one by an exponential moving average:

    h <- h_scan                                   if the cell was unknown,
    h <- h + new_weight (h_scan - h)              otherwise.

The average damps range noise (the maximum of noisy points is biased upward; averaging over
scans halves its spread at `new_weight` 0.5) while a change of view (a wall seen first from far
at a grazing angle, then from close) converges within a few scans: the robot drives toward
what it maps, so newer scans are the closer, better ones. A scan height that differs from the
stored one by more than `reset_jump_m` replaces it outright: such a jump is not noise but a
surface seen for the first time (the top of a wall whose foot was seen before).
"""

import math
from dataclasses import dataclass

import numpy as np

from ditch_drake.common.errors import ConfigError
from ditch_drake.planning.rolling_window import MAX_WINDOW_CELLS, RollingWindow, window_cells


@dataclass
class ElevationMapConfig:
    """The rolling elevation grid (m).

    Attributes:
        resolution_m: cell side.
        size_m: window side, centred on the robot (rounded to whole cells).
        new_weight: weight of a new scan's cell height against the stored one, in (0, 1];
            1 keeps the newest scan only.
        reset_jump_m: a new cell height further than this from the stored one replaces it
            (module doc); inf never.
    """

    resolution_m: float = 0.1
    size_m: float = 12.0
    new_weight: float = 0.5
    reset_jump_m: float = 0.3

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of range."""
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise ConfigError(f"elevation map resolution_m={self.resolution_m!r}: expected a positive length")
        if not (math.isfinite(self.size_m) and self.size_m >= 4 * self.resolution_m):
            raise ConfigError(f"elevation map size_m={self.size_m!r}: expected at least 4 cells of resolution_m")
        cells = window_cells(self.size_m, self.size_m, self.resolution_m)
        if cells > MAX_WINDOW_CELLS:
            raise ConfigError(f"elevation map size_m={self.size_m!r} at resolution_m={self.resolution_m!r} is "
                              f"{cells:,} cells; expected at most {MAX_WINDOW_CELLS:,} (a coarser resolution_m or "
                              "a smaller size_m)")
        if not 0.0 < self.new_weight <= 1.0:
            raise ConfigError(f"elevation map new_weight={self.new_weight!r}: expected 0 < new_weight <= 1")
        if not self.reset_jump_m > 0.0:
            raise ConfigError(f"elevation map reset_jump_m={self.reset_jump_m!r}: expected > 0 (inf: never)")


class ElevationGrid(RollingWindow):
    """The geometry and update rules of the rolling map; it holds no heights itself."""

    def __init__(self, config: ElevationMapConfig | None = None):
        self.config = config or ElevationMapConfig()
        self.config.validate()
        n = max(4, round(self.config.size_m / self.config.resolution_m))
        super().__init__(self.config.resolution_m, (n, n), np.nan)

    def empty(self) -> np.ndarray:
        """An all-unknown (NaN) map of `shape`."""
        return np.full(self.shape, np.nan)

    def scan_heights(self, origin: np.ndarray, points_W: np.ndarray) -> np.ndarray:
        """One scan's map: the highest finite point (N, 3) in W of each cell, NaN where none."""
        points_W = np.asarray(points_W, dtype=float).reshape(-1, 3)
        points_W = points_W[np.isfinite(points_W).all(axis=1)]
        iy, ix, inside = self.world_to_cell(origin, points_W[:, :2])
        flat = np.full(self.size, -np.inf)
        np.maximum.at(flat, iy[inside] * self.shape[1] + ix[inside], points_W[inside, 2])
        flat[flat == -np.inf] = np.nan
        return flat.reshape(self.shape)

    def fuse(self, heights: np.ndarray, origin: np.ndarray, points_W: np.ndarray) -> np.ndarray:
        """The map `heights` (of the window at `origin`) with a scan's points (N, 3) in W fused in
        by the module doc's rule; unseen cells keep their values (unknown stays NaN)."""
        scan = self.scan_heights(origin, points_W)
        seen = np.isfinite(scan)
        blended = heights + self.config.new_weight * (scan - heights)
        replace = seen & (~np.isfinite(heights) | (np.abs(scan - heights) > self.config.reset_jump_m))
        return np.where(replace, scan, np.where(seen, blended, heights))

    def fill_footprint(self, heights: np.ndarray, origin: np.ndarray, pose: np.ndarray, half_size_xy,
                       ground_point_W: np.ndarray, ground_normal_W: np.ndarray) -> np.ndarray:
        """Sets the unknown cells under the rectangle of half sizes `half_size_xy` (m, in the robot's
        planar frame) at pose (x, y, yaw) to the plane through `ground_point_W` with normal
        `ground_normal_W`: the ground under the robot's own wheels, which the lidar never sees."""
        xs, ys = self.cell_centers(origin)
        dx, dy = xs[None, :] - pose[0], ys[:, None] - pose[1]
        c, s = math.cos(pose[2]), math.sin(pose[2])
        under = (np.abs(c * dx + s * dy) <= half_size_xy[0]) & (np.abs(c * dy - s * dx) <= half_size_xy[1])
        p, n = np.asarray(ground_point_W, dtype=float), np.asarray(ground_normal_W, dtype=float)
        plane = p[2] - (n[0] * (xs[None, :] - p[0]) + n[1] * (ys[:, None] - p[1])) / max(n[2], 1e-6)
        return np.where(under & ~np.isfinite(heights), plane, heights)

    def sample(self, heights: np.ndarray, origin: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Heights (...) at world points xy (..., 2) by bilinear interpolation between cell centres.

        Unknown corners are left out and the known ones' weights renormalized; NaN where the
        known corners hold less than half the weight (about: the nearest cell is unknown) or the
        point lies outside the window.
        """
        xy = np.asarray(xy, dtype=float)
        ny, nx = self.shape
        u = (xy[..., 0] - self.origin_m(origin)[0]) / self.resolution - 0.5
        v = (xy[..., 1] - self.origin_m(origin)[1]) / self.resolution - 0.5
        inside = (u >= -0.5) & (u <= nx - 0.5) & (v >= -0.5) & (v <= ny - 0.5)
        u = np.clip(u, 0.0, nx - 1.000001)
        v = np.clip(v, 0.0, ny - 1.000001)
        ix, iy = u.astype(np.int64), v.astype(np.int64)
        fx, fy = u - ix, v - iy
        flat = heights.reshape(-1)
        base = iy * nx + ix
        total = np.zeros(u.shape)
        weight = np.zeros(u.shape)
        for offset, w in ((0, (1 - fx) * (1 - fy)), (1, fx * (1 - fy)), (nx, (1 - fx) * fy), (nx + 1, fx * fy)):
            h = flat[base + offset]
            known = np.isfinite(h)
            total += np.where(known, h, 0.0) * w
            weight += known * w
        with np.errstate(invalid="ignore", divide="ignore"):
            out = total / weight
        return np.where(inside & (weight >= 0.5), out, np.nan)


def presume_drops(heights: np.ndarray, resolution_m: float, slope_deg: float, max_distance_m: float,
                  within: np.ndarray | None = None) -> np.ndarray:
    """The map with its unknown cells near known ones presumed to fall away at `slope_deg`.

    A ditch's wall below its hinge is in the lidar's shadow until the robot is almost at the
    edge: the map shows flat ground ending in unknown cells. Read as "unknown", a planner drives
    head-on into it; read as the worst the terrain can be (a wall as steep as the ditches',
    falling away from the last known ground), the planner lines up a shallow angle to the edge
    *before* it reaches the hinge. Each unknown cell within `max_distance_m` of a known cell
    gets the height of its nearest known cell minus tan(slope) times the distance between the two
    cell centres; cells further out stay unknown (NaN), and so do those outside the mask `within`
    (where given: the caller's sensor range, so that the edge of what the lidar can reach on open
    ground is not taken for a drop).
    This is a planning view, computed per update; the stored map keeps unknown cells unknown.
    """
    unknown = ~np.isfinite(heights)
    if not unknown.any() or unknown.all() or not max_distance_m > 0:
        return heights
    from scipy.ndimage import distance_transform_edt

    distance, (iy, ix) = distance_transform_edt(unknown, return_indices=True)
    distance = distance * resolution_m
    presumed = heights[iy, ix] - math.tan(math.radians(slope_deg)) * distance
    presume = unknown & (distance <= max_distance_m)
    if within is not None:
        presume &= within
    return np.where(presume, presumed, heights)
