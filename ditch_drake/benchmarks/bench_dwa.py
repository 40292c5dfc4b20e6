"""Times one control step of the move_base baseline (`ditch_drake.systems.dwa.DwaController`).

Run: `python benchmarks/bench_dwa.py [points_count] [steps]`. One step is the whole periodic
update: roll the 20 m costmap window, PCA normals and raytracing of the cloud, inflation,
Dijkstra (every 10th step at planner_frequency 1 Hz) and the DWA. The cloud is
`bench_normal_image.lidar_depth_cloud`: a forward lidar's view of a ditch across the way
ahead, in the lidar frame L; the robot advances 0.1 m a step.
"""

import math
import sys
import time

import numpy as np
from pydrake.math import RigidTransform
from pydrake.perception import BaseField, Fields, PointCloud

from ditch_drake import robot
from ditch_drake.benchmarks.bench_normal_image import lidar_depth_cloud
from ditch_drake.systems.dwa import DwaController


def realistic_cloud(points_count: int = 4000) -> tuple[PointCloud, np.ndarray]:
    """A lidar's organized view (about `points_count` rays, 3 columns per 2 rows) of a ditch
    ahead, in L (NaN where a ray returns nothing), and the rays' unit directions (N, 3) in L."""
    rows = max(2, round(math.sqrt(points_count * 2 / 3)))
    cols = max(2, round(points_count / rows))
    height = robot.WHEEL_RADIUS_M + robot.LIDAR_MOUNT_XYZ_M[2]
    points = lidar_depth_cloud(rows, cols, height_m=height).reshape(-1, 3) - [0.0, 0.0, height]
    # The same rays as `lidar_depth_cloud`'s.
    elevation = np.linspace(-robot.LIDAR_VERTICAL_FOV_RAD / 2, -math.asin(height / robot.LIDAR_RANGE_M) - 0.002, rows)
    azimuth = np.linspace(robot.LIDAR_HORIZONTAL_FOV_RAD / 2, -robot.LIDAR_HORIZONTAL_FOV_RAD / 2, cols)
    e, a = (g.ravel() for g in np.meshgrid(elevation, azimuth, indexing="ij"))
    rays = np.c_[np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]
    cloud = PointCloud(len(points), Fields(BaseField.kXYZs))
    cloud.mutable_xyzs()[:] = points.T.astype(np.float32)
    return cloud, rays


def measure_dwa_step_ms(points_count: int = 4000, steps: int = 30) -> dict:
    """Times `steps` consecutive control-step updates after one warm-up step.

    The controller reads the cloud as organized (`ray_directions_L`), so the rays without a
    return are raytraced too, as with the project's lidar.

    Returns:
        {"dwa_step_ms": mean over the steps (replanning amortized), "dwa_step_median_ms",
        "dwa_step_max_ms" (a replanning step), "points": returns in the cloud}.
    """
    X_BL = RigidTransform(robot.LIDAR_MOUNT_XYZ_M)
    cloud, rays = realistic_cloud(points_count)
    controller = DwaController([30.0, 0.0], 1, X_BL, ray_directions_L=rays)
    context = controller.CreateDefaultContext()
    controller.GetInputPort("point_cloud").FixValue(context, cloud)
    poses = controller.GetInputPort("body_poses")
    times = []
    for step in range(steps + 1):
        poses.FixValue(context, [RigidTransform(), RigidTransform([0.1 * step, 0.0, robot.WHEEL_RADIUS_M])])
        context.SetTime(robot.CONTROL_PERIOD_S * step)
        start = time.perf_counter()
        context.SetDiscreteState(controller.EvalUniquePeriodicDiscreteUpdate(context))
        times.append(time.perf_counter() - start)
    times = 1e3 * np.array(times[1:])
    return {
        "dwa_step_ms": float(times.mean()),
        "dwa_step_median_ms": float(np.median(times)),
        "dwa_step_max_ms": float(times.max()),
        "points": int(np.isfinite(cloud.xyzs()).all(axis=0).sum()),
    }


if __name__ == "__main__":
    arguments = [int(a) for a in sys.argv[1:3]]
    print(measure_dwa_step_ms(*arguments))
