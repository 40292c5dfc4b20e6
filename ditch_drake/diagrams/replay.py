"""A rollout recorded as a standalone HTML page: Drake Meshcat's animation, no server needed.

`record_replay` builds the scene with meshcat visualization, the chosen controller, and a
lidar of its own for the picture; runs one seeded episode while Meshcat records the
visualizer's frames; and writes `Meshcat.StaticHtml()` to a file that any browser opens
offline: the robot, the ditch, the lidar's points and the driven path.

Meshcat animations carry transforms and properties, not geometry, so the lidar is shown as
one point-cloud object per snapshot (every `snapshot_period_s`, in the world frame), each
made visible only during its own interval of the animation.
"""

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.geometry import Meshcat, Rgba
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.analysis import Simulator, SimulatorStatus
from pydrake.systems.framework import Diagram, DiagramBuilder

from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene
from ditch_drake.diagrams.rollout import AddController, ExpertConfig, RolloutConfig
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.systems.lidar import AddLidar, LidarConfig, LidarHandles

_PREFIX = "/replay"
_LIDAR_RGBA = Rgba(1.0, 0.35, 0.0, 1.0)
_PATH_RGBA = Rgba(0.1, 0.3, 1.0, 1.0)


class ReplayOutputError(OSError):
    """The recording's HTML file cannot be written where asked."""


def _default_rollout() -> RolloutConfig:
    # The scripted expert needs no trained checkpoint, so a replay works on a fresh checkout.
    return RolloutConfig(controller=ExpertConfig())


@dataclass
class ReplayConfig:
    """What to record.

    Attributes:
        rollout: the scene and the controller (default: the scripted expert in the default scene).
        seed: the episode's seed.
        out: the HTML file.
        snapshot_period_s: simulated time between lidar snapshots (and path points).
        max_points_per_snapshot: each snapshot keeps at most this many lidar points
            (evenly strided), which bounds the file's size.
        frames_per_second: the animation's frame rate.
        lidar: the pictured lidar (the controller's own sensors are separate).
    """

    rollout: RolloutConfig = field(default_factory=_default_rollout)
    seed: int = 0
    out: str = "results/replay.html"
    snapshot_period_s: float = 0.5
    max_points_per_snapshot: int = 1500
    frames_per_second: float = 32.0
    lidar: LidarConfig = field(default_factory=LidarConfig)


@dataclass
class ReplayResult:
    """The episode's outcome and the written file."""

    outcome: EpisodeOutcome
    html_path: Path
    html_bytes: int
    snapshots: int


def record_replay(config: ReplayConfig, meshcat: Meshcat | None = None) -> ReplayResult:
    """Runs one seeded episode and writes its recording as standalone HTML (atomically).

    Args:
        config: what to record.
        meshcat: the Meshcat to record into (its scene is cleared first); None makes one.

    Raises:
        ConfigError: an unknown environment or controller (from the builders).
        ReplayOutputError: the output file cannot be written (checked before simulating).
    """
    if not (config.snapshot_period_s > 0 and config.max_points_per_snapshot > 0):
        raise ValueError(f"snapshot_period_s={config.snapshot_period_s} and max_points_per_snapshot="
                         f"{config.max_points_per_snapshot} must be positive")
    out = Path(config.out)
    meshcat = meshcat or Meshcat()
    meshcat.Delete()
    meshcat.DeleteRecording()
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, config.rollout.scene, meshcat)
    AddController(builder, scene, config.rollout.controller)
    lidar = AddLidar(builder, scene, config.lidar, name="replay_lidar")
    diagram = builder.Build()
    # After the builders (which validate the environment and controller) and before minutes of
    # simulation: an unwritable path fails fast, and a bad config leaves no file behind.
    temporary = _open_output(out)
    try:
        outcome, snapshots = _record_episode(config, meshcat, diagram, scene, lidar)
        temporary.write_text(meshcat.StaticHtml())
        os.replace(temporary, out)
    finally:
        temporary.unlink(missing_ok=True)
    return ReplayResult(outcome=outcome, html_path=out, html_bytes=out.stat().st_size, snapshots=snapshots)


def _open_output(out: Path) -> Path:
    """Creates `out`'s folder and an empty temporary file beside `out` (renamed over it at the end).

    Raises:
        ReplayOutputError: naming the path and the reason.
    """
    temporary = out.with_name(f".{out.name}.tmp")
    try:
        if out.is_dir():
            raise IsADirectoryError(21, "is a directory")
        out.parent.mkdir(parents=True, exist_ok=True)
        temporary.write_text("")
    except OSError as error:
        where = f"{error.filename}: " if error.filename else ""
        raise ReplayOutputError(f"cannot write the recording to {out} ({where}{error.strerror or error})") from error
    return temporary


def _record_episode(config: ReplayConfig, meshcat: Meshcat, diagram: Diagram, scene: DitchScene,
                    lidar: LidarHandles) -> tuple[EpisodeOutcome, int]:
    """Runs the seeded episode while meshcat records; returns its outcome and the snapshot count."""
    _frame_the_task(meshcat, scene)

    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetRandomContext(context, RandomGenerator(config.seed))
    simulator.Initialize()
    meshcat.StartRecording(frames_per_second=config.frames_per_second, set_visualizations_while_recording=False)
    plant_context = scene.plant.GetMyContextFromRoot(context)
    lidar_context = lidar.converter.GetMyContextFromRoot(context)
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    end_time = scene.episode.time_limit_s + 1.0
    path_W, snapshots, previous_t = [], 0, 0.0
    while True:
        status = simulator.AdvanceTo(min(context.get_time() + config.snapshot_period_s, end_time))
        now = context.get_time()
        X_WB = scene.plant.EvalBodyPoseInWorld(plant_context, chassis)
        path_W.append(X_WB.translation())
        cloud_L = lidar.converter.GetOutputPort("point_cloud").Eval(lidar_context)
        _add_snapshot(meshcat, snapshots, X_WB.multiply(lidar.X_BL), cloud_L, previous_t, now,
                      config.max_points_per_snapshot)
        snapshots += 1
        previous_t = now
        if status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition or now >= end_time:
            break
    meshcat.StopRecording()
    meshcat.SetLine(f"{_PREFIX}/path", np.asfortranarray(np.array(path_W).T), line_width=3.0, rgba=_PATH_RGBA)
    meshcat.PublishRecording()
    return scene.monitor.outcome(scene.monitor.GetMyContextFromRoot(context)), snapshots


def _frame_the_task(meshcat: Meshcat, scene: DitchScene) -> None:
    """Points the camera at the task from above one side; hides meshcat's grid and axes."""
    start, goal = np.asarray(scene.task.start[:2], float), np.asarray(scene.task.goal[:2], float)
    target = np.append((start + goal) / 2, -1.0)
    across = goal - start
    side = np.array([across[1], -across[0]]) / max(np.linalg.norm(across), 1e-9)
    camera = target + np.append(18.0 * side - 0.35 * across, 16.0)
    meshcat.SetCameraPose(camera_in_world=camera, target_in_world=target)
    meshcat.SetProperty("/Grid", "visible", False)
    meshcat.SetProperty("/Axes", "visible", False)


def _add_snapshot(meshcat: Meshcat, index: int, X_WL, cloud_L: PointCloud, shown_from: float, shown_until: float,
                  max_points: int) -> None:
    """One lidar snapshot in W, visible in the animation from `shown_from` to `shown_until` (s)."""
    p_LP = cloud_L.xyzs()
    p_LP = p_LP[:, np.isfinite(p_LP).all(axis=0)]
    stride = max(1, -(-p_LP.shape[1] // max_points))
    p_WP = X_WL.multiply(p_LP[:, ::stride])
    cloud_W = PointCloud(p_WP.shape[1], Fields(BaseField.kXYZs))
    cloud_W.mutable_xyzs()[:] = p_WP
    path = f"{_PREFIX}/lidar/{index:04d}"
    meshcat.SetObject(path, cloud_W, point_size=0.05, rgba=_LIDAR_RGBA)
    meshcat.SetProperty(path, "visible", False)
    meshcat.SetProperty(path, "visible", False, time_in_recording=0.0)
    meshcat.SetProperty(path, "visible", True, time_in_recording=shown_from)
    meshcat.SetProperty(path, "visible", False, time_in_recording=shown_until)
