"""The geometry of a rolling grid window centred on the robot, shared by the slope costmap and
the elevation map: square cells of side `resolution` on a world lattice, an origin in whole
cells, arrays indexed [iy, ix] so that cell (iy, ix) covers x in [(ox + ix) r, (ox + ix + 1) r),
y in [(oy + iy) r, (oy + iy + 1) r)."""

import math

import numpy as np

# The most cells a rolling map may hold (1000 x 1000). A map is part of its controller's state,
# copied at every control update, and a fine resolution grows it as its square: at the default
# 0.1 m the maps hold 14,400 (elevation) and 40,000 (costmap) cells, while 0.0001 m would ask
# for 10^10 and end in a MemoryError mid-rollout.
MAX_WINDOW_CELLS = 1_000_000


def window_cells(size_x_m: float, size_y_m: float, resolution_m: float) -> float:
    """How many cells a window of these sides (m) holds at `resolution_m`, rounded as the maps
    round (inf for an infinite side)."""
    sides = [size_x_m / resolution_m, size_y_m / resolution_m]
    if not all(math.isfinite(side) for side in sides):
        return math.inf
    return max(4, round(sides[0])) * max(4, round(sides[1]))


class RollingWindow:
    """A window of `shape` (ny, nx) cells of side `resolution` (m); cells entering it when it
    moves hold `fill_value`. It holds no cell values itself."""

    def __init__(self, resolution: float, shape: tuple[int, int], fill_value: float):
        self.resolution = float(resolution)
        self.shape = (int(shape[0]), int(shape[1]))
        self.size = self.shape[0] * self.shape[1]
        self.fill_value = float(fill_value)

    def window_origin(self, xy: np.ndarray) -> np.ndarray:
        """Origin (cells, (2,) int: [ox, oy]) of the window centred on the planar point `xy` (m)."""
        cell = np.floor(np.asarray(xy, dtype=float)[:2] / self.resolution).astype(int)
        return cell - np.array([self.shape[1] // 2, self.shape[0] // 2])

    def origin_m(self, origin: np.ndarray) -> np.ndarray:
        """World xy (m) of the window's lower-left corner."""
        return np.asarray(origin, dtype=float) * self.resolution

    def world_to_cell(self, origin: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cells (iy, ix) of world points xy (..., 2), and a mask of those inside the window."""
        cells = np.floor(np.asarray(xy, dtype=float) / self.resolution).astype(int) - np.asarray(origin)
        ix, iy = cells[..., 0], cells[..., 1]
        inside = (ix >= 0) & (ix < self.shape[1]) & (iy >= 0) & (iy < self.shape[0])
        return iy, ix, inside

    def cell_centers(self, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World x (nx,) and y (ny,) of the cell centres (m)."""
        ox, oy = self.origin_m(origin)
        return (ox + (np.arange(self.shape[1]) + 0.5) * self.resolution,
                oy + (np.arange(self.shape[0]) + 0.5) * self.resolution)

    def roll(self, values: np.ndarray, old_origin: np.ndarray, new_origin: np.ndarray) -> np.ndarray:
        """Moves the window: cells in both windows keep their values, new cells hold `fill_value`."""
        out = np.full(self.shape, self.fill_value)
        dx, dy = (int(v) for v in np.asarray(new_origin) - np.asarray(old_origin))
        ny, nx = self.shape
        if abs(dx) >= nx or abs(dy) >= ny:
            return out
        out[max(-dy, 0):ny + min(-dy, 0), max(-dx, 0):nx + min(-dx, 0)] = \
            values[max(dy, 0):ny + min(dy, 0), max(dx, 0):nx + min(dx, 0)]
        return out

    def pack(self, origin_m: np.ndarray, values: np.ndarray) -> np.ndarray:
        """The window as a controller's output vector: [origin_x (m), origin_y (m), values
        row-major]; `unpack` reads it back."""
        return np.concatenate([origin_m, np.reshape(values, -1)])

    def unpack(self, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origin xy (m), values of `shape`) from a vector made by `pack`."""
        value = np.asarray(value)
        return value[:2].copy(), value[2:].reshape(self.shape).copy()
