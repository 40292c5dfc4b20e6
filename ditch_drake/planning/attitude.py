"""The chassis attitude a planar pose would have on an elevation map, and its margin to tipping.

For poses (x, y, yaw), vectorized over any leading shape:

1. The four wheel contact points are the wheel joints' planar positions
   (`ditch_drake.spec.robot.wheel_positions_in_body_frame`: +-wheelbase/2, +-track/2) rotated by
   yaw; their heights come from the map (`ElevationGrid.sample`, bilinear).
2. A plane z = c0 + cx x + cy y (x, y in the yawed frame Y: +x the robot's heading, +y to its
   left) is fitted to them by least squares (exact through three known wheels; with fewer than
   three the attitude is unknown: NaN). For the symmetric rectangle the fit with all four is
   closed form: cx = (front - rear) / (2 wheelbase), cy = (left - right) / (2 track), sums of two
   wheels each. The chassis lies in that plane with its x-axis along the heading.
3. Roll and pitch are Drake's `RollPitchYaw` of that chassis, R_WB = Rz(yaw) Ry(pitch) Rx(roll):
   pitch = -atan(cx) (positive pitch is nose *down*), roll = asin(cy / sqrt(1 + cx^2 + cy^2))
   (positive roll is the left side *up*).
4. The static stability margin is the episode monitor's rule
   (`ditch_drake.systems.episode_monitor.stability_margins_rad`): with u the world's up in B,
   the lean toward the side wheels is atan2(u_y, u_z), toward the axles atan2(u_x, u_z), and
   the margin is min(sideways tip angle - |side lean|, fore-aft tip angle - |axle lean|), the tip
   angles from the robot's dimensions (`robot.tip_angle_sideways_rad`,
   `robot.tip_angle_fore_aft_rad`: about 61.6 and 59.6 deg). This is the force-angle margin of
   Papadopoulos and Rey (1996) for a rectangular support polygon: for each edge, the angle
   gravity must turn about that edge, measured in the plane normal to the edge, before the
   line of gravity through the centre of mass leaves the rectangle. Tilt in a diagonal
   direction is handled exactly: the projected centre of mass leaves a rectangle only across an
   edge, and each edge's condition involves only the lean in its own normal plane, so the
   minimum over the four edges is the combined margin, not an approximation of it.

Optionally (`clearance_m`), the chassis underside is checked: the map's height at a 5 x 3
stencil over the chassis rectangle, measured perpendicular to the wheel plane, must stay below
`clearance_m` (a wall or step between the wheels, or the ditch floor under the front bumper
when nosing into the toe).
"""

from dataclasses import dataclass

import numpy as np

from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.spec import robot

_WHEELS_B = np.array([robot.wheel_positions_in_body_frame()[name][:2] for name in robot.WHEEL_NAMES])
_HALF_WHEELBASE, _HALF_TRACK = robot.WHEELBASE_M / 2, robot.TRACK_M / 2
_STENCIL_B = np.stack(np.meshgrid(np.linspace(-1, 1, 5) * robot.CHASSIS_SIZE_M[0] / 2,
                                  np.linspace(-1, 1, 3) * robot.CHASSIS_SIZE_M[1] / 2), axis=-1).reshape(-1, 2)


@dataclass
class Attitude:
    """Predicted chassis attitude at poses of shape S (angles in rad).

    Attributes:
        roll: (S) Drake roll of the chassis; NaN where fewer than three wheels are known.
        pitch: (S) Drake pitch (positive: nose down); NaN likewise.
        margin: (S) static stability margin (negative: it tips); NaN likewise.
        side_margin: (S) its sideways part (about the left/right wheel lines).
        axle_margin: (S) its fore-aft part (about the front/rear axles).
        unknown: (S) some wheel stands on an unknown cell (or outside the map).
        obstructed: (S) the chassis underside would touch the map (False without `clearance_m`).
    """

    roll: np.ndarray
    pitch: np.ndarray
    margin: np.ndarray
    side_margin: np.ndarray
    axle_margin: np.ndarray
    unknown: np.ndarray
    obstructed: np.ndarray


def to_planar_frame(poses: np.ndarray, points_B: np.ndarray) -> np.ndarray:
    """World xy (S, P, 2) of planar body points (P, 2) at poses (S, 3)."""
    poses = np.asarray(poses, dtype=float)
    c, s = np.cos(poses[..., 2])[..., None], np.sin(poses[..., 2])[..., None]
    x = poses[..., 0:1] + c * points_B[:, 0] - s * points_B[:, 1]
    y = poses[..., 1:2] + s * points_B[:, 0] + c * points_B[:, 1]
    return np.stack([x, y], axis=-1)


def stability_margins(roll: np.ndarray, pitch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sideways and fore-aft static margins (rad) of chassis attitudes (module doc, step 4);
    the stability margin is their minimum."""
    sin_p, cos_p = np.sin(pitch), np.cos(pitch)
    up_x, up_y, up_z = -sin_p, cos_p * np.sin(roll), cos_p * np.cos(roll)
    side = robot.tip_angle_sideways_rad() - np.abs(np.arctan2(up_y, up_z))
    axle = robot.tip_angle_fore_aft_rad() - np.abs(np.arctan2(up_x, up_z))
    return side, axle


def fit_wheel_plane(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares plane (c0, cx, cy) in the frame Y through wheel heights z (S, 4), ordered as
    `robot.WHEEL_NAMES`; NaN heights are left out, and NaN planes where fewer than three remain."""
    z = np.asarray(z, dtype=float)
    known = np.isfinite(z)
    count = known.sum(axis=-1)
    c0 = z.mean(axis=-1)
    cx = (z[..., 0] + z[..., 2] - z[..., 1] - z[..., 3]) / (4 * _HALF_WHEELBASE)
    cy = (z[..., 0] + z[..., 1] - z[..., 2] - z[..., 3]) / (4 * _HALF_TRACK)
    three = count == 3
    if three.any():
        # Three known wheels: the plane through them (the 3 x 3 system is exact).
        rows = np.concatenate([np.ones((4, 1)), _WHEELS_B], axis=1)
        zs, mask = z[three], known[three]
        a = np.broadcast_to(rows, (len(zs), 4, 3))[mask].reshape(-1, 3, 3)
        solution = np.linalg.solve(a, zs[mask].reshape(-1, 3, 1))[..., 0]
        c0[three], cx[three], cy[three] = solution.T
    return c0, cx, cy


def predict_attitude(grid: ElevationGrid, heights: np.ndarray, origin: np.ndarray, poses: np.ndarray,
                     clearance_m: float | None = None) -> Attitude:
    """The attitude (module doc) of poses (S..., 3) on the map `heights` at window `origin`."""
    poses = np.asarray(poses, dtype=float)
    shape = poses.shape[:-1]
    flat = poses.reshape(-1, 3)
    z = grid.sample(heights, origin, to_planar_frame(flat, _WHEELS_B))
    c0, cx, cy = fit_wheel_plane(z)
    norm = np.sqrt(1.0 + cx * cx + cy * cy)
    pitch = -np.arctan(cx)
    roll = np.arcsin(cy / norm)
    obstructed = np.zeros(len(flat), dtype=bool)
    if clearance_m is not None:
        under = grid.sample(heights, origin, to_planar_frame(flat, _STENCIL_B))
        plane = c0[:, None] + cx[:, None] * _STENCIL_B[:, 0] + cy[:, None] * _STENCIL_B[:, 1]
        rise = (under - plane) / norm[:, None]
        with np.errstate(invalid="ignore"):
            obstructed = (np.where(np.isfinite(rise), rise, -np.inf) > clearance_m).any(axis=1)
    side, axle = stability_margins(roll, pitch)
    return Attitude(roll.reshape(shape), pitch.reshape(shape), np.minimum(side, axle).reshape(shape),
                    side.reshape(shape), axle.reshape(shape), (~np.isfinite(z)).any(axis=1).reshape(shape),
                    obstructed.reshape(shape))
