"""The skid-steer drive (`ditch_drake.systems.skid_steer_drive`): a (v, w) command to wheel speed targets."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from ditch_drake.spec import actions
from ditch_drake.systems import skid_steer_drive
from ditch_drake.systems.skid_steer_drive import ConstantCommand, SkidSteerDrive, wheel_speeds_radps

WHEEL_IS_LEFT = [True, False, True, False]


def desired_state(command) -> np.ndarray:
    speeds = wheel_speeds_radps(np.asarray(command, dtype=float), np.asarray(WHEEL_IS_LEFT))
    return np.concatenate([np.zeros_like(speeds), speeds])


def test_kept_wheel_speeds_are_those_of_the_map_bit_for_bit(monkeypatch):
    # Few kept commands, so that the drive also forgets them on the way.
    monkeypatch.setattr(skid_steer_drive, "_KEPT_COMMANDS", 5)
    drive = SkidSteerDrive(WHEEL_IS_LEFT)
    context = drive.CreateDefaultContext()
    port = drive.GetOutputPort("wheel_desired_state")
    labels = [actions.label_to_command(label) for label in range(17)]
    commands = [*labels, *labels[::-1], [0.0, 0.0], [-0.0, 0.0], [0.0, -0.0], [0.3, 1e-300], [0.3, 0.85]]
    for command in commands:
        drive.GetInputPort("command").FixValue(context, command)
        assert port.Eval(context).tobytes() == desired_state(command).tobytes(), command
    assert len(drive._desired_by_command) <= 5


@pytest.mark.parametrize("command", [[np.nan, 0.0], [1.0, np.inf]])
def test_non_finite_command_is_refused_every_time(command):
    drive = SkidSteerDrive(WHEEL_IS_LEFT)
    context = drive.CreateDefaultContext()
    drive.GetInputPort("command").FixValue(context, command)
    for _ in range(2):
        with pytest.raises(ValueError, match="must be finite"):
            drive.GetOutputPort("wheel_desired_state").Eval(context)


class WheelTargetReader(LeafSystem):
    """Reads the drive's output at every 20 ms step, as the plant's discrete step does."""

    def __init__(self, size: int):
        super().__init__()
        port = self.DeclareVectorInputPort("wheel_desired_state", size)
        self.DeclareDiscreteState(size)
        self.DeclarePeriodicDiscreteUpdateEvent(
            0.02, 0.0, lambda context, state: state.set_value(0, port.Eval(context)))


@pytest.mark.parametrize(("source", "calls"), [("vector_source", 50), ("constant_command", 2)])
def test_a_constant_command_is_mapped_once_until_it_changes(monkeypatch, source, calls):
    counted = []
    calc = SkidSteerDrive._calc_desired_state
    monkeypatch.setattr(SkidSteerDrive, "_calc_desired_state",
                        lambda self, context, output: counted.append(context.get_time()) or calc(self, context, output))
    builder = DiagramBuilder()
    command = [1.0, 0.0]
    block = ConstantVectorSource(command) if source == "vector_source" else ConstantCommand(command)
    builder.AddNamedSystem("constant_command", block)
    drive = builder.AddSystem(SkidSteerDrive(WHEEL_IS_LEFT))
    reader = builder.AddSystem(WheelTargetReader(2 * len(WHEEL_IS_LEFT)))
    builder.Connect(block.get_output_port(), drive.GetInputPort("command"))
    builder.Connect(drive.get_output_port(), reader.get_input_port())
    simulator = Simulator(builder.Build())
    context = simulator.get_mutable_context()
    simulator.AdvanceTo(0.5)
    block.get_mutable_source_value(block.GetMyMutableContextFromRoot(context)).set_value([0.5, 0.3])
    simulator.AdvanceTo(1.0)
    # ConstantVectorSource's output depends on the time for Drake's cache: a map per step.
    assert len(counted) == calls
    held = reader.GetMyContextFromRoot(context).get_discrete_state_vector().value()
    assert held.tobytes() == desired_state([0.5, 0.3]).tobytes()


def test_constant_command_checks_its_shape():
    with pytest.raises(ValueError, match=r"\[v m/s, w rad/s\]"):
        ConstantCommand([1.0, 0.0, 0.0])
