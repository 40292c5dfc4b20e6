"""A lidar cloud's returns in the world frame, as the planners' maps take them: the finite
points only (an organized cloud holds a non-finite point where a ray returned nothing), less
those on the robot itself."""

from collections.abc import Callable

import numpy as np
from pydrake.math import RigidTransform
from pydrake.perception import PointCloud

from ditch_drake.spec import robot


def returns_in_world(cloud: PointCloud, X_BL: RigidTransform, X_WB: RigidTransform,
                     on_robot_B: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The cloud's returns in W, less those on the robot.

    Args:
        cloud: points in the lidar frame L; non-finite: no return.
        X_BL: L's pose in the chassis frame B.
        X_WB: B's pose in W.
        on_robot_B: marks (with True) the points (3, M) in B that belong to the robot, whose
            returns are dropped; None: none do.

    Returns:
        The returns p_WP (K, 3) in W, and the mask (N,) of the cloud's points that are returns.
    """
    xyzs = cloud.xyzs() if cloud.size() else np.zeros((3, 0))
    returned = np.isfinite(xyzs).all(axis=0)
    # Only the returns are transformed (an organized cloud is about half NaN), by plain matrix
    # products: they cost less than RigidTransform.multiply's shape-matching wrapper.
    p_BP = X_BL.rotation().matrix() @ xyzs[:, returned] + X_BL.translation()[:, None]
    if on_robot_B is not None:
        p_BP = p_BP[:, ~on_robot_B(p_BP)]
    return (X_WB.rotation().matrix() @ p_BP).T + X_WB.translation(), returned


def within_chassis_in_plan(margin_m: float) -> Callable[[np.ndarray], np.ndarray]:
    """An `on_robot_B` test: the points (3, M) in B within the chassis box in plan (x and y),
    grown by `margin_m` (m) on each side."""
    half = robot.CHASSIS_SIZE_M[:2] / 2 + margin_m

    def within(p_BP: np.ndarray) -> np.ndarray:
        return (np.abs(p_BP[0]) <= half[0]) & (np.abs(p_BP[1]) <= half[1])

    return within


def open_rays_B(rays_L: np.ndarray, X_BL: RigidTransform, margin_m: float = 0.01) -> np.ndarray:
    """Unit rays (N, 3) in B; NaN rows for those given as NaN or passing through the chassis box."""
    rays_B = rays_L.reshape(-1, 3) @ X_BL.rotation().matrix().T
    half = robot.CHASSIS_SIZE_M / 2 + margin_m
    with np.errstate(divide="ignore", invalid="ignore"):
        low = (robot.chassis_center_in_body_frame() - half - X_BL.translation()) / rays_B
        high = (robot.chassis_center_in_body_frame() + half - X_BL.translation()) / rays_B
    enter = np.fmax.reduce(np.minimum(low, high), axis=1)  # The slab test; NaN components drop out.
    leave = np.fmin.reduce(np.maximum(low, high), axis=1)
    blocked = (leave >= np.maximum(enter, 0.0)) & (leave > 0.0)
    return np.where(blocked[:, None], np.nan, rays_B)
