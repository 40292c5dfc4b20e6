"""Times the move_base baseline (`ditch_drake.systems.dwa_controller.DwaController`) on the real lidar.

Run: `python -m ditch_drake.perf.bench_dwa [environment] [seconds]`. A closed-loop drive
of the DWA through the environment's first task (seed 0) records what the controller saw at
each control step: the rendered lidar's organized cloud and the chassis pose. A fresh
controller then replays those steps, timing each periodic update, and Dijkstra's global plan
is timed on its own on each step's master costmap. The issue's budget counts one update's
costmap work (roll, normals, marking and raytracing, inflation) plus the DWA local plan,
with the global plan apart: the update figures below are the steps on which the 1 Hz global
planner did not run.

The drive's recording and the timing loop, with what its wall and CPU times mean, are
`ditch_drake.perf.recorded_drive`'s.
"""

import sys
import time

import numpy as np
from pydrake.math import RigidTransform

from ditch_drake.perf.recorded_drive import (
    REPLAY_CHASSIS_INDEX,
    LidarDrive,
    record_lidar_drive,
    time_replayed_updates,
)
from ditch_drake.planning.global_planner import plan
from ditch_drake.systems.dwa_controller import DwaController


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
    controller = DwaController(drive.goal_xy, REPLAY_CHASSIS_INDEX, RigidTransform(drive.X_BL),
                               ray_directions_L=drive.ray_directions_L)
    plans = np.zeros(len(drive.clouds), dtype=int)  # The global plans made so far, after each step.
    plan_wall, plan_cpu = [], []

    def time_global_plan(repeat: int, step: int, context) -> None:
        if repeat > 0:
            return
        plans[step] = controller.planner_status(context)["plans"]
        origin, costs = controller.unpack_costmap(controller.GetOutputPort("costmap").Eval(context))
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        plan(costs, origin, controller.costmap_resolution, drive.poses[step][:2, 3], drive.goal_xy)
        plan_wall.append(time.perf_counter() - start_wall)
        plan_cpu.append(time.process_time() - start_cpu)

    wall, cpu = time_replayed_updates(controller, drive, repeats, time_global_plan)
    # The first step starts from an empty map (and always plans); later ones are the steady state.
    local_only = np.diff(plans) == 0
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
