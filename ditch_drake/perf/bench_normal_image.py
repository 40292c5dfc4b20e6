"""Times the surface-normal image (`ditch_drake.perception.normal_image`) on a lidar-like cloud.

Run: `python -m ditch_drake.perf.bench_normal_image.py [points_count] [repeats]`. Prints the median
times (ms, one process, one core) of the whole cloud -> image step with the organized
(fast) and the PCA (reference) normal estimators.
"""

import itertools
import math
import sys
import time

import numpy as np

from ditch_drake.perception.normal_image import NormalImageConfig, cloud_to_normal_image
from ditch_drake.spec import robot


def ditch_height(
    x: np.ndarray,
    y: np.ndarray,
    yaw_rad: float = 0.3,
    center_m: float = 2.5,
    width_m: float = 1.5,
    depth_m: float = 1.0,
    slope_deg: float = 55.0,
) -> np.ndarray:
    """A smooth ditch across the way ahead (tanh walls of the given steepest slope), m."""
    across = x * math.cos(yaw_rad) + y * math.sin(yaw_rad) - center_m
    softness = depth_m / (2.0 * math.tan(math.radians(slope_deg)))
    return -0.5 * depth_m * (np.tanh((across + width_m / 2) / softness) - np.tanh((across - width_m / 2) / softness))


def lidar_depth_cloud(
    rows: int,
    cols: int,
    height_m: float = robot.WHEEL_RADIUS_M + robot.LIDAR_MOUNT_XYZ_M[2],
    range_m: float = robot.LIDAR_RANGE_M,
    **ditch,
) -> np.ndarray:
    """An organized (rows, cols, 3) cloud of `ditch_height` seen by a forward-looking lidar.

    The lidar sits `height_m` above the ground plane at the origin, +x forward, +y left, +z
    up; row 0 looks farthest down (-40 deg), the last row at the flat ground `range_m` away
    (the rays above it never return, so they are left out), column 0 leftmost. NaN where a
    ray meets no ground within `range_m`.
    """
    lowest_return = math.asin(height_m / range_m) + 0.002
    elevation = np.linspace(-robot.LIDAR_VERTICAL_FOV_RAD / 2, -lowest_return, rows)[:, None]
    azimuth = np.linspace(robot.LIDAR_HORIZONTAL_FOV_RAD / 2, -robot.LIDAR_HORIZONTAL_FOV_RAD / 2, cols)[None, :]
    direction = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        axis=-1,
    )
    origin = np.array([0.0, 0.0, height_m])

    def above(t):
        p = origin + t[..., None] * direction
        return p[..., 2] - ditch_height(p[..., 0], p[..., 1], **ditch)

    # March to the first crossing below the surface, then bisect.
    steps = np.linspace(0.0, range_m, 801)
    low = np.full((rows, cols), np.nan)
    for a, b in itertools.pairwise(steps):
        crossing = np.isnan(low) & (above(np.full((rows, cols), b)) < 0.0)
        low[crossing] = a
    hit = ~np.isnan(low)
    low = np.where(hit, low, 0.0)
    high = low + steps[1]
    for _ in range(30):
        mid = 0.5 * (low + high)
        below = above(mid) < 0.0
        high = np.where(below, mid, high)
        low = np.where(below, low, mid)
    points = origin + (0.5 * (low + high))[..., None] * direction
    points[~hit] = np.nan
    return points


def _median_ms(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def measure_normal_image_ms(points_count: int = 5000, repeats: int = 50) -> dict:
    """Median time (ms) from an organized lidar cloud of about `points_count` pixels to the image.

    Args:
        points_count: pixels of the depth image (3 columns per 2 rows); most return.
        repeats: timed runs per method (after one warm-up run each).

    Returns:
        {"normal_image_organized_ms": ..., "normal_image_pca_ms": ..., "points": valid points}.
    """
    rows = max(2, round(math.sqrt(points_count * 2 / 3)))
    cols = max(2, round(points_count / rows))
    grid = lidar_depth_cloud(rows, cols)
    points = grid.reshape(-1, 3)
    organized = NormalImageConfig(normal_method="organized")
    pca = NormalImageConfig(normal_method="pca")
    result = {}
    for name, config in (("normal_image_organized_ms", organized), ("normal_image_pca_ms", pca)):
        cloud_to_normal_image(points, config, (rows, cols))
        result[name] = _median_ms(lambda config=config: cloud_to_normal_image(points, config, (rows, cols)), repeats)
    result["points"] = int(np.isfinite(points).all(axis=1).sum())
    return result


if __name__ == "__main__":
    arguments = [int(a) for a in sys.argv[1:3]]
    print(measure_normal_image_ms(*arguments))
