"""The dynamic window approach local planner, as ROS dwa_local_planner scores it.

One control step (`find_best_trajectory`):
1. The dynamic window: forward speeds within `acc_lim_x * sim_period` of the current
   (odometry) speed and inside [min_vel_x, max_vel_x], yaw rates within
   `acc_lim_theta * sim_period` inside [-max_vel_theta, max_vel_theta]; `vx_samples` by
   `vth_samples` evenly spaced samples (plus w = 0 when in the window). Samples slower than
   both `min_vel_trans` and `min_vel_theta` are dropped, as SimpleTrajectoryGenerator does.
2. Each (v, w) is held for `sim_time` along an exact unicycle arc, with poses every
   `sim_granularity` metres / `angular_sim_granularity` radians of the fastest sample.
3. The critics, named and scaled as in dwa_local_planner (distances in m):
   - path_distance_bias * 0.5 * (d_path(end) + d_path(end + forward point)): distance,
     through traversable cells of the local window, to the nearest cell of the global
     plan; the forward-point term ("alignment") is off within `forward_point_distance`
     of the goal;
   - goal_distance_bias * 0.5 * (d_goal(end) + d_goal(end + forward point)): the same to
     the local goal, the last plan point inside the local window;
   - occdist_scale * the largest costmap cost under the footprint's outline and centre
     along the trajectory (cells looked up from a stencil per heading bin and quarter-cell
     centre position, `footprint_costs`);
   - the oscillation critic: after the in-place rotation direction flipped, the other
     direction is refused until the robot has moved `oscillation_reset_dist`.
   A trajectory is refused when its footprint touches a LETHAL cell, when its end point
   cannot reach the plan or the local goal, or by the oscillation critic.
4. The admissible trajectory of least cost wins (ties: the first in sampling order,
   slowest first). None admissible: the caller stops and replans (move_base).

Departures from dwa_local_planner: one rolling costmap serves as move_base's global and
local costmaps, its central `local_costmap_width` square is the local one; distances
propagate over the 8-connected grid (MapGrid uses 4-connected wavefronts). By default
NO_INFORMATION cells are scored at the highest non-lethal cost and passed through, the
behaviour ROS gets with costmap_2d's default `track_unknown_space: false` (unseen space is
free) while the global planner still prefers seen ground. With `unknown_is_lethal` they
refuse a trajectory whose footprint touches them and block the distance maps, as
base_local_planner treats NO_INFORMATION: the robot then never drives where it has not
seen, and stops at the edge of a ditch too deep for its lidar to see the bottom of.
"""

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import dijkstra

from ditch_drake.planning.costmap import INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE, MAX_NON_OBSTACLE, NO_INFORMATION
from ditch_drake.planning.global_planner import grid_graph
from ditch_drake.spec import robot

# Oscillation flags (dwa_local_planner's OscillationCostFunction, rotation only: min_vel_x >= 0).
ROT_POS, ROT_NEG, ROT_POS_ONLY, ROT_NEG_ONLY = range(4)


@dataclass
class DwaPlannerConfig:
    """dwa_local_planner's parameters (its names; m, rad, s).

    Attributes:
        max_vel_x: largest forward speed.
        min_vel_x: smallest forward speed (0: no reversing).
        max_vel_theta: largest |yaw rate|.
        min_vel_trans: with |v| below this, |w| must reach `min_vel_theta`.
        min_vel_theta: see `min_vel_trans`.
        acc_lim_x: forward acceleration limit (m/s^2).
        acc_lim_theta: yaw acceleration limit (rad/s^2).
        vx_samples: forward speed samples.
        vth_samples: yaw rate samples.
        sim_time: how long each sample is forward-simulated (s).
        sim_granularity: largest distance between trajectory poses (m).
        angular_sim_granularity: largest heading change between trajectory poses (rad).
        path_distance_bias: weight of staying near the global plan.
        goal_distance_bias: weight of getting near the local goal.
        occdist_scale: weight of the costmap cost along the trajectory.
        forward_point_distance: the scoring point ahead of each trajectory's end (m).
        oscillation_reset_dist: travel that clears the oscillation flags (m).
        xy_goal_tolerance: the goal counts as reached this close (m).
        local_costmap_width: side of the local window around the robot (m).
        unknown_is_lethal: NO_INFORMATION cells refuse trajectories (base_local_planner's
            rule); False: they cost 252 (unseen space is passable).
    """

    max_vel_x: float = robot.MAX_SPEED_MPS
    min_vel_x: float = 0.0
    max_vel_theta: float = robot.MAX_ANGULAR_RATE_RADPS
    min_vel_trans: float = 0.1
    min_vel_theta: float = 0.4
    acc_lim_x: float = 2.5
    acc_lim_theta: float = 3.2
    vx_samples: int = 6
    vth_samples: int = 20
    sim_time: float = 1.7
    sim_granularity: float = 0.025
    angular_sim_granularity: float = 0.1
    path_distance_bias: float = 32.0
    goal_distance_bias: float = 24.0
    occdist_scale: float = 0.01
    forward_point_distance: float = 0.325
    oscillation_reset_dist: float = 0.05
    xy_goal_tolerance: float = 0.25
    local_costmap_width: float = 6.0
    unknown_is_lethal: bool = False


@dataclass
class DwaResult:
    """The chosen command and what it was chosen from.

    Attributes:
        v: forward speed (m/s); 0 when nothing is admissible.
        w: yaw rate (rad/s); 0 when nothing is admissible.
        admissible: whether any trajectory was admissible.
        cost: the winner's cost (inf if none).
        num_admissible: admissible samples, of `num_samples`.
        num_samples: samples in the dynamic window.
        trajectory: the winner's poses (N, 3) [x, y, yaw]; empty if none.
    """

    v: float
    w: float
    admissible: bool
    cost: float
    num_admissible: int
    num_samples: int
    trajectory: np.ndarray


def sample_velocities(velocity: np.ndarray, sim_period: float, config: DwaPlannerConfig) -> np.ndarray:
    """The dynamic window's (v, w) samples (M, 2) around the current velocity."""
    v0, w0 = (float(x) for x in velocity)
    v_lo = max(config.min_vel_x, min(v0, config.max_vel_x) - config.acc_lim_x * sim_period)
    v_hi = min(config.max_vel_x, max(v0, config.min_vel_x) + config.acc_lim_x * sim_period)
    w_lo = max(-config.max_vel_theta, min(w0, config.max_vel_theta) - config.acc_lim_theta * sim_period)
    w_hi = min(config.max_vel_theta, max(w0, -config.max_vel_theta) + config.acc_lim_theta * sim_period)
    vs = np.linspace(v_lo, v_hi, max(1, config.vx_samples)) if v_hi > v_lo else np.array([v_lo])
    ws = np.linspace(w_lo, w_hi, max(1, config.vth_samples)) if w_hi > w_lo else np.array([w_lo])
    if w_lo < 0.0 < w_hi:
        ws = np.union1d(ws, [0.0])
    samples = np.stack(np.meshgrid(vs, ws, indexing="ij"), axis=-1).reshape(-1, 2)
    eps = 1e-4
    too_slow = (np.abs(samples[:, 0]) + eps < config.min_vel_trans) & (np.abs(samples[:, 1]) + eps < config.min_vel_theta)
    return samples[~too_slow]


def trajectory_times(samples: np.ndarray, config: DwaPlannerConfig) -> np.ndarray:
    """The pose times (s) of every trajectory: `sim_time` cut finely enough for the fastest sample."""
    steps = max(1, math.ceil(max(np.max(np.abs(samples[:, 0])) * config.sim_time / config.sim_granularity,
                                 np.max(np.abs(samples[:, 1])) * config.sim_time / config.angular_sim_granularity)))
    return np.linspace(0.0, config.sim_time, steps + 1)


def arc_poses(pose: np.ndarray, samples: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses (M, T, 3) [x, y, yaw] at times t (T,) of each (v, w) of `samples` (M, 2) held from `pose`."""
    v, w, t = samples[:, 0:1], samples[:, 1:2], np.asarray(t, dtype=float)[None, :]
    x0, y0, yaw0 = (float(p) for p in pose[:3])
    yaw = yaw0 + w * t
    turning = np.abs(w) > 1e-9
    safe_w = np.where(turning, w, 1.0)
    x = np.where(turning, x0 + v / safe_w * (np.sin(yaw) - math.sin(yaw0)), x0 + v * t * math.cos(yaw0))
    y = np.where(turning, y0 - v / safe_w * (np.cos(yaw) - math.cos(yaw0)), y0 + v * t * math.sin(yaw0))
    return np.stack([x, y, yaw], axis=-1)


def simulate_trajectories(pose: np.ndarray, samples: np.ndarray, config: DwaPlannerConfig) -> np.ndarray:
    """Poses (M, N + 1, 3) [x, y, yaw] of each (v, w) held from `pose` for `sim_time`."""
    return arc_poses(pose, samples, trajectory_times(samples, config))


def prune_path(path_xy: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The plan from its point nearest the robot on (dwa_local_planner's prune_plan)."""
    if len(path_xy) == 0:
        return path_xy
    return path_xy[int(np.argmin(np.sum((path_xy - xy[:2]) ** 2, axis=1))):]


def _densify(path_xy: np.ndarray, spacing: float) -> np.ndarray:
    """Points along the polyline at most `spacing` apart."""
    if len(path_xy) < 2:
        return path_xy
    segments = np.diff(path_xy, axis=0)
    counts = np.maximum(1, np.ceil(np.linalg.norm(segments, axis=1) / spacing)).astype(int)
    owner = np.repeat(np.arange(len(segments)), counts)
    first = np.cumsum(counts) - counts
    fraction = (np.arange(counts.sum()) - first[owner] + 1) / counts[owner]
    return np.concatenate([path_xy[:1], path_xy[owner] + segments[owner] * fraction[:, None]])


def update_oscillation_flags(flags: np.ndarray, stationary_xy: np.ndarray, xy: np.ndarray, v: float, w: float,
                             config: DwaPlannerConfig) -> tuple[np.ndarray, np.ndarray]:
    """dwa_local_planner's updateOscillationFlags for the chosen (v, w) (rotation flags only).

    Returns:
        (flags (4,) as 0/1 floats indexed ROT_POS.., the position where they were last set).
    """
    flags = np.asarray(flags, dtype=float).copy()
    stationary_xy = np.asarray(stationary_xy, dtype=float).copy()
    flag_set = False
    if abs(v) <= config.min_vel_trans:
        if w < 0.0:
            if flags[ROT_POS]:
                flags[ROT_NEG_ONLY], flag_set = 1.0, True
            flags[ROT_POS], flags[ROT_NEG] = 0.0, 1.0
        elif w > 0.0:
            if flags[ROT_NEG]:
                flags[ROT_POS_ONLY], flag_set = 1.0, True
            flags[ROT_NEG], flags[ROT_POS] = 0.0, 1.0
    if flag_set:
        stationary_xy = np.asarray(xy[:2], dtype=float).copy()
    if (flags[ROT_POS_ONLY] or flags[ROT_NEG_ONLY]) and np.all(np.isfinite(stationary_xy)) and \
            np.linalg.norm(xy[:2] - stationary_xy) > config.oscillation_reset_dist:
        flags[:] = 0.0
    return flags, stationary_xy


# Footprint stencils: the footprint's outline cells are looked up from a table built once
# per (outline, resolution, grid width), indexed by heading and by where the pose's centre
# lies within its cell, instead of rotating and flooring every outline point of every pose.
STENCIL_HEADINGS = 128  # 2.8 deg bins: about 1.5 cm at the Husky's corners.
STENCIL_SUBCELLS = 4  # The centre's position within its cell, to a quarter cell.


@functools.lru_cache(maxsize=8)
def _footprint_stencil(outline_key: bytes, resolution: float, row_stride: int) -> np.ndarray:
    """Flat cell offsets (H S S, K) of the outline points and the centre from the centre's cell
    in a grid of `row_stride` columns; row (h S + sy) S + sx for heading bin h (yaw =
    2 pi h / H) and a centre at ((sx + 0.5) / S, (sy + 0.5) / S) of its cell. Read-only."""
    body = np.vstack([np.frombuffer(outline_key, dtype=float).reshape(-1, 2), [[0.0, 0.0]]]) / resolution
    yaw = 2.0 * np.pi * np.arange(STENCIL_HEADINGS) / STENCIL_HEADINGS
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    rotated_x, rotated_y = c * body[:, 0] - s * body[:, 1], s * body[:, 0] + c * body[:, 1]  # (H, K) in cells
    sub = (np.arange(STENCIL_SUBCELLS) + 0.5) / STENCIL_SUBCELLS
    dx = np.floor(sub[None, None, :, None] + rotated_x[:, None, None, :])
    dy = np.floor(sub[None, :, None, None] + rotated_y[:, None, None, :])
    stencil = (dy * row_stride + dx).astype(np.int32).reshape(-1, len(body))
    stencil.setflags(write=False)
    return stencil


def _footprint_reach_cells(footprint_xy: np.ndarray, resolution: float) -> int:
    """Cells from a pose's cell to the farthest cell its outline can touch, with a cell of margin."""
    return math.ceil(float(np.max(np.linalg.norm(footprint_xy, axis=1), initial=0.0)) / resolution) + 2


def footprint_costs(occupancy: np.ndarray, grid_origin: np.ndarray, resolution: float, poses: np.ndarray,
                    footprint_xy: np.ndarray) -> np.ndarray:
    """The largest cell value (..., ) under the footprint's outline points and centre at poses
    (..., 3) [x, y, yaw] in W; LETHAL where any of them leaves the grid.

    Args:
        occupancy: (ny, nx) cell values, integers 0..255; rows at y = grid_origin[1] + (iy + 0.5) resolution.
        grid_origin: world xy of the grid's lower-left corner.
        resolution: its cell side (m).
        poses: poses in W.
        footprint_xy: outline points (K, 2) in the body frame.
    """
    pad = _footprint_reach_cells(footprint_xy, resolution)
    ny, nx = occupancy.shape
    # Bytes: the gathers below move 35 values per pose.
    padded = np.full((ny + 2 * pad, nx + 2 * pad), LETHAL_OBSTACLE, dtype=np.uint8)
    padded[pad:pad + ny, pad:pad + nx] = occupancy
    stride = nx + 2 * pad
    outline_key = np.ascontiguousarray(footprint_xy, dtype=float).tobytes()  # Hashable, and cheap to hash.
    stencil = _footprint_stencil(outline_key, float(resolution), stride)
    flat_poses = poses.reshape(-1, 3)
    gx = (flat_poses[:, 0] - grid_origin[0]) / resolution
    gy = (flat_poses[:, 1] - grid_origin[1]) / resolution
    cx, cy = np.floor(gx), np.floor(gy)
    centre_inside = (cx >= 0) & (cx < nx) & (cy >= 0) & (cy < ny)
    sx = np.minimum((gx - cx) * STENCIL_SUBCELLS, STENCIL_SUBCELLS - 1).astype(np.int32)
    sy = np.minimum((gy - cy) * STENCIL_SUBCELLS, STENCIL_SUBCELLS - 1).astype(np.int32)
    heading = np.round(flat_poses[:, 2] * (STENCIL_HEADINGS / (2.0 * np.pi))).astype(np.int32) % STENCIL_HEADINGS
    centre = ((np.where(centre_inside, cy, 0) + pad) * stride + np.where(centre_inside, cx, 0) + pad).astype(np.int32)
    # np.take: whole stencil rows, then one flat gather of the cells (poses, K).
    cells = np.take(stencil, (heading * STENCIL_SUBCELLS + sy) * STENCIL_SUBCELLS + sx, axis=0) + centre[:, None]
    worst = np.take(padded, cells).max(axis=1)
    return np.where(centre_inside, worst, LETHAL_OBSTACLE).astype(float).reshape(poses.shape[:-1])


def _local_window(costs: np.ndarray, origin_m: np.ndarray, resolution: float, pose: np.ndarray,
                  config: DwaPlannerConfig) -> tuple[np.ndarray, np.ndarray]:
    """The local costmap, a square of the master around the robot (clipped to it), and its corner in W."""
    ny, nx = costs.shape
    half = max(2, round(config.local_costmap_width / 2 / resolution))
    cx, cy = (int(c) for c in np.floor((pose[:2] - origin_m) / resolution))
    ix0, ix1, iy0, iy1 = max(cx - half, 0), min(cx + half, nx), max(cy - half, 0), min(cy + half, ny)
    return costs[iy0:iy1, ix0:ix1], np.asarray(origin_m, dtype=float) + np.array([ix0, iy0]) * resolution


def find_best_trajectory(costs: np.ndarray, origin_m: np.ndarray, resolution: float, pose: np.ndarray,
                         velocity: np.ndarray, path_xy: np.ndarray, goal_xy: np.ndarray, footprint_xy: np.ndarray,
                         sim_period: float, config: DwaPlannerConfig | None = None,
                         oscillation_flags: np.ndarray | None = None) -> DwaResult:
    """Samples the dynamic window and returns the best admissible (v, w).

    Args:
        costs: the (ny, nx) master costmap (costmap_2d values).
        origin_m: world xy of its lower-left corner.
        resolution: its cell side (m).
        pose: the robot's [x, y, yaw] in W.
        velocity: its current [v, w] (odometry).
        path_xy: the global plan (K, 2) in W.
        goal_xy: the final goal in W.
        footprint_xy: points (M, 2) of the footprint's outline in the body frame.
        sim_period: the control period (s), which sizes the dynamic window.
        config: the planner's parameters.
        oscillation_flags: (4,) ROT_POS.. flags; None: all clear.
    """
    config = config or DwaPlannerConfig()
    pose = np.asarray(pose, dtype=float)
    none = DwaResult(0.0, 0.0, False, math.inf, 0, 0, np.zeros((0, 3)))
    local, local_origin = _local_window(costs, origin_m, resolution, pose, config)
    lny, lnx = local.shape

    def cell_of(xy):
        ix = np.floor((xy[..., 0] - local_origin[0]) / resolution)
        iy = np.floor((xy[..., 1] - local_origin[1]) / resolution)
        inside = (ix >= 0) & (ix < lnx) & (iy >= 0) & (iy < lny)
        return np.where(inside, iy * lnx + ix, -1).astype(int)

    # The plan inside the local window (prune behind the robot, stop where it leaves).
    path = _densify(prune_path(np.asarray(path_xy, dtype=float).reshape(-1, 2), pose), 0.5 * resolution)
    path_cells = cell_of(path)
    outside = np.nonzero(path_cells < 0)[0]
    path_cells = path_cells[:outside[0]] if len(outside) else path_cells
    passable = local < INSCRIBED_INFLATED_OBSTACLE
    if not config.unknown_is_lethal:
        passable |= local == NO_INFORMATION
    path_cells = path_cells[passable.reshape(-1)[path_cells]] if len(path_cells) else path_cells
    if len(path_cells) == 0:
        return none
    graph = grid_graph(np.where(passable, 1.0, np.inf), resolution)
    path_distance = dijkstra(graph, directed=True, indices=np.unique(path_cells), min_only=True)
    goal_distance = dijkstra(graph, directed=True, indices=int(path_cells[-1]))

    samples = sample_velocities(velocity, sim_period, config)
    if oscillation_flags is not None:
        flags = np.asarray(oscillation_flags)
        refused = (flags[ROT_POS_ONLY] > 0) & (samples[:, 1] < 0) | (flags[ROT_NEG_ONLY] > 0) & (samples[:, 1] > 0)
        samples = samples[~refused]
    if len(samples) == 0:
        return none
    times = trajectory_times(samples, config)
    # Obstacle critic: the footprint outline and centre at poses about a cell apart (and the last).
    stride = max(1, int(resolution / config.sim_granularity))
    checked = arc_poses(pose, samples, times[np.unique(np.r_[np.arange(0, len(times), stride), len(times) - 1])])
    unknown_value = LETHAL_OBSTACLE if config.unknown_is_lethal else MAX_NON_OBSTACLE
    occupancy = footprint_costs(np.where(local == NO_INFORMATION, float(unknown_value), local), local_origin,
                                resolution, checked, footprint_xy).max(axis=1)
    # Path and goal critics at the end point and the forward point.
    end = checked[:, -1, :]
    forward = end[:, :2] + config.forward_point_distance * np.stack([np.cos(end[:, 2]), np.sin(end[:, 2])], axis=1)

    def lookup(distance, xy):
        cell = cell_of(xy)
        return np.where(cell >= 0, distance[np.maximum(cell, 0)], np.inf)

    far_penalty = lnx * lny * resolution
    path_end, goal_end = lookup(path_distance, end[:, :2]), lookup(goal_distance, end[:, :2])
    path_front = np.minimum(lookup(path_distance, forward), far_penalty)
    goal_front = np.minimum(lookup(goal_distance, forward), far_penalty)
    alignment = 1.0 if np.linalg.norm(np.asarray(goal_xy) - pose[:2]) > config.forward_point_distance else 0.0
    cost = (0.5 * config.path_distance_bias * (path_end + alignment * path_front)
            + 0.5 * config.goal_distance_bias * (goal_end + goal_front)
            + config.occdist_scale * occupancy)
    admissible = (occupancy < LETHAL_OBSTACLE) & np.isfinite(path_end) & np.isfinite(goal_end)
    if not admissible.any():
        return DwaResult(0.0, 0.0, False, math.inf, 0, len(samples), np.zeros((0, 3)))
    best = int(np.argmin(np.where(admissible, cost, np.inf)))
    return DwaResult(float(samples[best, 0]), float(samples[best, 1]), True, float(cost[best]),
                     int(admissible.sum()), len(samples), arc_poses(pose, samples[best:best + 1], times)[0])


def footprint_outline(footprint: np.ndarray, spacing: float) -> np.ndarray:
    """Points (M, 2) along a closed polygon's edges, at most `spacing` apart."""
    closed = np.vstack([footprint, footprint[:1]])
    return _densify(closed, spacing)[:-1]
