"""The picture of the rollover-aware MPPI at the ditch: `ditch-drake figure mppi --env NAME`.

The MPPI baseline drives one episode (`RunEpisode`, the registered `mppi` config) until the
chassis origin first crosses the ditch's top edge (the hinge line, `approach_m` beyond it),
entering the down wall. At that control step the planner's update is repeated outside the
diagram, on the block's own state: the elevation map it had just fused, the warm start and
last angular rate it had before the update, the pose it planned from and its random generator
(seeded by planner seed and update count), so the samples drawn are the ones the block drew
and the chosen first command is the one it sent (checked: `MppiPicture.command_matches`).
The picture shows the map around the robot, every sampled trajectory coloured by its cost
(inadmissible ones, that break a tip margin, apart), the chosen trajectory, and in a second
panel the predicted sideways and fore-aft tip margins along it against the thresholds.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator

from ditch_drake.common.files import save_figure
from ditch_drake.diagrams.ditch_scene import SceneConfig, chassis_pose
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, MppiBaselineConfig, RolloutConfig, RunEpisode
from ditch_drake.planning.attitude import predict_attitude
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.planning.mppi import MppiPlannerConfig, MppiResult
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain

# The MppiController's discrete state groups, in the order it declares them.
_COMMAND_GROUP, _MAP_GROUP, _NOMINAL_GROUP, _STATUS_GROUP = range(4)
_STATUS_LAST_W, _STATUS_UPDATES = 8, 1


@dataclass
class MppiPicture:
    """One MPPI update repeated for the picture.

    Attributes:
        environment, task, seed: the episode.
        time_s: the update's time (s).
        edge_distance_m: the chassis origin's planar distance outside the hinge line (m).
        grid: the map's geometry; origin: its window (cells); heights: the fused map (m, NaN unknown).
        result: the planner's update (samples, costs, chosen trajectory, its attitude).
        config: the planner's config.
        goal_xy: the task's goal (m).
        command_matches: the repeated update's command equals the one the block sent.
    """

    environment: str
    task: int
    seed: int
    time_s: float
    edge_distance_m: float
    grid: ElevationGrid
    origin: np.ndarray
    heights: np.ndarray
    result: MppiResult
    config: MppiPlannerConfig
    goal_xy: np.ndarray
    command_matches: bool


def run_mppi_to_hinge(environment: str = "wide_walled", task: int = 1, seed: int = 0, approach_m: float = 0.0,
                      config: MppiBaselineConfig | None = None, end_time_s: float | None = None) -> MppiPicture:
    """Drives the MPPI until the chassis comes within `approach_m` of the hinge line (0: on it),
    or until `end_time_s` (then the last step is pictured), and repeats that step's update.

    Raises:
        ValueError: the episode ended before its first control step.
    """
    config = config or MppiBaselineConfig()
    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment, task=task),
                                                      controller=config))
    controller = diagram.GetSubsystemByName("mppi")
    period = scene.schedule.control_period_s
    before = {"nominal": controller.planner.initial_nominal(), "last_w": 0.0}
    seen: dict = {}
    next_step = [0]

    def watch(root_context) -> bool:
        # The block updates at k T + offset; read each step once, on the first simulator step
        # that ends after it (a step ending at the event's time ends before the event is handled).
        if root_context.get_time() < next_step[0] * period + scene.schedule.controller_offset_s + 1e-4:
            return False
        next_step[0] = math.floor(root_context.get_time() / period) + 1
        own = controller.GetMyContextFromRoot(root_context)
        state = own.get_discrete_state()
        X_WB = controller.GetInputPort("body_poses").Eval(own)[scene.plant.GetBodyByName(
            "chassis", scene.husky).index()]
        seen.update(time_s=root_context.get_time(), X_WB=X_WB, before=dict(before),
                    command=state.get_vector(_COMMAND_GROUP).CopyToVector(),
                    heights=state.get_vector(_MAP_GROUP).CopyToVector(),
                    status=state.get_vector(_STATUS_GROUP).CopyToVector())
        before.update(nominal=state.get_vector(_NOMINAL_GROUP).CopyToVector(),
                      last_w=float(state.get_vector(_STATUS_GROUP)[_STATUS_LAST_W]))
        return float(scene.terrain.beyond_edge_m(chassis_pose(diagram, scene, root_context).translation()[:2])) <= approach_m

    RunEpisode(Simulator(diagram), diagram, scene, seed, watch=watch, end_time_s=end_time_s)
    if not seen:
        raise ValueError(f"the {environment} episode ended before its first control step")
    X_WB = seen["X_WB"]
    pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
    grid = controller.grid
    origin = grid.window_origin(pose[:2])
    heights = seen["heights"].reshape(grid.shape)
    update = int(seen["status"][_STATUS_UPDATES]) - 1
    rng = np.random.default_rng([config.planner.seed, update])
    goal_xy = np.asarray(scene.task.goal, dtype=float)[:2]
    result = controller.planner.plan(grid, heights, origin, pose, goal_xy, seen["before"]["nominal"],
                                     seen["before"]["last_w"], rng)
    return MppiPicture(environment, task, seed, seen["time_s"], float(scene.terrain.beyond_edge_m(pose[:2])), grid, origin,
                       heights, result, controller.planner.config, goal_xy,
                       bool(np.allclose(result.command, seen["command"])))


def draw_mppi_picture(picture: MppiPicture, path: str | Path, terrain: DitchTerrain | None = None,
                      half_window_m: float = 5.0) -> Path:
    """Saves the two-panel picture (module doc) of `picture` as a PNG at `path`; returns it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon

    result, grid, config = picture.result, picture.grid, picture.config
    pose = result.poses[0]
    figure, (axis, margins_axis) = plt.subplots(1, 2, figsize=(14, 6.2), gridspec_kw={"width_ratios": [1.25, 1.0]})
    # The map: terrain colours by height, unknown cells grey.
    ny, nx = grid.shape
    x0, y0 = grid.origin_m(picture.origin)
    extent = [x0, x0 + nx * grid.resolution, y0, y0 + ny * grid.resolution]
    axis.set_facecolor("lavender")
    shown = axis.imshow(np.ma.masked_invalid(picture.heights), origin="lower", extent=extent,
                        interpolation="nearest", cmap="gray")
    figure.colorbar(shown, ax=axis, fraction=0.04, label="map height (m); lavender: unknown")
    if terrain is not None:
        for which, style in (("hinge", "--"), ("toe", ":")):
            for line in terrain.edge_lines(which):
                axis.plot(*np.vstack([line, line[:1]]).T, style, color="tab:cyan", lw=1.2)
    # The samples, coloured by cost; inadmissible ones thin and red.
    costs = result.sample_costs
    finite = np.isfinite(costs)
    bad = [p[:, :2] for p in result.sample_poses[~finite]]
    axis.add_collection(LineCollection(bad, colors="tab:red", linewidths=0.4, alpha=0.35))
    if finite.any():
        order = np.argsort(-costs[finite])  # The cheapest drawn last, on top.
        good = LineCollection([p[:, :2] for p in result.sample_poses[finite][order]], cmap="viridis_r",
                              linewidths=0.7, alpha=0.8)
        good.set_array(costs[finite][order])
        axis.add_collection(good)
        figure.colorbar(good, ax=axis, orientation="horizontal", fraction=0.05, pad=0.1,
                        label="sample cost (admissible samples)")
    axis.plot(*result.poses[:, :2].T, color="black", lw=3.0)
    axis.plot(*result.poses[:, :2].T, color="white", lw=1.2)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    half = robot.CHASSIS_SIZE_M[:2] / 2
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * half
    axis.add_patch(Polygon(corners @ np.array([[c, s], [-s, c]]) + pose[:2], closed=True, fill=False,
                           edgecolor="black", lw=2.0))
    goal_direction = picture.goal_xy - pose[:2]
    axis.annotate("", xy=pose[:2] + 2.0 * goal_direction / max(np.linalg.norm(goal_direction), 1e-9),
                  xytext=pose[:2], arrowprops={"arrowstyle": "->", "color": "gold", "lw": 2}, color="0.2")
    axis.set_xlim(pose[0] - half_window_m, pose[0] + half_window_m)
    axis.set_ylim(pose[1] - half_window_m, pose[1] + half_window_m)
    axis.set_aspect("equal")
    axis.set_xlabel("x (m)")
    axis.set_ylabel("y (m)")
    admissible = int(finite.sum())
    axis.set_title(f"elevation map, {len(costs)} samples ({admissible} admissible, red: break a margin),\n"
                   "chosen trajectory (black/white), robot (box), goal direction (gold);\ncyan: hinge (dashed), toe (dotted)", fontsize=9)
    # The predicted margins along the chosen trajectory.
    attitude = predict_attitude(grid, picture.heights, picture.origin, result.poses[1:], clearance_m=config.clearance_m)
    t = config.step_s * np.arange(1, len(result.poses))
    margins_axis.plot(t, np.degrees(attitude.side_margin), color="tab:blue", lw=2, label="sideways margin")
    margins_axis.plot(t, np.degrees(attitude.axle_margin), color="tab:orange", lw=2, label="fore-aft margin")
    margins_axis.axhline(config.margin_threshold_deg, color="tab:blue", ls="--", lw=1,
                         label=f"sideways threshold ({config.margin_threshold_deg:g} deg)")
    margins_axis.axhline(config.fore_aft_margin_threshold_deg, color="tab:orange", ls="--", lw=1,
                         label=f"fore-aft threshold ({config.fore_aft_margin_threshold_deg:g} deg)")
    margins_axis.plot(t, np.degrees(np.abs(attitude.roll)), color="0.4", ls=":", label="|roll|")
    margins_axis.plot(t, np.degrees(np.abs(attitude.pitch)), color="0.4", ls="-.", label="|pitch|")
    unknown = attitude.unknown
    if unknown.any():
        margins_axis.plot(t[unknown], np.zeros(unknown.sum()), "|", color="0.3", ms=10, label="a wheel on unknown")
    margins_axis.set_ylim(-2.0, 65.0)
    margins_axis.set_xlabel("time along the chosen trajectory (s)")
    margins_axis.set_ylabel("predicted (deg)")
    margins_axis.legend(fontsize=8, loc="center right")
    margins_axis.set_title("predicted tip margins and attitude along the chosen trajectory", fontsize=9)
    v, w = result.command
    figure.suptitle(f"{picture.environment}, task {picture.task}, seed {picture.seed}: MPPI at t = {picture.time_s:.1f} s, "
                    f"{picture.edge_distance_m:+.2f} m from the hinge line; command v = {v:.2f} m/s, w = {w:.2f} rad/s"
                    f" (label {result.label})", fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path, dpi=80)


def mppi_figure(environment: str, out_dir: str | Path, task: int = 1, seed: int = 0) -> Path:
    """Runs the MPPI to the hinge (module doc) and saves `mppi_<environment>.png` in `out_dir`."""
    picture = run_mppi_to_hinge(environment, task, seed)
    terrain = DitchTerrain(get_environment(environment).terrain)
    return draw_mppi_picture(picture, Path(out_dir) / f"mppi_{environment}.png", terrain)
