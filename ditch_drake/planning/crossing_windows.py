"""Where a ditch's wall is gentle enough to cross, read from an elevation map: the pure logic of
`ditch_drake.systems.window_search`.

Frame. A straight edge line found in the map (`find_edge`): `along` runs along it, `across`
points from the robot's side into the ditch; a point's coordinates are (s, c) = (distance along,
distance across) from the line's `origin_xy`. A curving edge is read as its tangent where it was
first seen: the search is meant for straight ditches.

What a wall's slope is read from. In bins of `bin_m` along the edge, the known cells of the wall
(below the top for the near wall, above the floor for the far one, within a band across the
edge) are fitted by a plane h = a + b c + d s; the wall's slope is its steepest, atan(hypot(b, d)). A bin with
too few wall cells, or too small a height span, is unknown (NaN). A wall is seen only where the
lidar looks into it: from the top, the near wall below a hinge is in the shadow of the hinge, but
a gentle wall set back from a steep one (a window: the same floor, a wider top) is seen
obliquely from the steep wall's edge beside it; from the floor the far wall faces the lidar.
A wall that stays unseen is never taken for a crossable one.
"""

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EdgeFrame:
    """A straight edge line: a point on it (m, world) and unit vectors along it and across it
    (into the ditch)."""

    origin_xy: np.ndarray
    along: np.ndarray
    across: np.ndarray

    @staticmethod
    def from_vector(value) -> "EdgeFrame":
        """From [origin_x (m), origin_y (m), along angle (rad)]: across is along turned clockwise."""
        x, y, angle = (float(v) for v in value[:3])
        along = np.array([math.cos(angle), math.sin(angle)])
        return EdgeFrame(np.array([x, y]), along, np.array([along[1], -along[0]]))

    def to_vector(self) -> np.ndarray:
        return np.array([*self.origin_xy, math.atan2(self.along[1], self.along[0])])

    def coordinates(self, xy) -> tuple[np.ndarray, np.ndarray]:
        """(along s, across c) (m) of world points xy (..., 2)."""
        d = np.asarray(xy, dtype=float) - self.origin_xy
        return d @ self.along, d @ self.across

    def point(self, s: float, c: float) -> np.ndarray:
        """The world xy (m) at along `s`, across `c`."""
        return self.origin_xy + s * self.along + c * self.across


def cell_centres(heights: np.ndarray, origin_xy_m, resolution_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World x and y (m) of every cell of `heights` [iy, ix] (both of its shape)."""
    ny, nx = heights.shape
    xs = origin_xy_m[0] + (np.arange(nx) + 0.5) * resolution_m
    ys = origin_xy_m[1] + (np.arange(ny) + 0.5) * resolution_m
    return np.meshgrid(xs, ys)


def ground_height(heights: np.ndarray, origin_xy_m, resolution_m: float, xy, radius_m: float = 0.4) -> float:
    """The median known height (m) within `radius_m` of xy, NaN if none."""
    xs, ys = cell_centres(heights, origin_xy_m, resolution_m)
    near = (np.hypot(xs - xy[0], ys - xy[1]) <= radius_m) & np.isfinite(heights)
    return float(np.median(heights[near])) if near.any() else math.nan


def find_edge(heights: np.ndarray, origin_xy_m, resolution_m: float, robot_xy, heading_rad: float,
              ground_z_m: float, max_range_m: float = 3.0, sector_deg: float = 40.0, drop_m: float = 0.3,
              min_cells: int = 8, min_range_m: float = 1.0, gap_m: float = 0.6) -> EdgeFrame | None:
    """The straight edge ahead of the robot, or None where none is seen.

    Edge cells: known cells at the ground's height (within `drop_m`) followed, away from the
    robot, by `gap_m` of cells unknown or lower by more than `drop_m` (a hinge's shadow; the holes
    between a scan's sparse far returns, narrower, are closed over first), from `min_range_m` (past the ground under
    the robot, which the lidar sees only from about 1.25 m ahead of it) to `max_range_m` of the
    robot (short of the lidar's range, where open ground ends in unknown cells too), within
    `sector_deg` of its heading (short of the field of view's sides). Their principal direction is the edge's.
    """
    from scipy.ndimage import binary_closing

    known = np.isfinite(heights)
    top = known & (np.abs(np.where(known, heights, 0.0) - ground_z_m) <= drop_m)
    gap_cells = max(1, round(gap_m / resolution_m))
    # A scan's far returns lie on arcs with unknown cells between them: closed over, they are no drop.
    covered = binary_closing(known, structure=np.ones((gap_cells + 1, gap_cells + 1), dtype=bool))
    beyond = ~(covered | known) | (np.where(known, heights, np.inf) < ground_z_m - drop_m)
    xs, ys = cell_centres(heights, origin_xy_m, resolution_m)
    dx, dy = xs - robot_xy[0], ys - robot_xy[1]
    edge = np.zeros_like(top)
    for oy, ox in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        outward_beyond = top & (ox * dx + oy * dy > 0)
        for k in range(1, gap_cells + 1):
            outward_beyond &= _shifted(beyond, k * oy, k * ox)
        edge |= outward_beyond
    bearing = np.arctan2(dy, dx) - heading_rad
    ahead = np.abs(np.arctan2(np.sin(bearing), np.cos(bearing))) <= math.radians(sector_deg)
    edge &= ahead & (np.hypot(dx, dy) <= max_range_m) & (np.hypot(dx, dy) >= min_range_m)
    if edge.sum() < min_cells:
        return None
    points = np.column_stack([xs[edge], ys[edge]])
    centre = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - centre).T))
    along = vectors[:, 1]
    across = np.array([along[1], -along[0]])
    if across @ (centre - np.asarray(robot_xy, dtype=float)[:2]) < 0:
        along, across = -along, -across
    return EdgeFrame(centre, along, across)


def _shifted(mask: np.ndarray, oy: int, ox: int) -> np.ndarray:
    """out[iy, ix] = mask[iy + oy, ix + ox], False off the array."""
    out = np.zeros_like(mask)
    ny, nx = mask.shape
    if abs(oy) < ny and abs(ox) < nx:
        out[max(-oy, 0):ny - max(oy, 0), max(-ox, 0):nx - max(ox, 0)] = \
            mask[max(oy, 0):ny - max(-oy, 0), max(ox, 0):nx - max(-ox, 0)]
    return out


def wall_slopes(heights: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame, bin_edges_m: np.ndarray,
                reference_z_m: float, across_band_m: tuple[float, float], rising: bool, min_rise_m: float = 0.3,
                min_cells: int = 4, min_span_m: float = 0.3) -> np.ndarray:
    """The wall's slope (deg, NaN unknown) in each bin between consecutive `bin_edges_m` along.

    Wall cells: known cells within `across_band_m` (c from, to) whose height lies beyond
    `reference_z_m` by more than `min_rise_m`: below it for the near wall seen from the top
    (`rising` False: the ground falls into the ditch), above it for the far wall seen from the
    floor (`rising` True); and, in each bin, more than `min_rise_m` off the bin's other extreme
    (the floor, or the far top, where the map holds it). A bin's slope is the steepest of the
    least-squares plane h = a + b c + d s through its wall cells, atan(hypot(b, d)); unknown with fewer than `min_cells` or a height span under `min_span_m`.
    """
    xs, ys = cell_centres(heights, origin_xy_m, resolution_m)
    s, c = frame.coordinates(np.stack([xs, ys], axis=-1))
    known = np.isfinite(heights)
    h = np.where(known, heights, reference_z_m)
    beyond = (h - reference_z_m > min_rise_m) if rising else (reference_z_m - h > min_rise_m)
    wall = known & beyond & (c >= across_band_m[0]) & (c <= across_band_m[1])
    s, c, h = s[wall], c[wall], h[wall]
    slopes = np.full(len(bin_edges_m) - 1, np.nan)
    which = np.digitize(s, bin_edges_m) - 1
    for b in np.unique(which[(which >= 0) & (which < len(slopes))]):
        in_bin = which == b
        # Off the other level too (the floor below a near wall, the top above a far one), where seen.
        extreme = h[in_bin].max() if rising else h[in_bin].min()
        in_bin &= np.abs(h - extreme) > min_rise_m
        if in_bin.sum() < min_cells or np.ptp(h[in_bin]) < min_span_m or np.ptp(c[in_bin]) < resolution_m:
            continue
        # A plane, not a line across: where the wall turns away from the edge line (the ditch's
        # rounded end), its heights fall along too, and a line across alone would read it gentle.
        design = np.column_stack([np.ones(in_bin.sum()), c[in_bin], s[in_bin]])
        _, across_gradient, along_gradient = np.linalg.lstsq(design, h[in_bin], rcond=None)[0]
        slopes[b] = math.degrees(math.atan(math.hypot(across_gradient, along_gradient)))
    return slopes


def crossable_windows(bin_edges_m: np.ndarray, slopes_deg: np.ndarray, limit_deg: float,
                      min_length_m: float) -> list[tuple[float, float]]:
    """The runs of bins whose known slope is at most `limit_deg`, at least `min_length_m` long:
    [(from s, to s)] (m) in order along. An unknown bin ends a run: what was not seen is no way."""
    crossable = np.isfinite(slopes_deg) & (np.nan_to_num(slopes_deg, nan=90.0) <= limit_deg)
    windows, start = [], None
    for b, ok in enumerate([*crossable, False]):
        if ok and start is None:
            start = b
        elif not ok and start is not None:
            if bin_edges_m[b] - bin_edges_m[start] >= min_length_m - 1e-9:
                windows.append((float(bin_edges_m[start]), float(bin_edges_m[b])))
            start = None
    return windows


def nearest_window(windows: list[tuple[float, float]], s_m: float) -> tuple[float, float] | None:
    """The window nearest along to `s_m` (one containing it first), None if there is none."""
    if not windows:
        return None
    return min(windows, key=lambda w: max(w[0] - s_m, s_m - w[1], 0.0))


def along_target(window: tuple[float, float], s_m: float, direction: float, lead_m: float, margin_m: float) -> float:
    """Where along a crossing through `window` should aim, from the robot at `s_m` heading
    `direction` (+-1) along: `lead_m` ahead (an oblique crossing travels along the wall while it
    goes down or up), kept within the window less `margin_m` at each end."""
    low, high = window[0] + margin_m, window[1] - margin_m
    if low > high:
        low = high = (window[0] + window[1]) / 2
    return float(np.clip(s_m + direction * lead_m, low, high))


def nearest_rise(heights: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame, reference_z_m: float,
                 across_band_m: tuple[float, float], min_rise_m: float = 0.3) -> float:
    """The least across c (m) of a known cell within `across_band_m` rising more than `min_rise_m`
    above `reference_z_m` (the far wall's foot seen from the floor), NaN if none."""
    rise = np.isfinite(heights) & (np.nan_to_num(heights, nan=-np.inf) - reference_z_m > min_rise_m)
    return _least_across(rise, origin_xy_m, resolution_m, frame, across_band_m)


def nearest_drop(heights: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame, s_range_m: tuple[float, float],
                 across_band_m: tuple[float, float], top_z_m: float, drop_m: float = 0.3) -> float:
    """The least across c (m) of a known cell within `s_range_m` along and `across_band_m` lower
    than `top_z_m` by more than `drop_m`: where the top is seen to fall away there (a window's
    hinge, set back from the steep wall's edge line), NaN if none."""
    drop = np.isfinite(heights) & (top_z_m - np.nan_to_num(heights, nan=np.inf) > drop_m)
    return _least_across(drop, origin_xy_m, resolution_m, frame, across_band_m, s_range_m)


def _least_across(cells: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame,
                  across_band_m: tuple[float, float], s_range_m: tuple[float, float] | None = None) -> float:
    """The least across c (m) of the map cells `cells` (a mask) within `across_band_m` and, where
    given, `s_range_m` along; NaN if none."""
    xs, ys = cell_centres(cells, origin_xy_m, resolution_m)
    s, c = frame.coordinates(np.stack([xs, ys], axis=-1))
    cells = cells & (c >= across_band_m[0]) & (c <= across_band_m[1])
    if s_range_m is not None:
        cells &= (s >= min(s_range_m)) & (s <= max(s_range_m))
    return float(c[cells].min()) if cells.any() else math.nan


def patch(heights: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame, s_range_m: tuple[float, float],
          c_range_m: tuple[float, float]) -> tuple[float, np.ndarray]:
    """(the fraction of cells known, their heights (m)) within along `s_range_m` and across
    `c_range_m` (each from, to; m)."""
    xs, ys = cell_centres(heights, origin_xy_m, resolution_m)
    s, c = frame.coordinates(np.stack([xs, ys], axis=-1))
    inside = (s >= min(s_range_m)) & (s <= max(s_range_m)) & (c >= c_range_m[0]) & (c <= c_range_m[1])
    if not inside.any():
        return 0.0, np.zeros(0)
    known = inside & np.isfinite(heights)
    return float(known.sum() / inside.sum()), heights[known]


def edge_ended(heights: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame, s_range_m: tuple[float, float],
               c_range_m: tuple[float, float], top_z_m: float, drop_m: float = 0.3,
               min_known_fraction: float = 0.7) -> bool:
    """Whether the ground across the edge line within `s_range_m` along is seen level with the
    top (most cells known, none lower than `top_z_m` by `drop_m`): the ditch has ended there (its
    rounded end). A wall beyond the line is either in the hinge's shadow (unknown) or falls away."""
    known_fraction, h = patch(heights, origin_xy_m, resolution_m, frame, s_range_m, c_range_m)
    return known_fraction >= min_known_fraction and bool(np.all(np.abs(h - top_z_m) <= drop_m))


def floor_ended(heights: np.ndarray, origin_xy_m, resolution_m: float, frame: EdgeFrame, s_range_m: tuple[float, float],
                c_range_m: tuple[float, float], floor_z_m: float, rise_m: float = 0.5, min_cells: int = 10) -> bool:
    """Whether the floor within `s_range_m` along and `c_range_m` across rises (at least
    `min_cells` cells more than `rise_m` above `floor_z_m`): a wall across the way along (the
    ditch's rounded end)."""
    _, h = patch(heights, origin_xy_m, resolution_m, frame, s_range_m, c_range_m)
    return int(np.sum(h - floor_z_m > rise_m)) >= min_cells


def crossing_direction(window: tuple[float, float], s_m: float, direction: float, needed_m: float,
                       under_way: bool = False, turn_m: float = 0.0) -> float:
    """Which way along (+-1) a crossing through `window` should travel from `s_m`: on
    `direction` while the window leaves `needed_m` ahead, else the way with more of it (back
    into it, where the robot has passed its end). `under_way` (the way already chosen on this
    level): kept while the window leaves `turn_m` ahead. Choosing anew by `needed_m` at every
    update turned the robot about wherever a window left less than `needed_m` ahead: in the
    middle of one shorter than twice `needed_m`, a few metres short of the end of a longer one,
    and each turn cost the time the next one was taken in."""
    ahead = window[1] - s_m if direction > 0 else s_m - window[0]
    if ahead >= (turn_m if under_way else needed_m):
        return direction
    behind = s_m - window[0] if direction > 0 else window[1] - s_m
    return -direction if behind > ahead else direction
