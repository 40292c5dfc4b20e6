"""A rollout recorded as a standalone HTML page: Drake Meshcat's animation, no server needed.

`record_replay` builds the scene with meshcat visualization, the chosen controller, and a
lidar of its own for the picture; runs one seeded episode while Meshcat records the
visualizer's frames; and writes `Meshcat.StaticHtml()` to a file that any browser opens
offline: the robot, the ditch, the lidar's points and the driven path, under a title and a
legend (inline HTML and CSS, nothing fetched) that say what was run and how it ended:
environment, task, seed, controller (and checkpoint), outcome, simulated time, path length,
and the colours of the path and the lidar returns.

A `shared` rollout's path is drawn from the chassis's position at every control step, in two
colours: where the policy drove and where the fallback did (a `DriverRecorder` reads the gate's
`who_drives` at each tick); `ReplayResult.drivers` holds the driver of each step.

Meshcat animations carry transforms and properties, not geometry, so the lidar is shown as
one point-cloud object per snapshot (every `snapshot_period_s`, in the world frame), each
made visible only during its own interval of the animation.
"""

import contextlib
import html
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.geometry import Meshcat, Rgba
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder

from ditch_drake.common.files import atomic_output, remove_stale_temporaries
from ditch_drake.diagrams.controllers import entry_for_config
from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene
from ditch_drake.diagrams.lidar_rig import AddLidar, LidarHandles
from ditch_drake.diagrams.rollout import (
    AddController,
    ConstantCommandConfig,
    DwaBaselineConfig,
    ExpertConfig,
    LearnedPolicyConfig,
    RolloutConfig,
    RunEpisode,
)
from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
from ditch_drake.perception.lidar_model import LidarConfig
from ditch_drake.systems.driver_recorder import DriverRecorder
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.systems.shared_control import FALLBACK, POLICY

_PREFIX = "/replay"
_LIDAR_RGBA = Rgba(1.0, 0.35, 0.0, 1.0)
_PATH_RGBA = Rgba(0.1, 0.3, 1.0, 1.0)
# A shared rollout's path: the policy's steps in the usual path colour, the fallback's in red.
_DRIVER_RGBA = {POLICY: _PATH_RGBA, FALLBACK: Rgba(0.9, 0.1, 0.1, 1.0)}
_DRIVER_NAMES = {POLICY: "policy", FALLBACK: "fallback"}


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
    drivers: list[int] | None = None  # A shared rollout's driver of each control step (0 policy, 1 fallback).


def _recording_meshcat() -> Meshcat:
    """A Meshcat that only records: its "listening for connections" line would invite the
    user to open a page that shows nothing until the recording is written, so it is not logged."""
    drake_log = logging.getLogger("drake")
    level = drake_log.level
    drake_log.setLevel(logging.WARNING)
    try:
        return Meshcat()
    finally:
        drake_log.setLevel(level)


def record_replay(config: ReplayConfig, meshcat: Meshcat | None = None, progress: str | None = None) -> ReplayResult:
    """Runs one seeded episode and writes its recording as standalone HTML (atomically).

    Args:
        config: what to record.
        meshcat: the Meshcat to record into (its scene is cleared first); None makes one.
        progress: a description for a progress bar of simulated time on stderr (None: none).

    Raises:
        ConfigError: an unknown environment or controller (from the builders).
        ReplayOutputError: the output file cannot be written (checked before simulating).
    """
    if not (config.snapshot_period_s > 0 and config.max_points_per_snapshot > 0):
        raise ValueError(f"snapshot_period_s={config.snapshot_period_s} and max_points_per_snapshot="
                         f"{config.max_points_per_snapshot} must be positive")
    out = Path(config.out)
    meshcat = meshcat or _recording_meshcat()
    meshcat.Delete()
    meshcat.DeleteRecording()
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, config.rollout.scene, meshcat)
    AddController(builder, scene, config.rollout.controller)
    lidar = AddLidar(builder, scene, config.lidar, name="replay_lidar")
    drivers = _add_driver_recorder(builder, scene)
    diagram = builder.Build()
    # After the builders (which validate the environment and controller) and before minutes of
    # simulation: an unwritable path fails fast, and a bad config leaves no file behind.
    remove_stale_temporaries(out.parent)
    with _output(out) as file:
        outcome, snapshots, driven = _record_episode(config, meshcat, diagram, scene, lidar, progress, drivers)
        file.write(with_legend(meshcat.StaticHtml(), replay_title(config, outcome),
                               replay_fields(config, scene, outcome), shared=drivers is not None).encode("utf-8"))
    return ReplayResult(outcome=outcome, html_path=out, html_bytes=out.stat().st_size, snapshots=snapshots,
                        drivers=driven)


def _add_driver_recorder(builder: DiagramBuilder, scene: DitchScene) -> DriverRecorder | None:
    """A "replay_drivers" recorder on the shared controller's gate, if the diagram has one;
    ticking at offset 0, a time every rollout already stops at, it changes nothing else."""
    if not builder.HasSubsystemNamed("shared_control"):
        return None
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    drivers = builder.AddNamedSystem("replay_drivers", DriverRecorder(
        chassis.index(), period_s=scene.schedule.control_period_s, offset_s=0.0))
    builder.Connect(builder.GetSubsystemByName("shared_control").GetOutputPort("who_drives"),
                    drivers.GetInputPort("who_drives"))
    builder.Connect(scene.plant.get_body_poses_output_port(), drivers.GetInputPort("body_poses"))
    return drivers


def controller_description(config) -> str:
    """The controller in words, with the learned policy's checkpoint and its file's digest."""
    if isinstance(config, LearnedPolicyConfig):
        from ditch_drake.learning.checkpoint import checkpoint_digest

        try:
            digest = f", sha256 {checkpoint_digest(config.checkpoint)}"
        except OSError:
            digest = ""
        return f"learned policy, checkpoint {config.checkpoint}{digest}"
    if isinstance(config, ExpertConfig):
        return f"scripted expert (style seed {config.style_seed})"
    if isinstance(config, DwaBaselineConfig):
        return "DWA baseline (move_base)"
    if isinstance(config, ConstantCommandConfig):
        return f"constant command {config.command} [m/s, rad/s]"
    if isinstance(config, EdgeAngleDriverConfig):
        return f"edge-angle driver (wall angle {config.wall_angle_deg:g} deg)"
    if isinstance(config, SharedControlControllerConfig):
        gate = config.gate
        return (f"shared control: {controller_description(config.policy)}; the {gate.fallback} takes over where "
                f"its {gate.signal} > {gate.upper_threshold:g}, hands back after {gate.calm_steps} steps "
                f"< {gate.lower_threshold:g}")
    return f"{entry_for_config(config).name} ({type(config).__name__})"  # A controller registered by a user.


def replay_title(config: ReplayConfig, outcome: EpisodeOutcome) -> str:
    """The page's title: the controller, the environment and task, the seed, the outcome."""
    short = {LearnedPolicyConfig: "Learned policy", ExpertConfig: "Scripted expert", DwaBaselineConfig: "DWA baseline",
             ConstantCommandConfig: "Constant command", EdgeAngleDriverConfig: "Edge-angle driver"}.get(
        type(config.rollout.controller)) or entry_for_config(config.rollout.controller).name
    scene = config.rollout.scene
    return f"{short} in {scene.environment}, task {scene.task}, seed {config.seed}: {outcome.status}"


def replay_fields(config: ReplayConfig, scene: DitchScene, outcome: EpisodeOutcome) -> list[tuple[str, str]]:
    """What the page's legend says, as (name, value) rows."""
    task = scene.task.name or "unnamed"
    return [("environment", config.rollout.scene.environment),
            ("task", f"{config.rollout.scene.task} ({task})"),
            ("seed", str(config.seed)),
            ("controller", controller_description(config.rollout.controller)),
            ("outcome", outcome.status),
            ("simulated time", f"{outcome.time_s:.1f} s (limit {scene.episode.time_limit_s:g} s)"),
            ("path length", f"{outcome.path_length_m:.1f} m"),
            ("peak tilt", f"{outcome.peak_tilt_deg:.0f} deg")]


def _css(rgba: Rgba) -> str:
    return f"rgb({round(255 * rgba.r())}, {round(255 * rgba.g())}, {round(255 * rgba.b())})"


def _legend_rows(fields: list[tuple[str, str]]) -> str:
    """The fields as table rows: short ones two to a row, a long one across the row."""
    cells, rows = [], []
    for name, value in fields:
        cell = f"<th>{html.escape(name)}</th><td>{html.escape(value)}</td>"
        if len(value) > 28:
            rows.append(cell.replace("<td>", '<td colspan="3">'))
        else:
            cells.append(cell)
        if len(cells) == 2:
            rows.append("".join(cells))
            cells = []
    rows += ["".join(cells)] if cells else []
    return "".join(f"<tr>{row}</tr>" for row in rows)


def with_legend(page: str, title: str, fields: list[tuple[str, str]], shared: bool = False) -> str:
    """Meshcat's static page with `title` as its title, and a legend over the scene's top left
    corner (above where the camera puts the robot's start): the `fields` and the colour keys of
    the path (with `shared`, one per driver) and the lidar returns. Inline HTML and CSS only, so
    the page still opens offline; the legend lets mouse events through to the scene."""
    paths = [(_PATH_RGBA, "driven path")] if not shared else [
        (_DRIVER_RGBA[POLICY], "path the policy drove"), (_DRIVER_RGBA[FALLBACK], "path the fallback drove")]
    keys = "".join(f'<span class="key" style="background:{_css(rgba)};height:4px"></span>{text} '
                   for rgba, text in paths)
    keys += (f'<span class="key" style="background:{_css(_LIDAR_RGBA)};border-radius:50%"></span>'
             "lidar returns (each snapshot shown until the next)")
    legend = f"""
  <div id="replay-legend">
    <h1>{html.escape(title)}</h1>
    <table>{_legend_rows(fields)}</table>
    <div>{keys}</div>
    <p>Open Controls (top right), then Animations, to play or scrub the episode; drag to turn the view.</p>
  </div>
  <style>
    #replay-legend {{
      position: fixed; top: 6px; left: 6px; z-index: 10; max-width: 520px; padding: 5px 10px;
      background: rgba(255, 255, 255, 0.85); border-radius: 6px; pointer-events: none;
      font: 11px/1.3 sans-serif; color: #222;
    }}
    #replay-legend h1 {{ font-size: 14px; margin: 0 0 3px 0; }}
    #replay-legend table {{ border-spacing: 0; }}
    #replay-legend th {{
      text-align: left; padding: 0 6px 0 0; font-weight: 600; vertical-align: top; white-space: nowrap;
    }}
    #replay-legend td {{ padding: 0 14px 0 0; }}
    #replay-legend .key {{
      display: inline-block; width: 12px; height: 12px; margin: 3px 5px 0 0; vertical-align: middle;
    }}
    #replay-legend span.key + span.key {{ margin-left: 12px; }}
    #replay-legend p {{ margin: 2px 0 0 0; color: #555; }}
  </style>
"""
    page = page.replace("<title>Drake MeshCat</title>", f"<title>{html.escape(title)}</title>", 1)
    end = page.rfind("</body>")
    return page[:end] + legend + page[end:] if end >= 0 else page + legend


@contextlib.contextmanager
def _output(out: Path):
    """`atomic_output(out)`, opened before the episode runs so that an unwritable path fails at once.

    Raises:
        ReplayOutputError: naming the path and the reason.
    """
    try:
        if out.is_dir():
            raise IsADirectoryError(21, "is a directory")
        opened = atomic_output(out)
        file = opened.__enter__()
    except OSError as error:
        where = f"{error.filename}: " if error.filename else ""
        raise ReplayOutputError(f"cannot write the recording to {out} ({where}{error.strerror or error})") from error
    with contextlib.ExitStack() as stack:
        stack.push(opened)
        yield file


def _record_episode(config: ReplayConfig, meshcat: Meshcat, diagram: Diagram, scene: DitchScene,
                    lidar: LidarHandles, progress: str | None = None, drivers: DriverRecorder | None = None
                    ) -> tuple[EpisodeOutcome, int, list[int] | None]:
    """Runs the seeded episode while meshcat records; returns its outcome, the snapshot count
    and, with `drivers`, the driver of each control step.

    Every `snapshot_period_s` of simulated time (`RunEpisode`'s watch) adds a path point and
    a lidar snapshot, shown from the previous snapshot's time to this one's. With `drivers`
    the path is drawn from its per-step positions instead, by driver (`_draw_driven_path`).
    """
    _frame_the_task(meshcat, scene)
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    path_W, shown_from = [], 0.0

    def snapshot(root_context) -> None:
        nonlocal shown_from
        now = root_context.get_time()
        X_WB = scene.plant.EvalBodyPoseInWorld(scene.plant.GetMyContextFromRoot(root_context), chassis)
        cloud_L = lidar.converter.GetOutputPort("point_cloud").Eval(lidar.converter.GetMyContextFromRoot(root_context))
        _add_snapshot(meshcat, len(path_W), X_WB.multiply(lidar.X_BL), cloud_L, shown_from, now,
                      config.max_points_per_snapshot)
        path_W.append(X_WB.translation())
        shown_from = now

    def start_recording(root_context) -> None:
        meshcat.StartRecording(frames_per_second=config.frames_per_second, set_visualizations_while_recording=False)

    simulator = Simulator(diagram)
    outcome = RunEpisode(simulator, diagram, scene, config.seed, progress, after_start=start_recording,
                         watch=snapshot, watch_period_s=config.snapshot_period_s)
    meshcat.StopRecording()
    driven = None
    if drivers is None:
        meshcat.SetLine(f"{_PREFIX}/path", np.asfortranarray(np.array(path_W).T), line_width=3.0, rgba=_PATH_RGBA)
    else:
        log = drivers.log(drivers.GetMyContextFromRoot(simulator.get_context()))
        driven = log.drivers()[1:].tolist()  # Entry 0 is the start, before the gate's first decision.
        _draw_driven_path(meshcat, log.positions(), driven)
    meshcat.PublishRecording()
    return outcome, len(path_W), driven


def driven_segments(drivers: list[int]) -> list[tuple[int, int, int]]:
    """The runs of one driver among the control steps: (driver, first point, last point) over
    the per-step positions, where step k goes from point k to point k + 1, so consecutive runs
    share their end point and the path has no gaps."""
    segments = []
    for step, driver in enumerate(drivers):
        if segments and segments[-1][0] == driver:
            segments[-1] = (driver, segments[-1][1], step + 1)
        else:
            segments.append((driver, step, step + 1))
    return segments


def _draw_driven_path(meshcat: Meshcat, p_W: np.ndarray, drivers: list[int]) -> None:
    """The path through the per-step positions `p_W` (T + 1, 3) as one line per run of a driver,
    `/replay/path/<NNN>_<policy|fallback>`, coloured by who drove it."""
    for index, (driver, first, last) in enumerate(driven_segments(drivers)):
        meshcat.SetLine(f"{_PREFIX}/path/{index:03d}_{_DRIVER_NAMES[driver]}",
                        np.asfortranarray(p_W[first:last + 1].T), line_width=3.0, rgba=_DRIVER_RGBA[driver])


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
