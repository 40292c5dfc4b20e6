"""The simulated Clearpath Husky's numbers (docs/design.md, "The robot"), in one place.

Every other module imports these; `models_sdf/husky.sdf` repeats them as data and
`tests/test_robot_model.py` checks that the two agree.

Frames: the chassis body frame B has its origin at the wheel-axle height, midway
between the axles, +x forward, +y left, +z up. On flat ground B sits
`WHEEL_RADIUS_M` above the ground plane.
"""

import numpy as np

# Chassis box (the paper's 0.990 x 0.670 x 0.39 m, section 4.2), lifted to the Husky's ground clearance.
CHASSIS_SIZE_M = np.array([0.990, 0.670, 0.39])
GROUND_CLEARANCE_M = 0.13

# Wheels: four, skid-steer.
WHEEL_RADIUS_M = 0.165
WHEELBASE_M = 0.512
TRACK_M = 0.555
WHEEL_NAMES = ("front_left", "rear_left", "front_right", "rear_right")

# Mass: about 50 kg in all; the centre of mass is kept low (see docs/concepts/physics.md).
CHASSIS_MASS_KG = 40.0
WHEEL_MASS_KG = 2.5
TOTAL_MASS_KG = CHASSIS_MASS_KG + 4 * WHEEL_MASS_KG
COM_HEIGHT_ABOVE_GROUND_M = 0.15

# Friction (Coulomb, static = dynamic), chosen in docs/concepts/physics.md. These are the
# effective coefficients between robot and terrain. Drake combines two
# geometries' coefficients as 2 mu1 mu2 / (mu1 + mu2), so each geometry carries
# the value that gives the effective one against `TERRAIN_FRICTION`.
TERRAIN_FRICTION = 2.0
WHEEL_FRICTION = 2.0
CHASSIS_FRICTION = 0.3


def geometry_friction(effective: float, other: float = TERRAIN_FRICTION) -> float:
    """The coefficient a geometry needs for `effective` against one with `other`."""
    if not 0 < effective < 2 * other:
        raise ValueError(f"effective friction {effective} must be in (0, {2 * other})")
    return effective * other / (2 * other - effective)

# Drive: wheel-speed damping control with a torque limit.
WHEEL_SPEED_GAIN_NMS = 300.0
WHEEL_TORQUE_LIMIT_NM = 100.0
# Skid-steer loses yaw rate to lateral wheel scrub; the kinematic map uses an
# effective track wider than the geometric one by a factor that depends on the
# commanded |w| (rad/s), interpolated in this table measured on flat ground
# (docs/concepts/physics.md; `ditch-drake calibrate` re-measures the tracking).
SKID_STEER_TRACK_FACTORS = (
    np.array([0.15, 0.25, 0.45, 0.65, 0.85]),
    np.array([2.12, 2.00, 1.93, 1.90, 1.885]),
)

# Lidar (paper 4.2): field of view and range, mounted on the chassis front-top.
LIDAR_HORIZONTAL_FOV_RAD = np.deg2rad(120.0)
LIDAR_VERTICAL_FOV_RAD = np.deg2rad(80.0)
LIDAR_RANGE_M = 4.0
# Mount frame L in B: on a mast 0.3 m above the chassis top near its front edge, high
# enough that the chassis does not hide the ground just ahead (a lower mount could not
# see into a ditch until the robot tipped over its edge).
LIDAR_MOUNT_XYZ_M = np.array([0.40, 0.0, 0.65])

CONTROL_PERIOD_S = 0.1  # 10 Hz, our choice: the paper gives none (docs/design.md, "The control schedule")
MAX_SPEED_MPS = 1.0
MAX_ANGULAR_RATE_RADPS = 0.85


def chassis_center_in_body_frame() -> np.ndarray:
    """Returns p_BC, the chassis box centre in the body frame B (m)."""
    z = GROUND_CLEARANCE_M + CHASSIS_SIZE_M[2] / 2 - WHEEL_RADIUS_M
    return np.array([0.0, 0.0, z])


def wheel_positions_in_body_frame() -> dict[str, np.ndarray]:
    """Returns p_BW for each wheel joint (m), keyed by `WHEEL_NAMES`."""
    x, y = WHEELBASE_M / 2, TRACK_M / 2
    return {
        "front_left": np.array([x, y, 0.0]),
        "rear_left": np.array([-x, y, 0.0]),
        "front_right": np.array([x, -y, 0.0]),
        "rear_right": np.array([-x, -y, 0.0]),
    }


def tip_angle_sideways_rad() -> float:
    """The static tip-over angle about the left or right wheel line (rad): atan(half track / CoM height).

    The chassis tips sideways once the world's vertical leans further than this from the body's
    z-axis in the body's y-z plane (about 61.6 deg for today's model: docs/design.md, "The robot").
    """
    return float(np.arctan2(TRACK_M / 2, COM_HEIGHT_ABOVE_GROUND_M))


def tip_angle_fore_aft_rad() -> float:
    """The static tip-over angle about the front or rear axle (rad): atan(half wheelbase / CoM height).

    About 59.6 deg for today's model (docs/design.md, "The robot").
    """
    return float(np.arctan2(WHEELBASE_M / 2, COM_HEIGHT_ABOVE_GROUND_M))
