"""The picture of a search for a way in and out: `ditch-drake figure search --env NAME`.

One episode per controller in a ditch crossable only in places (`DitchTerrain.sectioned`),
each drawn over the terrain's walls coloured by slope: the windows (no steeper than the
robot's smallest tip-over angle) green, the steeper sections red, the hinge and toe lines, the
chassis path sampled every `SAMPLE_PERIOD_S` and where the episode ended. A controller with a
`WindowSearch` block (a subsystem named `window_search`) also shows the route targets the
search gave, coloured by its phase.
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator

from ditch_drake.common.files import save_figure
from ditch_drake.diagrams.ditch_scene import SceneConfig, chassis_pose
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain
from ditch_drake.world.windows import smallest_tip_angle_deg, windows_by_side

SAMPLE_PERIOD_S = 0.25
SEARCH_SUBSYSTEM = "window_search"


@dataclass
class SearchEpisode:
    """One watched episode.

    Attributes:
        label: the controller's words in the legend.
        environment, task, seed: the episode.
        outcome: how it ended.
        track: (n, 2) chassis xy (m) every `SAMPLE_PERIOD_S`.
        targets: (n, 2) the search block's route target (m), empty without one.
        phases: (n,) its phase at those samples, empty without one.
    """

    label: str
    environment: str
    task: int
    seed: int
    outcome: EpisodeOutcome
    track: np.ndarray
    targets: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    phases: np.ndarray = field(default_factory=lambda: np.zeros(0))


def run_search_episode(label: str, controller, environment: str, task: int, seed: int) -> SearchEpisode:
    """Runs `controller` (a registered controller's config) once and samples its path."""
    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment, task=task),
                                                      controller=controller))
    search = diagram.GetSubsystemByName(SEARCH_SUBSYSTEM) if diagram.HasSubsystemNamed(SEARCH_SUBSYSTEM) else None
    track, targets, phases = [], [], []

    def watch(context) -> bool:
        track.append(chassis_pose(diagram, scene, context).translation()[:2].copy())
        if search is not None:
            search_context = search.GetMyContextFromRoot(context)
            targets.append(np.array(search.GetOutputPort("target_xy").Eval(search_context), dtype=float)[:2])
            phases.append(float(np.asarray(search.GetOutputPort("phase").Eval(search_context)).ravel()[0]))
        return False

    outcome = RunEpisode(Simulator(diagram), diagram, scene, seed, watch=watch, watch_period_s=SAMPLE_PERIOD_S)
    return SearchEpisode(label, environment, task, seed, outcome, np.array(track),
                         np.array(targets).reshape(-1, 2), np.array(phases))


def _slope_image(terrain: DitchTerrain, lower: np.ndarray, upper: np.ndarray, cell_m: float) -> np.ndarray:
    """(ny, nx, 4) RGBA: wall cells green where no steeper than the tip angle, red where
    steeper, transparent off the walls."""
    xs = np.arange(lower[0], upper[0], cell_m) + cell_m / 2
    ys = np.arange(lower[1], upper[1], cell_m) + cell_m / 2
    xy = np.stack(np.meshgrid(xs, ys), axis=-1)
    distance, _ = terrain.nearest_on_course(xy)
    on_wall = (distance > terrain.toe_distance_m) & (distance < terrain.hinge_distance_at(xy))
    steep = terrain.section_slope_deg(xy) > smallest_tip_angle_deg()
    rgba = np.zeros((*distance.shape, 4))
    rgba[on_wall & ~steep] = (0.2, 0.65, 0.25, 0.8)
    rgba[on_wall & steep] = (0.85, 0.2, 0.15, 0.7)
    return rgba


def save_search_figure(episodes: list[SearchEpisode], path: str | Path) -> Path:
    """One panel per episode: walls by slope, windows, the path, the search's targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(len(episodes), 1, figsize=(11, 4.2 * len(episodes)), squeeze=False)
    for axis, episode in zip(axes[:, 0], episodes, strict=True):
        environment = get_environment(episode.environment)
        terrain = DitchTerrain(environment.terrain)
        task = environment.tasks[episode.task]
        lower, upper = terrain.bounds_xy()
        starts, ends, _ = terrain.wall_segments()
        if len(starts):
            # A fenced field: the picture ends at its fences.
            lower, upper = np.vstack([starts, ends]).min(axis=0) - 1.0, np.vstack([starts, ends]).max(axis=0) + 1.0
        axis.imshow(_slope_image(terrain, lower, upper, 0.1), origin="lower",
                    extent=(lower[0], upper[0], lower[1], upper[1]), interpolation="nearest")
        for line in terrain.edge_lines("hinge"):
            axis.plot(*line.T, "--", color="tab:gray", lw=0.8)
        for start, end in zip(starts, ends, strict=True):
            axis.plot(*np.vstack([start, end]).T, color="black", lw=2.0)
        for side, windows in windows_by_side(terrain).items():
            for window in windows:
                axis.annotate(f"{side} wall window", np.mean([window.from_xy, window.to_xy], axis=0), fontsize=7,
                              ha="center")
        if len(episode.targets):
            axis.scatter(*episode.targets.T, c=episode.phases, cmap="viridis", s=8, marker="s",
                         label="search target (colour: phase)")
        axis.plot(*episode.track.T, color="tab:blue", lw=1.6, label="path")
        axis.plot(*task.start[:2], "o", color="tab:green", label="start")
        axis.plot(*task.goal, "*", markersize=14, color="gold", markeredgecolor="black", label="goal")
        if len(episode.track):
            axis.plot(*episode.track[-1], "x", color="black", markersize=10, mew=2)
        axis.set_aspect("equal")
        axis.set_xlim(lower[0], upper[0])
        axis.set_ylim(lower[1], upper[1])
        axis.set_title(f"{episode.label}: {episode.environment} task {episode.task} seed {episode.seed}, "
                       f"{episode.outcome.status} at {episode.outcome.time_s:.0f} s", fontsize=10)
        axis.set_ylabel("y (m)")
        axis.legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("x (m)")
    figure.tight_layout()
    return save_figure(figure, path, dpi=80)


def search_controllers(seed: int) -> list[tuple[str, object]]:
    """The controllers the figure compares: the privileged expert (it knows the windows) and
    the MPPI searching from its own map."""
    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.systems.window_search import WindowSearchConfig

    mppi = controller_config("mppi")
    mppi.search = WindowSearchConfig()
    return [("expert (privileged: knows the windows)", controller_config("expert", seed=seed)),
            ("mppi with the window search (its own map)", mppi)]


def search_figure(environment: str, out_dir: str | Path, task: int = 0, seed: int = 0) -> Path:
    """Runs each of `search_controllers` once and saves `search_<environment>.png`."""
    episodes = [run_search_episode(label, config, environment, task, seed)
                for label, config in search_controllers(seed)]
    return save_search_figure(episodes, Path(out_dir) / f"search_{environment}.png")
