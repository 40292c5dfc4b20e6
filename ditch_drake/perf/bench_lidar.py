"""Times the lidar (`ditch_drake.systems.lidar`): one control step's render and point cloud.

Run: `python -m ditch_drake.perf.bench_lidar [environment] [repeats] [terrain_faces]`
(`LidarConfig.terrain_faces`: up, top or all; default up). Prints the median wall and CPU
times (ms, one process) of the lidar's update (both cameras' depth renders through
`RenderEngineVtk` plus the conversion to the organized cloud; the returns-only
`point_cloud` is made only when read, which the policies' loops never do), the robot
moving a little between steps so that every step renders afresh. `RenderEngineVtk`
renders on the CPU here (Mesa's llvmpipe through EGL). `AddLidar` keeps the render on
the calling thread (`LidarConfig.rasterizer_threads`, `LP_NUM_THREADS=0`);
`LP_NUM_THREADS=2` in the environment before the process starts measures llvmpipe's
threaded default instead, whose CPU time can exceed its wall time.
"""

import sys
import time

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder

from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar
from ditch_drake.perception.lidar_model import LidarConfig


def measure_lidar_ms(env: str = "wide", repeats: int = 20, config: LidarConfig | None = None) -> dict:
    """Median time (ms) of one lidar update: render every camera and make the organized cloud.

    The robot stands at the environment's first task start and moves 2 mm forward between
    updates (a moved robot invalidates the cached renders). One untimed update warms up.

    Args:
        env: environment name.
        repeats: timed updates.
        config: the lidar; None for `LidarConfig()`.

    Returns:
        {"lidar_render_and_cloud_ms": median wall time, "lidar_render_and_cloud_cpu_ms":
        median process CPU time, "lidar_points": returns in the last cloud,
        "lidar_pixels": pixels rendered per update}.
    """
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment=env))
    lidar = AddLidar(builder, scene, config)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant = scene.plant
    plant_context = plant.GetMyMutableContextFromRoot(context)
    chassis = plant.GetBodyByName("chassis", scene.husky)
    converter = lidar.converter
    converter_context = converter.GetMyMutableContextFromRoot(context)
    X_WB = plant.EvalBodyPoseInWorld(plant_context, chassis)
    walls, cpus = [], []
    for k in range(repeats + 1):
        step = RigidTransform(X_WB.rotation().multiply([0.002 * k, 0.0, 0.0]))
        plant.SetFreeBodyPose(plant_context, chassis, step @ X_WB)
        wall, cpu = time.perf_counter(), time.process_time()
        converter.ExecuteForcedEvents(converter_context)
        if k > 0:
            walls.append(time.perf_counter() - wall)
            cpus.append(time.process_time() - cpu)
    rows, cols = converter.organized_shape
    return {
        "lidar_render_and_cloud_ms": 1e3 * float(np.median(walls)),
        "lidar_render_and_cloud_cpu_ms": 1e3 * float(np.median(cpus)),
        "lidar_points": converter.GetOutputPort("point_cloud").Eval(converter_context).size(),
        "lidar_pixels": rows * cols,
    }


if __name__ == "__main__":
    environment = sys.argv[1] if len(sys.argv) > 1 else "wide"
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 20
    faces = sys.argv[3] if len(sys.argv) > 3 else LidarConfig.terrain_faces
    print(measure_lidar_ms(environment, repeats, LidarConfig(terrain_faces=faces)))
