"""The Husky model agrees with the numbers in ditch_drake/spec/robot.py (docs/design.md, "The robot")."""

import numpy as np
import pytest
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import RevoluteJoint

from ditch_drake.diagrams.ditch_scene import AddHusky, MakeParser
from ditch_drake.spec import robot


@pytest.fixture(scope="module")
def husky_plant():
    plant = MultibodyPlant(0.01)
    husky = AddHusky(plant)
    plant.Finalize()
    return plant, husky


def test_mass_and_centre_of_mass_height(husky_plant):
    plant, _ = husky_plant
    context = plant.CreateDefaultContext()
    assert plant.CalcTotalMass(context) == pytest.approx(robot.TOTAL_MASS_KG)
    # B sits one wheel radius above flat ground.
    com_z = plant.CalcCenterOfMassPositionInWorld(context)[2] - plant.EvalBodyPoseInWorld(
        context, plant.GetBodyByName("chassis")).translation()[2]
    assert com_z + robot.WHEEL_RADIUS_M == pytest.approx(robot.COM_HEIGHT_ABOVE_GROUND_M, abs=1e-6)


def test_wheels_and_actuators(husky_plant):
    plant, husky = husky_plant
    positions = robot.wheel_positions_in_body_frame()
    for name in robot.WHEEL_NAMES:
        joint = plant.GetJointByName(f"{name}_wheel_joint", husky)
        assert isinstance(joint, RevoluteJoint)
        assert np.allclose(joint.frame_on_parent().GetFixedPoseInBodyFrame().translation(), positions[name])
    actuators = [plant.get_joint_actuator(index) for index in plant.GetJointActuatorIndices(husky)]
    assert len(actuators) == 4
    for actuator in actuators:
        assert actuator.effort_limit() == robot.WHEEL_TORQUE_LIMIT_NM
        assert actuator.get_controller_gains().d == robot.WHEEL_SPEED_GAIN_NMS


def test_chassis_box_friction_and_lidar_mount(husky_plant):
    plant, husky = husky_plant
    sdf_path = MakeParser(MultibodyPlant(0.0)).package_map().GetPath("ditch_drake") + "/husky.sdf"
    with open(sdf_path) as sdf:
        text = sdf.read()
    size = " ".join(f"{value:.6g}" for value in robot.CHASSIS_SIZE_M)
    assert f"<size>{size}</size>" in text
    for effective in (robot.CHASSIS_FRICTION, robot.WHEEL_FRICTION):
        assert f"<drake:mu_dynamic>{robot.geometry_friction(effective):.6g}</drake:mu_dynamic>" in text
    mount = plant.GetFrameByName("lidar_mount", husky)
    assert np.allclose(mount.GetFixedPoseInBodyFrame().translation(), robot.LIDAR_MOUNT_XYZ_M)


def test_geometry_friction_combines_to_the_effective_value():
    for effective in (0.3, 2.0):
        mu = robot.geometry_friction(effective)
        assert 2 * mu * robot.TERRAIN_FRICTION / (mu + robot.TERRAIN_FRICTION) == pytest.approx(effective)
