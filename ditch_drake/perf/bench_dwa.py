"""Times the move_base baseline (`ditch_drake.systems.dwa_controller.DwaController`) on the real lidar.

Run: `python -m ditch_drake.perf.bench_dwa [environment] [seconds]`. A closed-loop drive
of the DWA through the environment's first task (seed 0) records what the controller saw at
each control step: the rendered lidar's organized cloud and the chassis pose. A fresh
controller then replays those steps, timing each periodic update, and Dijkstra's global plan
is timed on its own on each step's master costmap. The issue's budget counts one update's
costmap work (roll, normals, marking and raytracing, inflation) plus the DWA local plan,
with the global plan apart: the update figures below are the steps on which the 1 Hz global
planner did not run.

Wall time is what a real-time loop sees; CPU time (`time.process_time`, this process's single
thread) is the time on one core, which stays meaningful on a shared machine where other
processes take turns on the cores. Each step is replayed `repeats` times and its fastest run
kept, as `timeit` does, so that a step that lost the core to another process counts at its
own cost.
"""

import sys
import time
from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import DwaBaselineConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.planning.global_planner import plan
from ditch_drake.spec import robot
from ditch_drake.systems.dwa_controller import DwaController


@dataclass
class LidarDrive:
    """What the DWA block saw at each control step of a closed-loop drive.

    Attributes:
        clouds: (steps, N, 3) organized clouds in the lidar frame L (NaN: no return), float32.
        poses: (steps, 4, 4) chassis poses X_WB.
        ray_directions_L: (N, 3) the rays' unit directions in L.
        X_BL: the lidar frame's pose in B (4, 4).
        goal_xy: the task's goal in W (m).
    """

    clouds: np.ndarray
    poses: np.ndarray
    ray_directions_L: np.ndarray
    X_BL: np.ndarray
    goal_xy: np.ndarray


def record_lidar_drive(environment: str = "wide", task: int = 0, seed: int = 0, duration_s: float = 10.0,
                       config=None, controller_name: str = "dwa") -> LidarDrive:
    """Drives a lidar-fed planner block (the DWA baseline unless `config` names another, whose
    block `controller_name` is) for `duration_s` (s), or until the episode ends, and records its
    inputs at each control step.

    The recording reads the controller's input ports once per control step, at the first
    simulator step that ends 0.1 ms or more after the controller's update
    (`controller_offset_s`): every block is discrete, so they hold the values that update
    used until the next event.
    """
    config = config if config is not None else DwaBaselineConfig()
    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment, task=task),
                                                      controller=config))
    controller = diagram.GetSubsystemByName(controller_name)
    chassis_index = scene.plant.GetBodyByName("chassis", scene.husky).index()
    steps = round(duration_s / scene.schedule.control_period_s)
    clouds, poses = [], []

    def read_after_update(step: int) -> float:
        return step * scene.schedule.control_period_s + scene.schedule.controller_offset_s + 1e-4

    def record(root_context) -> None:
        if len(clouds) < steps and root_context.get_time() >= read_after_update(len(clouds)):
            controller_context = controller.GetMyContextFromRoot(root_context)
            clouds.append(controller.GetInputPort("point_cloud").Eval(controller_context).xyzs().T.copy())
            poses.append(controller.GetInputPort("body_poses").Eval(controller_context)[chassis_index].GetAsMatrix4())

    RunEpisode(Simulator(diagram), diagram, scene, seed, watch=record, end_time_s=read_after_update(steps - 1))
    lidar = diagram.GetSubsystemByName("lidar")
    X_BL = scene.plant.GetFrameByName("lidar_mount", scene.husky).GetFixedPoseInBodyFrame()
    return LidarDrive(np.array(clouds), np.array(poses), np.asarray(lidar.ray_directions_L, dtype=float),
                      X_BL.GetAsMatrix4(), np.asarray(scene.task.goal, dtype=float)[:2])


def recorded_cloud(p_LP: np.ndarray) -> PointCloud:
    """A recorded step's points (N, 3) in L as the PointCloud the lidar gave."""
    cloud = PointCloud(len(p_LP), Fields(BaseField.kXYZs))
    cloud.mutable_xyzs()[:] = p_LP.T
    return cloud


def timed_update(controller, context) -> tuple[float, float]:
    """Runs `controller`'s periodic update on `context` in place; its wall and CPU seconds."""
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    context.SetDiscreteState(controller.EvalUniquePeriodicDiscreteUpdate(context))
    return time.perf_counter() - start_wall, time.process_time() - start_cpu


def measure_dwa_ms(drive: LidarDrive | None = None, repeats: int = 3) -> dict:
    """Times the DWA block's update on a recorded drive (see the module doc).

    Args:
        drive: the recorded inputs; None: `record_lidar_drive()` (about 20 s).
        repeats: replays; each step keeps its fastest run.

    Returns:
        {"dwa_update_ms", "dwa_update_cpu_ms": median wall and CPU time of an update without
        a global plan (costmap update + DWA local plan), "dwa_update_p90_ms": its 90th
        percentile (wall), "dwa_global_plan_ms", "dwa_global_plan_cpu_ms": median time of
        one Dijkstra global plan over the 20 m costmap, "dwa_step_ms": mean wall time of the
        whole update over all steps (global plans at 1 Hz amortized), "dwa_points": median
        returns per cloud, "dwa_steps": steps timed}.
    """
    drive = drive if drive is not None else record_lidar_drive()
    X_BL = RigidTransform(drive.X_BL)
    controller = DwaController(drive.goal_xy, 1, X_BL, ray_directions_L=drive.ray_directions_L)
    clouds = [recorded_cloud(p_LP) for p_LP in drive.clouds]
    steps = len(clouds)
    wall, cpu = np.full((repeats, steps), np.inf), np.full((repeats, steps), np.inf)
    planned = np.zeros(steps, dtype=bool)
    plan_wall, plan_cpu = [], []
    for repeat in range(repeats):
        context = controller.CreateDefaultContext()
        for step, (cloud, X_WB) in enumerate(zip(clouds, drive.poses, strict=True)):
            controller.GetInputPort("point_cloud").FixValue(context, cloud)
            controller.GetInputPort("body_poses").FixValue(context, [RigidTransform(), RigidTransform(X_WB)])
            context.SetTime(step * robot.CONTROL_PERIOD_S)
            plans = controller.planner_status(context)["plans"]
            wall[repeat, step], cpu[repeat, step] = timed_update(controller, context)
            planned[step] = controller.planner_status(context)["plans"] > plans
            if repeat == 0:
                origin, costs = controller.unpack_costmap(controller.GetOutputPort("costmap").Eval(context))
                start_wall, start_cpu = time.perf_counter(), time.process_time()
                plan(costs, origin, controller.costmap_resolution, X_WB[:2, 3], drive.goal_xy)
                plan_wall.append(time.perf_counter() - start_wall)
                plan_cpu.append(time.process_time() - start_cpu)
    # The first step starts from an empty map (and always plans); later ones are the steady state.
    wall, cpu = 1e3 * wall.min(axis=0)[1:], 1e3 * cpu.min(axis=0)[1:]
    local_only = ~planned[1:]
    return {
        "dwa_update_ms": float(np.median(wall[local_only])),
        "dwa_update_cpu_ms": float(np.median(cpu[local_only])),
        "dwa_update_p90_ms": float(np.percentile(wall[local_only], 90)),
        "dwa_global_plan_ms": float(np.median(1e3 * np.array(plan_wall))),
        "dwa_global_plan_cpu_ms": float(np.median(1e3 * np.array(plan_cpu))),
        "dwa_step_ms": float(wall.mean()),
        "dwa_points": float(np.median(np.isfinite(drive.clouds).all(axis=2).sum(axis=1))),
        "dwa_steps": float(len(wall)),
    }


if __name__ == "__main__":
    environment = sys.argv[1] if len(sys.argv) > 1 else "wide"
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 10.0
    print(measure_dwa_ms(record_lidar_drive(environment, duration_s=seconds)))
