"""Tests of the observation sensors: IMU, goal sensor and frame stacker."""

import math

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.common.value import Value
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource

from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.spec import observation_layout as spec
from ditch_drake.spec import robot
from ditch_drake.spec.planar import wrap_to_pi
from ditch_drake.systems.frame_stacker import FrameStacker
from ditch_drake.systems.goal import GoalSensor
from ditch_drake.systems.imu import AddImu, Imu, ImuConfig

CHASSIS = 1  # Body index of the chassis in the hand-made pose lists below (0 is the world).


def poses(X_WB: RigidTransform) -> list[RigidTransform]:
    return [RigidTransform(), X_WB]


def pose(x: float = 0.0, y: float = 0.0, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> RigidTransform:
    return RigidTransform(RollPitchYaw(roll, pitch, yaw), [x, y, 0.3])


def test_observation_spec_sizes():
    assert spec.IMAGE_SIZE == 128 and spec.STACK_DEPTH == 4 and spec.IMU_SIZE == 2
    assert spec.IMAGE_STACK_SHAPE == (4, 128, 128)
    assert spec.IMAGE_STACK_SIZE == 4 * 128 * 128
    assert (spec.IMU_STACK_SIZE, spec.DISTANCE_STACK_SIZE, spec.BEARING_STACK_SIZE) == (8, 4, 4)


@pytest.mark.parametrize("roll, pitch, yaw", [(0.0, 0.0, 0.0), (0.3, -0.2, 1.0), (-1.2, 0.7, -2.5)])
def test_imu_reads_roll_pitch(roll, pitch, yaw):
    imu = Imu(CHASSIS)
    assert [imu.get_input_port(i).get_name() for i in range(imu.num_input_ports())] == ["body_poses"]
    context = imu.CreateDefaultContext()
    imu.GetInputPort("body_poses").FixValue(context, poses(pose(roll=roll, pitch=pitch, yaw=yaw)))
    np.testing.assert_allclose(imu.GetOutputPort("roll_pitch").Eval(context), [roll, pitch], atol=1e-12)


def test_imu_reads_rotation_about_world_axes():
    # Tilted 0.25 rad nose-down about the body y axis: pitch +0.25 (Drake's RPY).
    imu = Imu(CHASSIS)
    context = imu.CreateDefaultContext()
    imu.GetInputPort("body_poses").FixValue(context, poses(RigidTransform(RotationMatrix.MakeYRotation(0.25))))
    np.testing.assert_allclose(imu.GetOutputPort("roll_pitch").Eval(context), [0.0, 0.25], atol=1e-12)


def test_imu_noise_scales_the_noise_input():
    imu = Imu(CHASSIS, ImuConfig(noise_std_rad=0.1))
    context = imu.CreateDefaultContext()
    imu.GetInputPort("body_poses").FixValue(context, poses(pose(roll=0.2, pitch=0.1)))
    imu.GetInputPort("noise").FixValue(context, [1.0, -2.0])
    np.testing.assert_allclose(imu.GetOutputPort("roll_pitch").Eval(context), [0.3, -0.1], atol=1e-12)
    with pytest.raises(ValueError):
        Imu(CHASSIS, ImuConfig(noise_std_rad=-1.0))


def noisy_imu_diagram():
    """A level, still robot's noisy IMU in a diagram, with its noise source."""
    builder = DiagramBuilder()
    source = builder.AddSystem(ConstantValueSource(Value(poses(pose()))))
    imu = AddImu(builder, source.get_output_port(), CHASSIS, ImuConfig(noise_std_rad=0.05))
    assert builder.HasSubsystemNamed("imu_noise")
    return builder.Build(), imu


def noisy_readings(diagram, imu, seed: int | None, steps: int = 4) -> np.ndarray:
    """IMU readings at the first `steps` control ticks, from a context seeded with `seed`."""
    context = diagram.CreateDefaultContext()
    if seed is not None:
        diagram.SetRandomContext(context, RandomGenerator(seed))
    simulator = Simulator(diagram, context)
    imu_context = imu.GetMyContextFromRoot(context)
    readings = []
    for step in range(steps):
        simulator.AdvanceTo(step * robot.CONTROL_PERIOD_S + 1e-6)
        readings.append(imu.GetOutputPort("roll_pitch").Eval(imu_context).copy())
    return np.array(readings)


def test_imu_noise_is_deterministic_per_seed():
    diagram, imu = noisy_imu_diagram()
    first, other = noisy_readings(diagram, imu, 7), noisy_readings(diagram, imu, 8)
    assert not np.allclose(first, other)
    np.testing.assert_array_equal(noisy_readings(diagram, imu, None), noisy_readings(diagram, imu, None))
    # The same seed gives the same readings, in a rebuilt diagram too.
    rebuilt, rebuilt_imu = noisy_imu_diagram()
    np.testing.assert_array_equal(first, noisy_readings(diagram, imu, 7))
    np.testing.assert_array_equal(first, noisy_readings(rebuilt, rebuilt_imu, 7))
    # A new sample every tick, of about the configured size.
    assert len({tuple(row) for row in first}) == len(first)
    assert np.all(np.abs(first) < 0.05 * 6)


@pytest.mark.parametrize("xy, yaw, goal, distance, bearing", [
    ((0.0, 0.0), 0.0, (3.0, 4.0), 5.0, math.atan2(4.0, 3.0)),
    ((1.0, 1.0), math.pi / 2, (1.0, 3.0), 2.0, 0.0),
    ((1.0, 1.0), math.pi / 2, (3.0, 1.0), 2.0, -math.pi / 2),
    ((0.0, 0.0), 0.0, (-2.0, 0.0), 2.0, math.pi),  # Straight behind: +pi, not -pi.
    ((0.0, 0.0), 3.0, (-1.0, -0.1), math.hypot(1.0, 0.1), math.atan2(-0.1, -1.0) - 3.0 + 2 * math.pi),
    ((0.0, 0.0), -3.0, (-1.0, 0.1), math.hypot(1.0, 0.1), math.atan2(0.1, -1.0) + 3.0 - 2 * math.pi),
])
def test_goal_distance_and_bearing(xy, yaw, goal, distance, bearing):
    sensor = GoalSensor(CHASSIS, goal)
    context = sensor.CreateDefaultContext()
    sensor.GetInputPort("body_poses").FixValue(context, poses(pose(*xy, yaw=yaw)))
    both = sensor.GetOutputPort("distance_bearing").Eval(context)
    np.testing.assert_allclose(both, [distance, bearing], atol=1e-12)
    np.testing.assert_allclose(sensor.GetOutputPort("distance").Eval(context), [distance], atol=1e-12)
    np.testing.assert_allclose(sensor.GetOutputPort("bearing").Eval(context), [bearing], atol=1e-12)
    assert -math.pi < both[1] <= math.pi


def test_goal_bearing_uses_the_planar_heading_when_tilted():
    # Pitched and rolled: the bearing still follows the x-axis's ground projection.
    sensor = GoalSensor(CHASSIS, (0.0, 5.0))
    context = sensor.CreateDefaultContext()
    sensor.GetInputPort("body_poses").FixValue(context, poses(pose(roll=0.4, pitch=-0.6, yaw=math.pi / 2)))
    np.testing.assert_allclose(sensor.GetOutputPort("distance_bearing").Eval(context), [5.0, 0.0], atol=1e-12)


def test_wrap_to_pi():
    for angle, wrapped in [(math.pi, math.pi), (-math.pi, math.pi), (3 * math.pi, math.pi),
                           (2 * math.pi + 0.1, 0.1), (-2 * math.pi - 0.1, -0.1)]:
        assert wrap_to_pi(angle) == pytest.approx(wrapped)


def fix_stacker_inputs(stacker: FrameStacker, context, step: int) -> None:
    """Inputs that identify the step: every value is step + 1 (plus 0.5 for pitch)."""
    value = float(step + 1)
    stacker.GetInputPort("normal_image").FixValue(context, np.full(spec.IMAGE_PIXELS, value))
    stacker.GetInputPort("roll_pitch").FixValue(context, [value, value + 0.5])
    stacker.GetInputPort("distance").FixValue(context, [value])
    stacker.GetInputPort("bearing").FixValue(context, [-value])


def expected_stacks(pushes: int) -> dict[str, np.ndarray]:
    newest_first = [float(pushes - age) if age < pushes else 0.0 for age in range(spec.STACK_DEPTH)]
    imu = [[v, v + 0.5] if v else [0.0, 0.0] for v in newest_first]
    return {
        "image_stack": np.repeat(newest_first, spec.IMAGE_PIXELS),
        "imu_stack": np.array(imu).ravel(),
        "distance_stack": np.array(newest_first),
        "bearing_stack": -np.array(newest_first),
    }


def check_stacks(stacker: FrameStacker, context, pushes: int) -> None:
    for name, expected in expected_stacks(pushes).items():
        np.testing.assert_array_equal(stacker.GetOutputPort(name).Eval(context), expected, err_msg=name)


def test_stacker_starts_at_zero_with_the_spec_sizes():
    stacker = FrameStacker()
    context = stacker.CreateDefaultContext()
    sizes = {name: stacker.GetOutputPort(name).size() for name in expected_stacks(0)}
    assert sizes == {"image_stack": spec.IMAGE_STACK_SIZE, "imu_stack": spec.IMU_STACK_SIZE,
                     "distance_stack": spec.DISTANCE_STACK_SIZE, "bearing_stack": spec.BEARING_STACK_SIZE}
    check_stacks(stacker, context, 0)
    image = stacker.GetOutputPort("image_stack").Eval(context).reshape(spec.IMAGE_STACK_SHAPE)
    assert image.shape == (4, 128, 128)


def test_stacker_forced_updates_stack_newest_first():
    stacker = FrameStacker()
    context = stacker.CreateDefaultContext()
    for step in range(5):
        fix_stacker_inputs(stacker, context, step)
        update = stacker.AllocateDiscreteVariables()
        stacker.CalcForcedDiscreteVariableUpdate(context, update)
        context.SetDiscreteState(update)
        if step + 1 in (1, 2, 5):
            check_stacks(stacker, context, step + 1)


def test_stacker_periodic_updates_in_a_simulator():
    stacker = FrameStacker()
    context = stacker.CreateDefaultContext()
    simulator = Simulator(stacker, context)
    for step in range(5):
        fix_stacker_inputs(stacker, context, step)
        # The tick at t_k = k * period is handled by the call that passes it.
        simulator.AdvanceTo(step * robot.CONTROL_PERIOD_S + 0.5 * robot.CONTROL_PERIOD_S)
        pushes = step + 1
        if pushes in (1, 2, 5):
            check_stacks(stacker, context, pushes)
    # Two contexts never share a stack.
    check_stacks(stacker, stacker.CreateDefaultContext(), 0)


def test_sensors_in_the_ditch_scene():
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="wide"))
    plant = scene.plant
    chassis = plant.GetBodyByName("chassis", scene.husky).index()
    body_poses = plant.get_body_poses_output_port()
    imu = AddImu(builder, body_poses, chassis)
    goal = builder.AddNamedSystem("goal_sensor", GoalSensor(chassis, scene.task.goal))
    builder.Connect(body_poses, goal.GetInputPort("body_poses"))
    stacker = builder.AddNamedSystem("frame_stacker", FrameStacker())
    image = builder.AddNamedSystem("blank_image", ConstantVectorSource(np.zeros(spec.IMAGE_PIXELS)))
    builder.Connect(image.get_output_port(), stacker.GetInputPort("normal_image"))
    builder.Connect(imu.GetOutputPort("roll_pitch"), stacker.GetInputPort("roll_pitch"))
    builder.Connect(goal.GetOutputPort("distance"), stacker.GetInputPort("distance"))
    builder.Connect(goal.GetOutputPort("bearing"), stacker.GetInputPort("bearing"))
    diagram = builder.Build()

    context = diagram.CreateDefaultContext()
    scene.drive.GetInputPort("command").FixValue(scene.drive.GetMyContextFromRoot(context), [1.0, 0.0])
    goal_context = goal.GetMyContextFromRoot(context)
    start = goal.GetOutputPort("distance_bearing").Eval(goal_context).copy()
    simulator = Simulator(diagram, context)
    simulator.AdvanceTo(2.0)
    end = goal.GetOutputPort("distance_bearing").Eval(goal_context)
    roll_pitch = imu.GetOutputPort("roll_pitch").Eval(imu.GetMyContextFromRoot(context))
    assert np.all(np.isfinite(end)) and np.all(np.isfinite(roll_pitch))
    assert end[0] < start[0] - 0.5
    assert np.all(np.abs(roll_pitch) < 0.2)

    stacker_context = stacker.GetMyContextFromRoot(context)
    distances = stacker.GetOutputPort("distance_stack").Eval(stacker_context)
    # Newest first while driving toward the goal: the distances grow with age.
    assert np.all(np.diff(distances) > 0)
    assert np.all(np.isfinite(stacker.GetOutputPort("imu_stack").Eval(stacker_context)))
