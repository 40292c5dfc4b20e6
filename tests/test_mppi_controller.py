"""The MPPI baseline's Drake block: in a rollout diagram, and on bad clouds."""

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform
from pydrake.perception import PointCloud
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.controllers import controller_config, get_controller
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, MppiBaselineConfig, RolloutConfig
from ditch_drake.planning.mppi import MppiPlannerConfig
from ditch_drake.spec import robot
from ditch_drake.systems.mppi_controller import MppiController, MppiMode

X_BL = RigidTransform(robot.LIDAR_MOUNT_XYZ_M)
CHASSIS = 1


def test_mppi_is_registered():
    assert isinstance(controller_config("mppi"), MppiBaselineConfig)
    assert "MPPI" in get_controller("mppi").description


def test_rollout_diagram_with_mppi_commands_a_finite_label_and_maps_the_ground():
    diagram, _scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment="wide_walled", task=1),
                                                      controller=MppiBaselineConfig()))
    controller = diagram.GetSubsystemByName("mppi")
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetRandomContext(context, RandomGenerator(0))
    simulator.Initialize()
    simulator.AdvanceTo(1.0)
    own = controller.GetMyContextFromRoot(context)
    command = controller.GetOutputPort("command").Eval(own)
    assert np.all(np.isfinite(command)) and command[0] == 1.0  # Driving, at the label speed.
    status = controller.planner_status(own)
    assert status["mode"] == MppiMode.DRIVING and status["updates"] == 10 and status["no_data"] == 0
    _origin, heights = controller.unpack_map(controller.GetOutputPort("elevation_map").Eval(own))
    seen = np.isfinite(heights)
    assert 0.02 < seen.mean() < 0.6 and np.abs(heights[seen]).max() < 0.2  # Flat field near the start.


def test_empty_or_all_nan_cloud_gives_zero_command_and_keeps_the_map_unknown():
    controller = MppiController([10.0, 0.0], CHASSIS, X_BL, MppiPlannerConfig(samples=64))
    context = controller.CreateDefaultContext()
    controller.GetInputPort("body_poses").FixValue(context, [RigidTransform(), RigidTransform([0, 0, 0.165])])
    simulator = Simulator(controller, context)
    for cloud in (PointCloud(), PointCloud(5)):  # Empty; 5 points of NaN (the default xyzs).
        if cloud.size():
            cloud.mutable_xyzs()[:] = np.nan
        controller.GetInputPort("point_cloud").FixValue(context, cloud)
        simulator.AdvanceTo(context.get_time() + 0.1)
        np.testing.assert_array_equal(controller.GetOutputPort("command").Eval(context), [0.0, 0.0])
        assert controller.planner_status(context)["mode"] == MppiMode.NO_DATA
    _, heights = controller.unpack_map(controller.GetOutputPort("elevation_map").Eval(context))
    known = np.isfinite(heights)
    assert 0 < known.sum() < 150 and np.allclose(heights[known], 0.0)  # Only the ground under the wheels.


def test_mppi_benchmark_times_the_update_on_a_tiny_replay():
    from ditch_drake.perf.bench_mppi import measure_mppi_ms, record_mppi_drive

    config = MppiBaselineConfig(planner=MppiPlannerConfig(samples=64))
    drive = record_mppi_drive("wide_walled", task=1, duration_s=0.5, config=config)
    assert drive.clouds.shape[:2] == (5, len(drive.ray_directions_L))
    figures = measure_mppi_ms(drive, repeats=1, config=config)
    for key in ("mppi_update_ms", "mppi_update_cpu_ms", "mppi_update_p90_ms"):
        assert 0.0 < figures[key] < 1000.0, key
    assert figures["mppi_steps"] == 4 and figures["mppi_samples"] == 64 and figures["mppi_points"] > 1000
