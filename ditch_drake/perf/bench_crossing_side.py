"""Times the perceived crossing side (`ditch_drake.systems.perceived_crossing_side.PerceivedCrossingSide`).

Run: `python -m ditch_drake.perf.bench_crossing_side`. A closed-loop drive of the DWA baseline
toward the wide ditch (`recorded_drive.record_lidar_drive`: the same lidar the learned policy
has, and the same clouds) records the organized cloud and the chassis pose at each control
step; a fresh block then replays them, timing each periodic update. The block does nothing more
once it holds its side, so it is timed with the hold switched off: every step pays for marking
the rays, rolling the window and estimating the edge, the cost of a step before the approach
zone, which bounds what the block adds to any control step.
"""

from dataclasses import replace

import numpy as np
from pydrake.math import RigidTransform

from ditch_drake.perf.recorded_drive import REPLAY_CHASSIS_INDEX, LidarDrive, record_lidar_drive, time_replayed_updates
from ditch_drake.spec import robot
from ditch_drake.systems.perceived_crossing_side import PerceivedCrossingSide, PerceivedCrossingSideConfig


def measure_crossing_side_ms(drive: LidarDrive | None = None, repeats: int = 3) -> dict:
    """Times the perceived crossing side's periodic update on a recorded drive (module doc).

    Returns:
        {"crossing_side_ms", "crossing_side_cpu_ms": median wall and CPU time of one update,
        "crossing_side_p90_ms": its 90th percentile (wall), "crossing_side_steps": steps timed,
        "crossing_side_seen_steps": of them, those where the edge was seen}.
    """
    drive = drive if drive is not None else record_lidar_drive("wide", 0, 0, 12.0)
    never_hold = replace(PerceivedCrossingSideConfig(), approach_margin_m=1e-6, hold_tilt_deg=90.0)
    block = PerceivedCrossingSide(drive.goal_xy, REPLAY_CHASSIS_INDEX, RigidTransform(drive.X_BL),
                                  drive.ray_directions_L, robot.LIDAR_RANGE_M, never_hold)
    seen = []

    def count_seen(repeat: int, step: int, context) -> None:
        if repeat == 0 and step > 0:
            seen.append(block.GetOutputPort("edge").Eval(context)[0] > 0)

    wall, cpu = time_replayed_updates(block, drive, repeats, after_update=count_seen)
    return {"crossing_side_ms": float(np.median(wall)), "crossing_side_cpu_ms": float(np.median(cpu)),
            "crossing_side_p90_ms": float(np.percentile(wall, 90)), "crossing_side_steps": len(wall),
            "crossing_side_seen_steps": int(np.sum(seen))}


if __name__ == "__main__":
    import json

    print(json.dumps(measure_crossing_side_ms(), indent=1))
