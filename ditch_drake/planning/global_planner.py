"""Dijkstra's algorithm over the costmap grid, as ROS global_planner's `use_dijkstra` mode.

The grid is an 8-connected graph solved with `scipy.sparse.csgraph.dijkstra`. A cell of
cost c weighs like global_planner's `getCost`:

    w(c) = min(neutral_cost + cost_factor * c, lethal_cost - 1) / neutral_cost

per metre (1 on free ground; unknown cells, when `allow_unknown`, weigh the highest
non-lethal value). Cells with c >= `lethal_cost` (253: inscribed and lethal) are not in
the graph, except the robot's own cell (global_planner clears it). An edge between two
neighbouring cells weighs its length (m) times the mean of their weights.

The target. The costmap is a rolling window with no static map behind it. A goal inside
the window is planned to directly: if its cell cannot be reached, to the reachable cell
nearest to it within `default_tolerance`. A goal outside the window is replaced by the
point where the straight line from the robot to the goal leaves the window; the plan
goes to the reachable cell on the window's border nearest to that point, so the robot
heads out of the window toward the goal and discovers the rest as it goes (a wall seen
across the line makes the plan go round its seen end).
"""

import functools
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from ditch_drake.planning.costmap import INSCRIBED_INFLATED_OBSTACLE, NO_INFORMATION


@dataclass
class GlobalPlannerConfig:
    """ROS global_planner's parameters (its names; lengths in m).

    Attributes:
        neutral_cost: the cost of a free cell, in the weight formula's units.
        cost_factor: multiplies the costmap cost in the weight formula.
        lethal_cost: cells with at least this cost are untraversable.
        allow_unknown: plan through NO_INFORMATION cells (at the highest weight).
        default_tolerance: a goal cell that cannot be reached may be replaced by the
            reachable cell nearest to it within this distance.
    """

    neutral_cost: float = 50.0
    cost_factor: float = 3.0
    lethal_cost: int = INSCRIBED_INFLATED_OBSTACLE
    allow_unknown: bool = True
    default_tolerance: float = 0.5


# The 8 neighbours (dy, dx) of a cell, in the order of its edges in `grid_graph`'s rows.
NEIGHBOURS = ((0, 1), (1, 0), (1, 1), (1, -1), (0, -1), (-1, 0), (-1, -1), (-1, 1))


@functools.lru_cache(maxsize=16)
def grid_edges(ny: int, nx: int) -> tuple[np.ndarray, np.ndarray]:
    """The CSR layout of the 8-connected grid: every cell's row holds 8 edges, to its
    `NEIGHBOURS` in order (a self-loop where the neighbour is off the grid; `grid_graph`
    weighs those inf). Returns (column indices (ny nx 8,), row pointer (ny nx + 1,)), read-only.

    With a fixed 8 edges a row, `grid_graph` fills in the weights with shifted slices of the
    weight grid: no sorting (scipy's COO to CSR conversion) and no gathers, which cost more
    than Dijkstra itself on the 200 x 200 window.
    """
    index = np.arange(ny * nx).reshape(ny, nx)
    rows, cols = np.arange(ny)[:, None], np.arange(nx)[None, :]
    neighbour = np.empty((ny, nx, len(NEIGHBOURS)), dtype=np.int32)
    for k, (dy, dx) in enumerate(NEIGHBOURS):
        on_grid = (rows + dy >= 0) & (rows + dy < ny) & (cols + dx >= 0) & (cols + dx < nx)
        neighbour[:, :, k] = np.where(on_grid, index + dy * nx + dx, index)
    indices = neighbour.reshape(-1)
    indptr = np.arange(0, indices.size + 1, len(NEIGHBOURS), dtype=np.int32)
    indices.setflags(write=False)  # Shared by every call through the cache.
    indptr.setflags(write=False)
    return indices, indptr


def grid_graph(weights: np.ndarray, resolution: float) -> csr_matrix:
    """The grid as a directed sparse graph with every edge both ways, for Dijkstra with
    `directed=True` (the weights are symmetric; this skips scipy's symmetrization).

    Args:
        weights: (ny, nx) cell weights per metre; inf for cells left out.
        resolution: cell side (m).

    Returns:
        An edge weighs its length (m) times the mean of its end cells' weights; edges at a
        left-out cell (and the self-loops of `grid_edges`) weigh inf, which Dijkstra never
        relaxes: the same as no edge.
    """
    ny, nx = weights.shape
    indices, indptr = grid_edges(ny, nx)
    padded = np.full((ny + 2, nx + 2), np.inf)
    padded[1:-1, 1:-1] = weights
    data = np.empty((ny, nx, len(NEIGHBOURS)))
    for k, (dy, dx) in enumerate(NEIGHBOURS):
        length = float(np.hypot(dx, dy))
        np.multiply(length * resolution * 0.5, weights + padded[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx],
                    out=data[:, :, k])
    return csr_matrix((data.reshape(-1), indices, indptr), shape=(ny * nx, ny * nx))


def cell_weights(costs: np.ndarray, config: GlobalPlannerConfig) -> np.ndarray:
    """Per-metre weight of each cell (global_planner's getCost over neutral_cost), inf if blocked."""
    ceiling = (config.lethal_cost - 1) / config.neutral_cost
    weights = np.minimum((config.neutral_cost + config.cost_factor * costs) / config.neutral_cost, ceiling)
    blocked = costs >= config.lethal_cost
    unknown = costs == NO_INFORMATION
    weights = np.where(blocked, np.inf, weights)
    if config.allow_unknown:
        weights = np.where(unknown, ceiling, weights)
    return weights


def window_aim(origin_m: np.ndarray, shape: tuple[int, int], resolution: float, start_xy: np.ndarray,
               goal_xy: np.ndarray) -> tuple[np.ndarray, bool]:
    """The point to plan to: the goal if inside the window, else where the line to it leaves.

    Returns:
        (aim xy, whether it is the goal itself).
    """
    lower = np.asarray(origin_m, dtype=float) + 0.5 * resolution
    upper = lower + (np.array([shape[1], shape[0]]) - 1) * resolution
    goal_xy = np.asarray(goal_xy, dtype=float)
    if np.all(goal_xy >= lower) and np.all(goal_xy <= upper):
        return goal_xy, True
    start_xy = np.clip(np.asarray(start_xy, dtype=float), lower, upper)
    direction = goal_xy - start_xy
    with np.errstate(divide="ignore", invalid="ignore"):
        limits = np.where(direction > 0, (upper - start_xy) / direction,
                          np.where(direction < 0, (lower - start_xy) / direction, np.inf))
    return start_xy + min(1.0, float(np.min(limits))) * direction, False


@dataclass
class Plan:
    """A global plan: cell-centre waypoints (K, 2) in W from the robot's cell to the target."""

    path_xy: np.ndarray
    target_xy: np.ndarray
    reaches_goal: bool


def plan(costs: np.ndarray, origin_m: np.ndarray, resolution: float, start_xy: np.ndarray, goal_xy: np.ndarray,
         config: GlobalPlannerConfig | None = None) -> Plan | None:
    """Plans from `start_xy` toward `goal_xy` (m, world) over a master costmap.

    Args:
        costs: the (ny, nx) master costmap (costmap_2d values).
        origin_m: world xy of the window's lower-left corner.
        resolution: cell side (m).
        start_xy: the robot's position; must lie in the window.
        goal_xy: the goal, anywhere.
        config: the planner's parameters.

    Returns:
        The plan, or None when no reachable cell moves the robot toward the target
        (the robot's cell is walled in, or the goal is blocked beyond the tolerance).
    """
    config = config or GlobalPlannerConfig()
    ny, nx = costs.shape
    origin_m = np.asarray(origin_m, dtype=float)
    start = np.floor((np.asarray(start_xy, dtype=float)[:2] - origin_m) / resolution).astype(int)
    if not (0 <= start[0] < nx and 0 <= start[1] < ny):
        return None
    start_index = start[1] * nx + start[0]
    weights = cell_weights(costs, config)
    weights.reshape(-1)[start_index] = min(weights.reshape(-1)[start_index], 1.0)
    distance, predecessors = dijkstra(grid_graph(weights, resolution), directed=True, indices=start_index,
                                      return_predecessors=True)
    aim, is_goal = window_aim(origin_m, costs.shape, resolution, start_xy[:2], goal_xy)
    reachable = np.isfinite(distance).reshape(ny, nx)
    if not is_goal:
        border = np.zeros_like(reachable)
        border[[0, -1], :] = True
        border[:, [0, -1]] = True
        reachable &= border
    iy, ix = np.nonzero(reachable)
    if len(iy) == 0:
        return None
    centres = origin_m + (np.stack([ix, iy], axis=1) + 0.5) * resolution
    gaps = np.linalg.norm(centres - aim, axis=1)
    best = int(np.argmin(gaps))
    if is_goal and gaps[best] > max(config.default_tolerance, resolution):
        return None
    target = iy[best] * nx + ix[best]
    if target == start_index and np.linalg.norm(aim - centres[best]) > resolution:
        return None
    cells = [target]
    while cells[-1] != start_index:
        cells.append(predecessors[cells[-1]])
    cells = np.array(cells[::-1])
    path = origin_m + (np.stack([cells % nx, cells // nx], axis=1) + 0.5) * resolution
    return Plan(path_xy=path, target_xy=centres[best], reaches_goal=is_goal)
