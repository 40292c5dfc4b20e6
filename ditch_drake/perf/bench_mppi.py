"""Times the rollover-aware MPPI baseline (`ditch_drake.systems.mppi_controller.MppiController`).

Run: `python -m ditch_drake.perf.bench_mppi [environment] [task] [seconds]`. As the DWA's
bench (`ditch_drake.perf.bench_dwa`): a closed-loop drive of the MPPI itself through
the environment's task (seed 0) records what the controller saw at each control step, the
rendered lidar's organized cloud and the chassis pose; a fresh controller then replays those
steps, timing each whole periodic update (window roll, fusion of the cloud, footprint fill and
one MPPI plan of all samples). The default drive, wide_walled task 1 for 15 s, goes from the
start over the flat to the ditch's down wall, so the map fills and the walls' cells enter the
samples' attitude predictions, the expensive case.

The timing loop, with what its wall and CPU times mean, is `ditch_drake.perf.recorded_drive`'s.
numpy runs one thread here only if the caller limits BLAS threads; the update's work is
elementwise numpy, which is single-threaded anyway.
"""

import sys

import numpy as np
from pydrake.math import RigidTransform

from ditch_drake.diagrams.rollout import MppiBaselineConfig
from ditch_drake.perf.recorded_drive import (
    REPLAY_CHASSIS_INDEX,
    LidarDrive,
    record_lidar_drive,
    time_replayed_updates,
)
from ditch_drake.systems.mppi_controller import MppiController


def record_mppi_drive(environment: str = "wide_walled", task: int = 1, seed: int = 0, duration_s: float = 15.0,
                      config: MppiBaselineConfig | None = None) -> LidarDrive:
    """Drives the MPPI baseline for `duration_s` (s), or until the episode ends, and records its
    inputs at each control step (`recorded_drive.record_lidar_drive`)."""
    return record_lidar_drive(environment, task, seed, duration_s, config or MppiBaselineConfig(), "mppi")


def measure_mppi_ms(drive: LidarDrive | None = None, repeats: int = 3, config: MppiBaselineConfig | None = None) -> dict:
    """Times the MPPI block's whole periodic update on a recorded drive (see the module doc).

    Args:
        drive: the recorded inputs; None: `record_mppi_drive()` (about a minute).
        repeats: replays; each step keeps its fastest run.
        config: the controller's config (None: the registered default), as the drive's.

    Returns:
        {"mppi_update_ms", "mppi_update_cpu_ms": median wall and CPU time of one update,
        "mppi_update_p90_ms": its 90th percentile (wall), "mppi_samples": samples per plan,
        "mppi_points": median returns per cloud, "mppi_steps": steps timed}. The first step
        (an empty map) is left out, as in the DWA's bench.
    """
    drive = drive if drive is not None else record_mppi_drive()
    config = config or MppiBaselineConfig()
    controller = MppiController(drive.goal_xy, REPLAY_CHASSIS_INDEX, RigidTransform(drive.X_BL), config.planner,
                                config.elevation_map, goal_tolerance_m=config.goal_tolerance_m)
    wall, cpu = time_replayed_updates(controller, drive, repeats)
    return {
        "mppi_update_ms": float(np.median(wall)),
        "mppi_update_cpu_ms": float(np.median(cpu)),
        "mppi_update_p90_ms": float(np.percentile(wall, 90)),
        "mppi_samples": float(config.planner.samples),
        "mppi_points": float(np.median(np.isfinite(drive.clouds).all(axis=2).sum(axis=1))),
        "mppi_steps": float(len(wall)),
    }


if __name__ == "__main__":
    environment = sys.argv[1] if len(sys.argv) > 1 else "wide_walled"
    task = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    seconds = float(sys.argv[3]) if len(sys.argv) > 3 else 15.0
    print(measure_mppi_ms(record_mppi_drive(environment, task, duration_s=seconds)))
