"""The DWA baseline in the four ditch environments: one episode each, a picture of the
planner at the ditch, and the part of `docs/concepts/baseline.md` that reports them.

Run: `python -m ditch_drake.docs_tools.baseline_page --out docs/concepts/baseline.md --figures docs/img`. It runs one
full episode per environment (task 0, seed 0, `RunEpisode`) with the DWA baseline on the
rendered lidar, draws `dwa_<env>.png` from the same run, measures the controller's update
time, draws the slope cost of `dwa` and `dwa_paper` (`costmap_cost_curves.png`, quick alone:
`ditch-drake figure cost-curves`), and writes its part of the page (between two HTML comments; the rest of the page is
left as it is); every number in that part comes from this run. `ditch-drake figure dwa
--env NAME` draws one picture alone (the run stops at the picture's moment).

The picture's moment is the robot's closest approach to the ditch's top edge (the hinge
line), frozen the first time it comes within `approach_m` of it: then the costmap holds the
drop, and the plan and the chosen trajectory show what the planner makes of it.
"""

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator

from ditch_drake.common.files import save_figure
from ditch_drake.diagrams.ditch_scene import SceneConfig, chassis_pose
from ditch_drake.diagrams.rollout import (
    DwaBaselineConfig,
    MakeRolloutDiagram,
    RolloutConfig,
    RunEpisode,
    paper_dwa_config,
)
from ditch_drake.planning import costmap as costmap_values
from ditch_drake.planning.dwa import simulate_trajectories
from ditch_drake.planning.global_planner import grid_graph
from ditch_drake.spec import robot, schedule
from ditch_drake.spec.planar import planar_yaw
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.world.environments import environment_names, get_environment
from ditch_drake.world.terrain import DitchTerrain


@dataclass
class DwaSnapshot:
    """What the DWA block held just after one of its updates (SI units, world frame W).

    Attributes:
        time_s: the update's time.
        pose: the chassis [x, y, yaw] the update planned from.
        command: the chosen [v m/s, w rad/s].
        origin_xy: the costmap's lower-left corner.
        costs: the master costmap (ny, nx), costmap_2d values.
        resolution: its cell side (m).
        path_xy: the global plan (K, 2).
        trajectory: the chosen local trajectory (N, 3) [x, y, yaw] (the command's arc).
        edge_distance_m: the chassis origin's distance outside the hinge line (negative: inside).
    """

    time_s: float
    pose: np.ndarray
    command: np.ndarray
    origin_xy: np.ndarray
    costs: np.ndarray
    resolution: float
    path_xy: np.ndarray
    trajectory: np.ndarray
    edge_distance_m: float


@dataclass
class DwaEpisode:
    """One DWA episode and what was seen along it.

    Attributes:
        environment: the environment's name.
        task: the task's index.
        seed: the episode's seed.
        outcome: the episode monitor's outcome.
        track: (T, 3) [t s, x m, y m] of the chassis at the control rate.
        min_edge_distance_m: the closest the chassis origin came to the hinge line (negative:
            it went over the edge).
        closest_xy: where that was.
        planner: the DWA block's counters (halts, plans, plan_failures, recoveries, goal_reached).
        snapshot: the picture's moment (see the module doc), if the run got that far.
        wall_s: wall time of the episode (s).
    """

    environment: str
    task: int
    seed: int
    outcome: EpisodeOutcome
    track: np.ndarray
    min_edge_distance_m: float
    closest_xy: np.ndarray
    planner: dict = field(default_factory=dict)
    snapshot: DwaSnapshot | None = None
    wall_s: float = 0.0


class _EpisodeWatcher:
    """`RunEpisode`'s watch after every step: records the chassis once per control step, after
    the DWA's update, and keeps the snapshot of the closest approach to the ditch edge (frozen
    within `approach_m`); with `stop_at_snapshot` it ends the episode there."""

    def __init__(self, diagram, scene, controller, approach_m: float, stop_at_snapshot: bool):
        self._diagram, self._scene, self._controller = diagram, scene, controller
        self._approach_m, self._stop = approach_m, stop_at_snapshot
        self._next_step = 0
        self.track: list[tuple[float, float, float]] = []
        self.snapshot: DwaSnapshot | None = None
        self._frozen = False

    def __call__(self, root_context) -> bool:
        """Looks at the step that just ended; True ends the episode (the snapshot is taken)."""
        # The DWA updates at k T + CONTROLLER_OFFSET_S; read each step once, after it.
        if root_context.get_time() < self._next_step * robot.CONTROL_PERIOD_S + schedule.CONTROLLER_OFFSET_S:
            return False
        self._next_step = math.floor(root_context.get_time() / robot.CONTROL_PERIOD_S) + 1
        X_WB = chassis_pose(self._diagram, self._scene, root_context)
        xy = X_WB.translation()[:2]
        self.track.append((root_context.get_time(), float(xy[0]), float(xy[1])))
        edge = float(self._scene.terrain.beyond_edge_m(xy))
        if not self._frozen and (self.snapshot is None or edge < self.snapshot.edge_distance_m):
            self.snapshot = self._take_snapshot(root_context, edge)
            self._frozen = edge <= self._approach_m
            return self._frozen and self._stop
        return False

    def _take_snapshot(self, root_context, edge: float) -> DwaSnapshot:
        controller = self._controller
        context = controller.GetMyContextFromRoot(root_context)
        X_WB = chassis_pose(self._diagram, self._scene, root_context)
        pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
        command = np.array(controller.GetOutputPort("command").Eval(context), dtype=float)
        origin, costs = controller.unpack_costmap(controller.GetOutputPort("costmap").Eval(context))
        path = controller.unpack_path(controller.GetOutputPort("path_W").Eval(context))
        # The chosen trajectory is the command's arc from the pose it was planned from.
        trajectory = simulate_trajectories(pose, command[None, :], DwaBaselineConfig().planner.local_planner)[0]
        return DwaSnapshot(root_context.get_time(), pose, command, origin, costs, controller.costmap_resolution, path,
                           trajectory, edge)


def run_dwa_episode(environment: str, task: int = 0, seed: int = 0, approach_m: float = 1.0,
                    stop_at_snapshot: bool = False) -> DwaEpisode:
    """One episode of the DWA baseline (`RunEpisode`), watched (see `DwaEpisode`).

    Args:
        environment: a packaged environment's name.
        task: the task's index.
        seed: the episode's seed (start jitter, lidar noise).
        approach_m: the snapshot is frozen the first time the chassis comes this close to the
            hinge line (m).
        stop_at_snapshot: end the run there (for the picture alone); the outcome then says
            "running".
    """
    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment, task=task),
                                                      controller=DwaBaselineConfig()))
    controller = diagram.GetSubsystemByName("dwa")
    simulator = Simulator(diagram)
    watcher = _EpisodeWatcher(diagram, scene, controller, approach_m, stop_at_snapshot)
    start = time.perf_counter()
    outcome = RunEpisode(simulator, diagram, scene, seed, watch=watcher)
    wall_s = time.perf_counter() - start
    track = np.array(watcher.track) if watcher.track else np.zeros((0, 3))
    edges = scene.terrain.beyond_edge_m(track[:, 1:]) if len(track) else np.zeros(0)
    closest = int(np.argmin(edges)) if len(edges) else 0
    return DwaEpisode(
        environment=environment, task=task, seed=seed, outcome=outcome, track=track,
        min_edge_distance_m=float(edges[closest]) if len(edges) else float("nan"),
        closest_xy=track[closest, 1:] if len(track) else np.full(2, np.nan),
        planner=controller.planner_status(controller.GetMyContextFromRoot(simulator.get_context())),
        snapshot=watcher.snapshot, wall_s=wall_s)


# ----- the picture ------------------------------------------------------------------------
def _costmap_rgb(costs: np.ndarray) -> np.ndarray:
    """(ny, nx, 3) colours: free white, slope cost yellow to red, inscribed purple, lethal
    black, unknown grey."""
    import matplotlib

    ramp = matplotlib.colormaps["YlOrRd"]
    rgb = ramp(np.clip(costs / costmap_values.MAX_NON_OBSTACLE, 0.0, 1.0))[..., :3]
    rgb[costs == costmap_values.FREE_SPACE] = 1.0
    rgb[costs == costmap_values.INSCRIBED_INFLATED_OBSTACLE] = (0.55, 0.25, 0.7)
    rgb[costs == costmap_values.LETHAL_OBSTACLE] = 0.0
    rgb[costs == costmap_values.NO_INFORMATION] = 0.82
    return rgb


def draw_snapshot(axis, snapshot: DwaSnapshot, terrain: DitchTerrain, goal_xy: np.ndarray) -> None:
    """Draws the costmap, the ditch's edges, the global plan, the chosen trajectory, the
    robot and the goal on a matplotlib axis."""
    from matplotlib.patches import Patch, Polygon

    ny, nx = snapshot.costs.shape
    x0, y0 = snapshot.origin_xy
    extent = [x0, x0 + nx * snapshot.resolution, y0, y0 + ny * snapshot.resolution]
    axis.imshow(_costmap_rgb(snapshot.costs), origin="lower", extent=extent, interpolation="nearest")
    for which, style in (("hinge", "--"), ("toe", ":")):
        for line in terrain.edge_lines(which):
            axis.plot(*np.vstack([line, line[:1]]).T, style, color="tab:cyan", lw=1.2)
    axis.plot(*snapshot.path_xy.T, color="tab:blue", lw=2.0)
    axis.plot(*snapshot.trajectory[:, :2].T, color="tab:green", lw=3.0)
    c, s = math.cos(snapshot.pose[2]), math.sin(snapshot.pose[2])
    outline = costmap_values.SlopeCostmap().footprint @ np.array([[c, s], [-s, c]]) + snapshot.pose[:2]
    axis.add_patch(Polygon(outline, closed=True, fill=False, edgecolor="tab:red", lw=2.0))
    axis.annotate("", xy=snapshot.pose[:2] + 1.2 * np.array([c, s]), xytext=snapshot.pose[:2],
                  arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 2})
    axis.plot(*goal_xy, marker="*", markersize=18, color="gold", markeredgecolor="black")
    # The window, and the goal when it lies outside it.
    lower = np.minimum([extent[0], extent[2]], goal_xy - 1.0)
    upper = np.maximum([extent[1], extent[3]], goal_xy + 1.0)
    axis.set_xlim(lower[0], upper[0])
    axis.set_ylim(lower[1], upper[1])
    axis.set_aspect("equal")
    axis.set_xlabel("x (m)")
    axis.set_ylabel("y (m)")
    handles = [Patch(color=(1.0, 1.0, 1.0), ec="0.5", label="free"), Patch(color="orange", label="slope cost"),
               Patch(color=(0.55, 0.25, 0.7), label="inscribed"), Patch(color="black", label="lethal"),
               Patch(color="0.82", label="unknown"),
               axis.plot([], [], "--", color="tab:cyan", label="ditch top edge (hinge)")[0],
               axis.plot([], [], ":", color="tab:cyan", label="ditch floor edge (toe)")[0],
               axis.plot([], [], color="tab:blue", lw=2, label="global plan (Dijkstra)")[0],
               axis.plot([], [], color="tab:green", lw=3, label="chosen DWA trajectory")[0],
               Patch(fill=False, edgecolor="tab:red", label="robot"),
               axis.plot([], [], "*", color="gold", markeredgecolor="black", markersize=12, label="goal")[0]]
    axis.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)


def save_snapshot_figure(episode: DwaEpisode, out_dir: str | Path) -> Path:
    """Saves `dwa_<environment>.png` of the episode's snapshot in `out_dir`; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if episode.snapshot is None:
        raise ValueError(f"the {episode.environment} episode ended before its first control step")
    environment = get_environment(episode.environment)
    terrain = DitchTerrain(environment.terrain)
    snapshot = episode.snapshot
    figure, axis = plt.subplots(figsize=(9.5, 7.5))
    draw_snapshot(axis, snapshot, terrain, np.asarray(environment.tasks[episode.task].goal, dtype=float))
    v, w = snapshot.command
    axis.set_title(f"{episode.environment}, task {episode.task}, seed {episode.seed}: DWA at t = {snapshot.time_s:.1f} s, "
                   f"{snapshot.edge_distance_m:.1f} m from the edge\ncommand v = {v:.2f} m/s, w = {w:.2f} rad/s",
                   fontsize=10)
    figure.tight_layout()
    return save_figure(figure, Path(out_dir) / f"dwa_{episode.environment}.png", dpi=80)


def dwa_figure(environment: str, out_dir: str | Path, task: int = 0, seed: int = 0) -> Path:
    """Runs the DWA to its moment at the ditch (see the module doc) and saves `dwa_<environment>.png`."""
    return save_snapshot_figure(run_dwa_episode(environment, task, seed, stop_at_snapshot=True), out_dir)


def save_tracks_figure(episodes: list[DwaEpisode], path: str | Path) -> Path:
    """One panel per episode: the ditch's edges, start, goal and the chassis track."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(episodes), figsize=(4.2 * len(episodes), 4.6), squeeze=False)
    for axis, episode in zip(axes[0], episodes, strict=True):
        environment = get_environment(episode.environment)
        terrain = DitchTerrain(environment.terrain)
        for which, style in (("hinge", "--"), ("toe", ":")):
            for line in terrain.edge_lines(which):
                axis.plot(*np.vstack([line, line[:1]]).T, style, color="tab:cyan", lw=1.0)
        task = environment.tasks[episode.task]
        axis.plot(*episode.track[:, 1:].T, color="tab:blue", lw=1.5)
        axis.plot(*task.start[:2], "o", color="tab:green")
        axis.plot(*task.goal, "*", markersize=14, color="gold", markeredgecolor="black")
        axis.plot(*episode.track[-1, 1:], "x", color="tab:red", markersize=10, mew=2)
        axis.set_aspect("equal")
        axis.set_title(f"{episode.environment}: {episode.outcome.status} at {episode.outcome.time_s:.0f} s", fontsize=10)
        axis.set_xlabel("x (m)")
    axes[0][0].set_ylabel("y (m)")
    figure.tight_layout()
    return save_figure(figure, path, dpi=70)


# ----- geometry: how long is the way around? -------------------------------------------
def detour_length_m(terrain: DitchTerrain, start_xy, goal_xy, clearance_m: float, cell_m: float = 0.25,
                    margin_m: float = 15.0) -> float:
    """Shortest planar path (m) from start to goal that stays `clearance_m` outside the hinge line.

    Dijkstra over an 8-connected grid (`grid_graph`) of the ditch's surroundings finds the
    way; its cell path, up to 8 % longer than the straight lines it zigzags along, is then
    pulled taut (each point joined to the farthest later one in clear sight) and measured.
    inf if the ditch with its clearance closes the way.
    """
    from scipy.sparse.csgraph import dijkstra

    keep_out = terrain.hinge_distance_m + clearance_m
    points = np.vstack([terrain.course_xy, start_xy, goal_xy])
    lower = points.min(axis=0) - keep_out - margin_m
    upper = points.max(axis=0) + keep_out + margin_m
    xs = np.arange(lower[0], upper[0], cell_m) + cell_m / 2
    ys = np.arange(lower[1], upper[1], cell_m) + cell_m / 2
    distance, _ = terrain.nearest_on_course(np.stack(np.meshgrid(xs, ys), axis=-1))
    weights = np.where(distance > keep_out, 1.0, np.inf)

    def cell(xy):
        return int(np.floor((xy[1] - lower[1]) / cell_m)) * len(xs) + int(np.floor((xy[0] - lower[0]) / cell_m))

    lengths, predecessors = dijkstra(grid_graph(weights, cell_m), directed=True, indices=cell(start_xy),
                                     return_predecessors=True)
    if not np.isfinite(lengths[cell(goal_xy)]):
        return float("inf")
    cells = [cell(goal_xy)]
    while cells[-1] != cell(start_xy):
        cells.append(predecessors[cells[-1]])
    path = np.vstack([start_xy, np.stack([xs[np.array(cells[::-1]) % len(xs)],
                                          ys[np.array(cells[::-1]) // len(xs)]], axis=1)[1:-1], goal_xy])
    return _taut_length(path, lambda xy: terrain.nearest_on_course(xy)[0] > keep_out, cell_m / 2)


def _taut_length(path: np.ndarray, free, spacing: float) -> float:
    """Length (m) of a polyline pulled taut: from each point, straight to the farthest later
    point whose segment stays `free` (checked every `spacing`; found by bisection, which the
    shape of a shortest grid path around convex ends allows)."""

    def clear(a, b):
        count = max(2, math.ceil(np.linalg.norm(b - a) / spacing) + 1)
        return bool(np.all(free(a + np.linspace(0.0, 1.0, count)[:, None] * (b - a))))

    total, here = 0.0, 0
    while here < len(path) - 1:
        low, high = here + 1, len(path) - 1  # low is always in sight (neighbouring cells).
        while low < high:
            middle = (low + high + 1) // 2
            low, high = (middle, high) if clear(path[here], path[middle]) else (low, middle - 1)
        total += float(np.linalg.norm(path[low] - path[here]))
        here = low
    return total


def ditch_length_to_block_m(terrain: DitchTerrain, start_xy, goal_xy, clearance_m: float, detour_limit_m: float,
                            longest_m: float = 400.0) -> float:
    """The shortest straight or sine ditch (m, course length) whose way around is longer than
    `detour_limit_m`, other parameters kept; nan for a crater (a point course)."""
    from dataclasses import replace

    if terrain.params.course == "point":
        return float("nan")

    def detour(length):  # The same cross-section and course, longer (a sine gets more periods).
        return detour_length_m(DitchTerrain(replace(terrain.params, length_m=length)), start_xy, goal_xy, clearance_m,
                               cell_m=0.5)

    low, high = terrain.params.length_m, longest_m
    if detour(high) <= detour_limit_m:
        return float("inf")
    while high - low > 1.0:
        middle = 0.5 * (low + high)
        low, high = (middle, high) if detour(middle) <= detour_limit_m else (low, middle)
    return high


# ----- the page -----------------------------------------------------------------------------
def _route(episode: DwaEpisode, terrain: DitchTerrain) -> str:
    """How the track passed the ditch, in words."""
    if episode.min_edge_distance_m < 0.0:
        floor = episode.min_edge_distance_m < terrain.toe_distance_m - terrain.hinge_distance_m
        return "went over the edge" + (" down to the floor" if floor else " onto the wall")
    xs = episode.track[:, 1]
    if terrain.params.course == "point":
        side = "west" if np.mean(xs) < 0.0 else "east"
        return f"stayed on the rim, {side} of the crater"
    half = float(np.max(np.abs(terrain.course_xy[:, 0])))
    if xs.min() < -half:
        return "drove around the west end"
    if xs.max() > half:
        return "drove around the east end"
    return "stayed on the start side"


def geometry_rows(environments: list[str], clearance_m: float, speed_mps: float, time_limit_s: float) -> list[dict]:
    """Per environment and task: the straight distance, the way around the ditch, and the
    ditch length that would make the way around longer than `speed_mps * time_limit_s`."""
    rows = []
    for name in environments:
        environment = get_environment(name)
        terrain = DitchTerrain(environment.terrain)
        for index, task in enumerate(environment.tasks):
            start, goal = np.asarray(task.start[:2], float), np.asarray(task.goal, float)
            around = detour_length_m(terrain, start, goal, clearance_m)
            rows.append({
                "environment": name, "task": index, "straight_m": float(np.linalg.norm(goal - start)),
                "length_m": float("nan") if terrain.params.course == "point" else terrain.params.length_m,
                "span_m": float(np.ptp(terrain.course_xy[:, 0])) + 2 * terrain.hinge_distance_m,
                "around_m": around, "around_s": around / speed_mps,
                "blocking_length_m": ditch_length_to_block_m(terrain, start, goal, clearance_m, speed_mps * time_limit_s),
            })
    return rows


def _number(value: float, digits: int = 1) -> str:
    return "-" if not np.isfinite(value) else f"{value:.{digits}f}"


def _speed_section(speed: dict, notes: dict) -> list[str]:
    rows = [("costmap update + DWA local plan, median wall", "dwa_update_ms"),
            ("the same, median CPU time of its one thread", "dwa_update_cpu_ms"),
            ("the same, 90th percentile wall", "dwa_update_p90_ms"),
            ("Dijkstra global plan over the 200 x 200 window, median wall", "dwa_global_plan_ms"),
            ("whole update, mean over all steps (global plan at 1 Hz included)", "dwa_step_ms")]
    return [
        "### Speed", "",
        ("One control-step update of the block, replayed on a recorded drive of the real lidar "
         "(`ditch_drake/perf/bench_dwa.py`; the same keys are in `ditch-drake bench --json`). "
         "The issue's budget: costmap update + local plan <= 10 ms on one core, the global plan apart."), "",
        "| figure | key | ms |", "| --- | --- | --- |",
        *[f"| {label} | `{key}` | {speed[key]:.2f} |" for label, key in rows], "",
        (f"Measured on {notes['machine']}, load average {notes['load']} during the run: other processes "
         "shared the cores, so wall times include waiting for one; CPU time is the time on one core."), "",
    ]


def _pictures_section(episodes: list[DwaEpisode], figures: dict[str, str], notes: dict) -> list[str]:
    lines = [
        "### The planner at the ditch", "",
        (f"Each picture is the moment of the episode below when the robot first came within {notes['approach_m']:g} m "
         "of the ditch's top edge (or its closest approach): the costmap (white free, yellow to red slope cost, "
         "purple inscribed, black lethal, grey unknown), the ditch's edges from the terrain model, Dijkstra's "
         "global plan, the trajectory the DWA chose, the robot and the goal. `ditch-drake figure dwa --env all "
         "--out docs/img` draws them alone (the run stops at the picture's moment)."), "",
    ]
    for episode in episodes:
        snapshot = episode.snapshot
        if episode.environment in figures and snapshot is not None:
            lines += [f"![DWA in {episode.environment}]({figures[episode.environment]})", "",
                      (f"*{episode.environment}: t = {snapshot.time_s:.1f} s, {snapshot.edge_distance_m:.2f} m from the "
                       f"edge, command v = {snapshot.command[0]:.2f} m/s, w = {snapshot.command[1]:.2f} rad/s.*"), ""]
    return lines


def _episodes_section(episodes: list[DwaEpisode], tracks_figure: str, notes: dict) -> list[str]:
    header = ("| environment | outcome | time (s) | path (m) | peak tilt (deg) | closest to edge (m) | at (x, y) | route "
              "| final (x, y) | halts | plans | plan failures | recoveries | wall (s) |")
    lines = [
        "### One episode per environment (task 0, seed 0)", "",
        (f"`RunEpisode` from `ditch_drake/diagrams/rollout.py`, time limit {notes['time_limit_s']:g} s. Closest to edge: "
         "the chassis origin's least distance outside the ditch's top edge (negative: over it). Halts: control "
         "steps stopped without an admissible trajectory."), "",
        header, "| --- " * 14 + "|",
    ]
    routes = []
    for episode in episodes:
        outcome, terrain = episode.outcome, DitchTerrain(get_environment(episode.environment).terrain)
        routes.append(_route(episode, terrain))
        planner = episode.planner
        lines.append(
            f"| {episode.environment} | {outcome.status} | {outcome.time_s:.1f} | {outcome.path_length_m:.1f} | "
            f"{outcome.peak_tilt_deg:.1f} | {episode.min_edge_distance_m:.2f} | "
            f"({episode.closest_xy[0]:.1f}, {episode.closest_xy[1]:.1f}) | {routes[-1]} | "
            f"({outcome.final_xy[0]:.1f}, {outcome.final_xy[1]:.1f}) | {planner.get('halts', 0)} | "
            f"{planner.get('plans', 0)} | {planner.get('plan_failures', 0)} | {planner.get('recoveries', 0)} | "
            f"{episode.wall_s:.0f} |")
    reached = sum(episode.outcome.success for episode in episodes)
    over = sum(episode.min_edge_distance_m < 0.0 for episode in episodes)
    lines += ["", (f"In short: {reached} of {len(episodes)} episodes reached the goal; {over} went over a ditch's "
                   f"edge; the routes: {'; '.join(f'{e.environment} {r}' for e, r in zip(episodes, routes, strict=True))}."),
              "", f"![Tracks of the episodes]({tracks_figure})", "",
              ("*The chassis tracks (blue) from the start (green) toward the goal (star), ending at the cross; "
               "dashed: the ditch's top edge, dotted: its floor.*"), ""]
    return lines


def _geometry_section(geometry: list[dict], notes: dict) -> list[str]:
    lethal = DwaBaselineConfig().planner.costmap.lethal_slope_deg
    limit_m = notes["speed_mps"] * notes["time_limit_s"]
    lines = [
        "### Can it go around? The ditches' length against the tasks", "",
        (f"The costmap makes slopes from {lethal:g} deg lethal and the walls are {notes['wall_deg']} deg: once the "
         "lidar has seen a wall (or the drop behind an edge), neither planner plans across it, and the only way to "
         "the goal left is around the ditch. The ditches are finite (straight and sine: a course of the given "
         "length with rounded ends, on an open field). The table gives the shortest way around that keeps the "
         f"chassis centre {notes['clearance_m']:.2f} m (half its width) outside the top edge (a grid path pulled "
         "taut; within a cell of exact), and its time at the top speed of "
         f"{notes['speed_mps']:g} m/s against the {notes['time_limit_s']:g} s limit. Blocking length: the course "
         f"length (same cross-section and course) from which the way around is longer than {limit_m:g} m, so that "
         "going around cannot finish in time."), "",
        ("| environment | task | start to goal (m) | ditch course length (m) | ditch extent along x (m) "
         "| way around (m) | at top speed (s) | blocking course length (m) |"),
        "| --- " * 8 + "|",
    ]
    for row in geometry:
        lines.append(f"| {row['environment']} | {row['task']} | {row['straight_m']:.1f} | {_number(row['length_m'])} | "
                     f"{row['span_m']:.1f} | {_number(row['around_m'])} | {_number(row['around_s'], 0)} | "
                     f"{_number(row['blocking_length_m'], 0)} |")
    lines += ["", ("A crater cannot be made impassable by its size alone: only walls (or the field's boundary) "
                   "can keep a robot from going round it."), ""]
    return lines


def _cost_row(name: str, config: DwaBaselineConfig, wall_deg: float) -> str:
    """One controller's row of the cost-curve table, from its costmap config."""
    costmap = config.planner.costmap
    lethal = costmap.lethal_slope_deg
    wall_cost = float(costmap_values.slope_cost(math.cos(math.radians(wall_deg)), costmap.free_slope_deg, lethal))
    wall = "LETHAL (254)" if wall_cost == costmap_values.LETHAL_OBSTACLE else f"{wall_cost:.0f}"
    never = lethal == math.inf
    top = 90.0 if never else lethal
    rises = (f"252 (cos {costmap.free_slope_deg:g} - n_z) / (cos {costmap.free_slope_deg:g} - cos {top:g}): "
             + (f"252 at {top:g} deg" if never else f"up to 252 below {top:g} deg"))
    by_slope = "lethal by slope" if not never else ""
    by_step = (f"lethal by step height (a cell's points span > {costmap.max_step_height:g} m, its highest and "
               "lowest left out)" if costmap.max_step_height > 0.0 else "")
    vertical = " and ".join(part for part in (by_slope, by_step) if part) or "slope cost only (252)"
    drops = (f"LETHAL where rays pass unseen > {costmap.negative_obstacle_depth:g} m below the wheels' plane"
             if costmap.negative_obstacle_depth > 0.0
             else "not marked: they stay unknown, which " + (
                 "both planners pass at the highest non-lethal cost"
                 if config.planner.global_planner.allow_unknown and not config.planner.local_planner.unknown_is_lethal
                 else "a planner refuses"))
    return (f"| `{name}` | 0 to {costmap.free_slope_deg:g} deg | {rises} | "
            f"{'none' if never else f'{lethal:g} deg'} | {wall} | {vertical} | "
            f"{drops} |")


def _cost_curves_section(figure: str | None, wall_deg: float) -> list[str]:
    """The slope cost of each DWA baseline (`dwa`, `dwa_paper`), from their configs."""
    lines = [
        "### The slope cost of each baseline", "",
        ("Both baselines are the same block (`DwaBaselineConfig`); they differ in the costmap "
         "(`ditch_drake/planning/costmap.py`, whose module doc has the formula). A point's cost comes from "
         "its PCA normal's world z, n_z = cos(slope); a cell takes the largest of its points' costs. `dwa` is "
         "today's baseline; `dwa_paper` is the paper's move_base (section 4.2: the cost \"increases with "
         "increasing or decreasing terrain slope, while flat terrain garners zero cost\"), made by "
         "`paper_dwa_config` in `ditch_drake/diagrams/rollout.py`: no slope is lethal, real obstacles still "
         "are. The episodes below are `dwa`'s."), "",
        (f"| controller | free | cost rises (linear in n_z) | lethal slope | {wall_deg:g} deg ditch wall "
         "| vertical obstacles | hidden drops |"),
        "| --- " * 7 + "|",
        _cost_row("dwa", DwaBaselineConfig(), wall_deg),
        _cost_row("dwa_paper", paper_dwa_config(), wall_deg), "",
    ]
    if figure:
        lines += [f"![Slope cost of dwa and dwa_paper]({figure})", "",
                  (f"*Cost against slope for each baseline; dots: the ditches' {wall_deg:g} deg walls. "
                   "`ditch-drake figure cost-curves --out docs/img` draws it alone.*"), ""]
    return lines


BEGIN_MARK = "<!-- begin: generated by python -m ditch_drake.docs_tools.baseline_page; rerun it to update this part -->"
END_MARK = "<!-- end: generated by python -m ditch_drake.docs_tools.baseline_page -->"


def baseline_page(episodes: list[DwaEpisode], speed: dict, geometry: list[dict], figures: dict[str, str],
                  tracks_figure: str, command: str, notes: dict, cost_curves_figure: str | None = None) -> str:
    """The Markdown section of docs/concepts/baseline.md made from the measured pieces (no hand-typed
    numbers), between `BEGIN_MARK` and `END_MARK`.

    Args:
        episodes: one per environment, with snapshots.
        speed: `ditch_drake.perf.bench_dwa.measure_dwa_ms`'s figures.
        geometry: `geometry_rows`.
        figures: environment name -> the picture's path relative to the page.
        tracks_figure: the tracks picture's path relative to the page.
        command: the command that made the section.
        notes: machine, load, approach_m, time_limit_s, clearance_m, speed_mps, wall_deg.
        cost_curves_figure: the cost-curve picture's path relative to the page (None: no picture).
    """
    config = DwaBaselineConfig().planner
    intro = [
        BEGIN_MARK, "",
        "## One seeded episode per environment, the planner at the ditch, and its speed", "",
        f"*Generated by `{command}`; every number in this part comes from that run.*", "",
        ("The block: a rolling 20 m slope costmap filled from the rendered lidar's organized cloud (cost from "
         f"the world z of PCA normals, lethal from {config.costmap.lethal_slope_deg:g} deg; raytraced clearing and "
         f"hidden-drop marking), Dijkstra's global plan at {config.planner_frequency:g} Hz and the DWA local "
         "planner, updated at 10 Hz; `MakeRolloutDiagram(RolloutConfig(..., controller=DwaBaselineConfig()))` "
         "wires it to the lidar and the drive."), "",
    ]
    wall_deg = float(str(notes["wall_deg"]).split("/")[0])
    sections = (intro, _cost_curves_section(cost_curves_figure, wall_deg), _speed_section(speed, notes),
                _pictures_section(episodes, figures, notes),
                _episodes_section(episodes, tracks_figure, notes), _geometry_section(geometry, notes), [END_MARK])
    return "\n".join(line for section in sections for line in section)


def replace_generated_section(page: str, section: str) -> str:
    """`page` with its generated part (between the marks) replaced by `section`, or with
    `section` appended if it has none: what people wrote around it stays."""
    if BEGIN_MARK in page and END_MARK in page:
        head, rest = page.split(BEGIN_MARK, 1)
        return head + section + rest.split(END_MARK, 1)[1]
    return page.rstrip("\n") + "\n\n" + section + "\n"


def main(argv: list[str] | None = None) -> int:
    """Runs the episodes, draws the pictures, times the block and writes the page."""
    import os
    import platform

    from ditch_drake.docs_tools.figures import cost_curve_figure
    from ditch_drake.perf.bench_dwa import measure_dwa_ms
    from ditch_drake.perf.recorded_drive import record_lidar_drive

    parser = argparse.ArgumentParser(prog="python -m ditch_drake.docs_tools.baseline_page", description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="docs/concepts/baseline.md", help="the page to write")
    parser.add_argument("--figures", default="docs/img", help="folder of the PNG figures")
    parser.add_argument("--env", action="append", metavar="NAME", help=f"repeatable; default: all of {environment_names()}")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    names = args.env or environment_names()
    out, figures_dir = Path(args.out), Path(args.figures)
    episodes, figures = [], {}
    for name in names:
        episode = run_dwa_episode(name, 0, args.seed)
        print(f"{name}: {episode.outcome.status} at {episode.outcome.time_s:.1f} s ({episode.wall_s:.0f} s wall)",
              flush=True)
        episodes.append(episode)
        figures[name] = os.path.relpath(save_snapshot_figure(episode, figures_dir), out.parent)
    tracks = os.path.relpath(save_tracks_figure(episodes, figures_dir / "dwa_episodes.png"), out.parent)
    cost_curves = os.path.relpath(cost_curve_figure(figures_dir), out.parent)
    load = ", ".join(f"{value:.1f}" for value in os.getloadavg())
    speed = measure_dwa_ms(record_lidar_drive("wide"))
    scene = SceneConfig()
    clearance = float(robot.CHASSIS_SIZE_M[1]) / 2
    notes = {"machine": f"{os.cpu_count()} cores ({platform.processor() or platform.machine()})", "load": load,
             "approach_m": 1.0, "time_limit_s": scene.episode.time_limit_s, "clearance_m": clearance,
             "speed_mps": robot.MAX_SPEED_MPS,
             "wall_deg": "/".join(sorted({f"{get_environment(n).terrain.slope_deg:g}" for n in names}))}
    geometry = geometry_rows(names, clearance, robot.MAX_SPEED_MPS, scene.episode.time_limit_s)
    command = " ".join(["python -m ditch_drake.docs_tools.baseline_page", *(sys.argv[1:] if argv is None else argv)])
    out.parent.mkdir(parents=True, exist_ok=True)
    page = out.read_text() if out.exists() else "# The DWA baseline\n"
    out.write_text(replace_generated_section(page, baseline_page(episodes, speed, geometry, figures, tracks, command,
                                                                 notes, cost_curves)))
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
