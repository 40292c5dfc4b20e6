"""What a lidar-fed planner block saw on a closed-loop drive, and its periodic update timed on a
replay of it: the recorded-cloud timing loop of the DWA's and the MPPI's benches
(`bench_dwa`, `bench_mppi`).

Wall time is what a real-time loop sees; CPU time (`time.process_time`, this process's single
thread) is the time on one core, which stays meaningful on a shared machine where other
processes take turns on the cores. Each step is replayed `repeats` times and its fastest run
kept, as `timeit` does, so that a step that lost the core to another process counts at its
own cost.
"""

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import DwaBaselineConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.spec import robot

# The replayed block's chassis: index 1 of the `body_poses` it is given (index 0, the world).
REPLAY_CHASSIS_INDEX = 1


@dataclass
class LidarDrive:
    """What a lidar-fed planner block saw at each control step of a closed-loop drive.

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


def time_replayed_updates(controller, drive: LidarDrive, repeats: int = 3,
                          after_update: Callable[[int, int, object], None] | None = None,
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Replays `drive` into `controller` (built with chassis index `REPLAY_CHASSIS_INDEX`),
    `repeats` times from a fresh context, timing each periodic update.

    Args:
        controller: the planner block: `point_cloud` and `body_poses` inputs, one periodic
            discrete update.
        drive: the recorded inputs.
        repeats: replays; each step keeps its fastest run.
        after_update: called as (repeat, step, context) after each update, outside the timing.

    Returns:
        The wall and CPU time (ms) of each step after the first (which starts from an empty
        map), each its fastest over the repeats.
    """
    clouds = [recorded_cloud(p_LP) for p_LP in drive.clouds]
    wall, cpu = np.full((repeats, len(clouds)), np.inf), np.full((repeats, len(clouds)), np.inf)
    for repeat in range(repeats):
        context = controller.CreateDefaultContext()
        for step, (cloud, X_WB) in enumerate(zip(clouds, drive.poses, strict=True)):
            controller.GetInputPort("point_cloud").FixValue(context, cloud)
            poses = [RigidTransform()] * REPLAY_CHASSIS_INDEX + [RigidTransform(X_WB)]
            controller.GetInputPort("body_poses").FixValue(context, poses)
            context.SetTime(step * robot.CONTROL_PERIOD_S)
            wall[repeat, step], cpu[repeat, step] = timed_update(controller, context)
            if after_update is not None:
                after_update(repeat, step, context)
    return 1e3 * wall.min(axis=0)[1:], 1e3 * cpu.min(axis=0)[1:]
