"""The MPPI's attitude model against the simulator, along the scripted expert's drives.

Run: `python -m ditch_drake.validation.mppi_validation [--seeds 0 1] [--out-figure PNG] [--out-data NPZ]`.

Each drive is a rollout diagram with the registered `expert` (style drawn from the seed)
driving, and an `MppiController` block added as an observer: it gets its own lidar and the
plant's body poses as in the `mppi` controller, but its command is connected to nothing. It
fuses its elevation map on the fly exactly as when it drives. At each control step, just after
the block's update, the chassis's true planar pose (x, y, yaw) is put on the block's map and
`ditch_drake.planning.attitude.predict_attitude` predicts roll and pitch, compared with
Drake's `RollPitchYaw` of the simulated chassis pose.

Two maps are read: the block's own ("controller map": the lidar fused plus, in cells still
unknown, the plane of the wheels under the robot that the block fills in from the chassis
pose, which the lidar cannot see) and a lidar-only map fused here by the same grid and rule
from the same clouds without that fill ("lidar map"), so that the fill cannot flatter the
comparison: under the robot the controller map holds the true attitude's plane wherever the
lidar had not seen the ground before.

Per environment: median and 95th percentile of |error| of roll and pitch (deg) over the steps
with a prediction (three or more wheels on known cells), the fraction of steps with some wheel
on an unknown cell, and the fraction with no prediction at all.
"""

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.math import RollPitchYaw
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ditch_drake.common.files import save_figure
from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar
from ditch_drake.diagrams.rollout import AddController, ExpertConfig, RunEpisode
from ditch_drake.planning.attitude import predict_attitude
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.planning.mppi import MppiPlannerConfig
from ditch_drake.spec import actions
from ditch_drake.spec.planar import planar_yaw
from ditch_drake.systems.mppi_controller import MppiController

WALLED_ENVIRONMENTS = ("crater_walled", "wide_walled", "narrow_walled", "sine_walled")


@dataclass
class AttitudeTrace:
    """One expert drive, one row per control step (angles in rad).

    Attributes:
        environment, task, seed, status: the drive and its outcome's status.
        time_s: (T,) step times; true_rpy: (T, 2) simulated roll, pitch.
        controller: (T, 2) predicted roll, pitch on the block's map (NaN: no prediction);
            controller_unknown: (T,) some wheel on an unknown cell of it.
        lidar: (T, 2) and lidar_unknown: (T,) the same on the lidar-only map.
    """

    environment: str
    task: int
    seed: int
    status: str = ""
    time_s: list = field(default_factory=list)
    true_rpy: list = field(default_factory=list)
    controller: list = field(default_factory=list)
    controller_unknown: list = field(default_factory=list)
    lidar: list = field(default_factory=list)
    lidar_unknown: list = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(getattr(self, name), dtype=float) for name in
                ("time_s", "true_rpy", "controller", "controller_unknown", "lidar", "lidar_unknown")}


def trace_expert_drive(environment: str, task: int, seed: int, end_time_s: float | None = None) -> AttitudeTrace:
    """Runs the expert with the observing MPPI block (module doc) and returns its trace."""
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment=environment, task=task))
    AddController(builder, scene, ExpertConfig(style_seed=seed))
    chassis = scene.plant.GetBodyByName("chassis", scene.husky).index()
    lidar = AddLidar(builder, scene, name="mppi_lidar")
    # The fewest samples the planner allows: its plan is not used, only its map.
    observer = builder.AddNamedSystem("mppi_observer", MppiController(
        scene.task.goal, chassis, lidar.X_BL, MppiPlannerConfig(samples=actions.NUM_LABELS + 2),
        period_s=scene.schedule.control_period_s, offset_s=scene.schedule.controller_offset_s))
    builder.Connect(lidar.converter.GetOutputPort("organized_points"), observer.GetInputPort("point_cloud"))
    builder.Connect(scene.plant.get_body_poses_output_port(), observer.GetInputPort("body_poses"))
    diagram = builder.Build()
    grid: ElevationGrid = observer.grid
    period = scene.schedule.control_period_s
    trace = AttitudeTrace(environment, task, seed)
    lidar_map = {"heights": grid.empty(), "origin": None}
    next_step = [0]

    def watch(root_context) -> None:
        # Read each step once, on the first simulator step that ends after the block's update.
        if root_context.get_time() < next_step[0] * period + scene.schedule.controller_offset_s + 1e-4:
            return
        next_step[0] = int(np.floor(root_context.get_time() / period)) + 1
        own = observer.GetMyContextFromRoot(root_context)
        X_WB = observer.GetInputPort("body_poses").Eval(own)[chassis]
        pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
        origin_m, heights = observer.unpack_map(observer.GetOutputPort("elevation_map").Eval(own))
        origin = np.round(origin_m / grid.resolution).astype(int)
        # The lidar-only map: the same grid and fusion rule, no footprint fill.
        window = grid.window_origin(pose[:2])
        if lidar_map["origin"] is not None:
            lidar_map["heights"] = grid.roll(lidar_map["heights"], lidar_map["origin"], window)
        lidar_map["origin"] = window
        points_W = observer.cloud_in_world(observer.GetInputPort("point_cloud").Eval(own), X_WB)
        if len(points_W):
            lidar_map["heights"] = grid.fuse(lidar_map["heights"], window, points_W)
        rpy = RollPitchYaw(X_WB.rotation())
        trace.time_s.append(root_context.get_time())
        trace.true_rpy.append([rpy.roll_angle(), rpy.pitch_angle()])
        for name, (map_heights, map_origin) in (("controller", (heights, origin)),
                                                ("lidar", (lidar_map["heights"], window))):
            attitude = predict_attitude(grid, map_heights, map_origin, pose)
            getattr(trace, name).append([float(attitude.roll), float(attitude.pitch)])
            getattr(trace, f"{name}_unknown").append(bool(attitude.unknown))

    outcome = RunEpisode(Simulator(diagram), diagram, scene, seed, watch=watch, end_time_s=end_time_s)
    trace.status = outcome.status
    return trace


def summarize(traces: list[AttitudeTrace], which: str = "controller", tilted_deg: float = 0.0) -> dict:
    """Per-environment errors (deg) and unknown fractions of `which` map (module doc).

    Args:
        tilted_deg: only the steps where the simulated |roll| or |pitch| exceeds this (deg),
            the robot on or at a wall (0: every step; most steps are on the flat, where every
            rule is right, so the medians over all steps say little about the walls).
    """
    rows = {}
    for environment in dict.fromkeys(trace.environment for trace in traces):
        mine = [trace.arrays() for trace in traces if trace.environment == environment]
        true = np.concatenate([a["true_rpy"] for a in mine])
        predicted = np.concatenate([a[which] for a in mine])
        unknown = np.concatenate([a[f"{which}_unknown"] for a in mine]).astype(bool)
        chosen = (np.degrees(np.abs(true)) > tilted_deg).any(axis=1) if tilted_deg > 0 else np.ones(len(true), bool)
        true, predicted, unknown = true[chosen], predicted[chosen], unknown[chosen]
        known = np.isfinite(predicted).all(axis=1)
        error = np.degrees(np.abs(predicted[known] - true[known]))
        rows[environment] = {
            "drives": len(mine), "steps": len(true),
            "roll_median_deg": float(np.median(error[:, 0])), "roll_p95_deg": float(np.percentile(error[:, 0], 95)),
            "pitch_median_deg": float(np.median(error[:, 1])),
            "pitch_p95_deg": float(np.percentile(error[:, 1], 95)),
            "unknown_fraction": float(unknown.mean()), "no_prediction_fraction": float(1.0 - known.mean()),
            "true_abs_roll_p95_deg": float(np.percentile(np.degrees(np.abs(true[:, 0])), 95)),
            "true_abs_pitch_p95_deg": float(np.percentile(np.degrees(np.abs(true[:, 1])), 95)),
        }
    return rows


def markdown_table(rows: dict) -> str:
    header = ("| environment | drives | steps | roll err median | roll err p95 | pitch err median | pitch err p95 "
              "| some wheel unknown | no prediction | true abs roll p95 | true abs pitch p95 |")
    lines = [header, "|---|---|---|---|---|---|---|---|---|---|---|"]
    for environment, row in rows.items():
        lines.append(f"| {environment} | {row['drives']} | {row['steps']} | {row['roll_median_deg']:.2f} | "
                     f"{row['roll_p95_deg']:.2f} | {row['pitch_median_deg']:.2f} | {row['pitch_p95_deg']:.2f} | "
                     f"{100 * row['unknown_fraction']:.1f} % | {100 * row['no_prediction_fraction']:.1f} % | "
                     f"{row['true_abs_roll_p95_deg']:.1f} | {row['true_abs_pitch_p95_deg']:.1f} |")
    return "\n".join(lines)


def draw_traces(traces: list[AttitudeTrace], path: str | Path) -> Path:
    """Predicted (both maps) against simulated roll and pitch over time, one drive per row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(len(traces), 2, figsize=(13, 2.6 * len(traces)), squeeze=False, sharex="row")
    for row, trace in zip(axes, traces, strict=True):
        a = trace.arrays()
        for column, (axis, angle) in enumerate(zip(row, ("roll", "pitch"), strict=True)):
            axis.plot(a["time_s"], np.degrees(a["true_rpy"][:, column]), color="black", lw=2.0, label="simulator")
            axis.plot(a["time_s"], np.degrees(a["controller"][:, column]), color="tab:orange", lw=1.2,
                      label="predicted, controller map")
            axis.plot(a["time_s"], np.degrees(a["lidar"][:, column]), color="tab:blue", lw=1.0, ls="--",
                      label="predicted, lidar-only map")
            unknown = a["controller_unknown"].astype(bool)
            if unknown.any():
                axis.plot(a["time_s"][unknown], np.zeros(unknown.sum()), "|", color="tab:red", ms=6,
                          label="a wheel on unknown (controller map)")
            axis.set_ylabel(f"{angle} (deg)")
            axis.set_title(f"{trace.environment}, task {trace.task}, seed {trace.seed} ({trace.status}): {angle}",
                           fontsize=9)
            axis.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="best")
    for axis in axes[-1]:
        axis.set_xlabel("time (s)")
    figure.suptitle("Predicted chassis attitude on the elevation map built on the fly vs the simulator's "
                    "(scripted expert drives)", fontsize=10)
    figure.tight_layout()
    return save_figure(figure, path, dpi=70)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", nargs="+", default=list(WALLED_ENVIRONMENTS))
    parser.add_argument("--tasks", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--out-figure", default="docs/img/mppi_attitude_validation.png")
    parser.add_argument("--out-data", default="results/mppi_validation.npz")
    parser.add_argument("--plot-task", type=int, default=1, help="the drive per environment plotted (seed: the first)")
    args = parser.parse_args(argv)
    traces = []
    for environment in args.env:
        for task in args.tasks:
            for seed in args.seeds:
                trace = trace_expert_drive(environment, task, seed)
                traces.append(trace)
                print(f"{environment} task {task} seed {seed}: {trace.status}, {len(trace.time_s)} steps",
                      file=sys.stderr, flush=True)
    for which in ("controller", "lidar"):
        for tilted_deg, steps in ((0.0, "all steps"), (5.0, "steps with simulated |roll| or |pitch| > 5 deg")):
            print(f"\n{which} map, {steps} (|predicted - simulated|, deg, over those with a prediction):")
            print(markdown_table(summarize(traces, which, tilted_deg)))
    shown = [next(t for t in traces if t.environment == env and t.task == args.plot_task and t.seed == args.seeds[0])
             for env in args.env if args.plot_task in args.tasks]
    if shown:
        print(f"\nwrote {draw_traces(shown, args.out_figure)}")
    if args.out_data:
        out = Path(args.out_data)
        out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out, **{f"{t.environment}_t{t.task}_s{t.seed}_{key}": value for t in traces
                                    for key, value in t.arrays().items()})
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
