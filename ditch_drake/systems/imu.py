"""IMU: the chassis roll and pitch, optionally with seeded Gaussian noise."""

from dataclasses import dataclass

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import Value
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.primitives import RandomSource

from ditch_drake.spec import robot
from ditch_drake.spec.observation_layout import IMU_SIZE


@dataclass
class ImuConfig:
    """The IMU's noise.

    Attributes:
        noise_std_rad: standard deviation of the zero-mean Gaussian noise added to
            roll and pitch (rad), drawn independently per axis and per control
            step. 0 (the default) is noise-free and gives the system no `noise` port.
    """

    noise_std_rad: float = 0.0


class Imu(LeafSystem):
    """Reads the chassis attitude as [roll, pitch] (rad).

    Roll and pitch are those of Drake's `RollPitchYaw` of R_WB, the chassis
    orientation in the world (roll in (-pi, pi], pitch in [-pi/2, pi/2]).

    The output is computed from the current body poses (direct feedthrough, cheap),
    so a system sampling it at a control tick sees the pose at that tick.

    Noise: with `noise_std_rad > 0` the system has a vector input port `noise`
    (size 2), labelled as a random input of unit Gaussians, and outputs
    `[roll, pitch] + noise_std_rad * noise`. The randomness lives in the Context of
    the source feeding it: `AddImu` connects a Drake `RandomSource`, whose periodic
    update at the control rate draws a new sample and holds it, and whose seed
    `diagram.SetRandomContext(context, RandomGenerator(seed))` re-draws, so the same
    seed gives the same readings. (A default context uses the source's own seed,
    unique per `RandomSource` instance in the process: repeatable for one built
    diagram, not across rebuilds; seed episodes with `SetRandomContext`.)
    (`pydrake.systems.primitives.AddRandomInputs` wires the port the same way.)
    The source draws at t_k = k * period; a system updating at the same ticks (the
    `FrameStacker`) reads the sample drawn at t_{k-1}, so it sees each sample once.
    A LeafSystem written in Python cannot override `SetRandomState`, so the noise is
    not drawn inside this system.

    .. pydrake_system::

        name: Imu
        input_ports:
        - body_poses
        - noise (only with noise_std_rad > 0)
        output_ports:
        - roll_pitch

    Ports:
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        noise: unit Gaussian samples, [n_roll, n_pitch].
        roll_pitch: [roll (rad), pitch (rad)] of the chassis.
    """

    def __init__(self, chassis_body_index, config: ImuConfig | None = None):
        """Args:
            chassis_body_index: the chassis's BodyIndex in the plant.
            config: the noise; None for `ImuConfig()` (noise-free).
        """
        super().__init__()
        config = config if config is not None else ImuConfig()
        if not config.noise_std_rad >= 0.0:
            raise ValueError(f"noise_std_rad={config.noise_std_rad} must be >= 0")
        self._chassis_index = int(chassis_body_index)
        self._noise_std_rad = float(config.noise_std_rad)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        tickets = {self.input_port_ticket(self._poses_port.get_index())}
        self._noise_port = None
        if self._noise_std_rad > 0.0:
            self._noise_port = self.DeclareVectorInputPort(
                "noise", BasicVector(IMU_SIZE), RandomDistribution.kGaussian)
            tickets.add(self.input_port_ticket(self._noise_port.get_index()))
        self.DeclareVectorOutputPort("roll_pitch", IMU_SIZE, self._calc_roll_pitch, prerequisites_of_calc=tickets)

    @property
    def noise_std_rad(self) -> float:
        """The noise standard deviation (rad); 0 when noise-free."""
        return self._noise_std_rad

    def _calc_roll_pitch(self, context, output: BasicVector) -> None:
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        rpy = RollPitchYaw(X_WB.rotation())
        reading = np.array([rpy.roll_angle(), rpy.pitch_angle()])
        if self._noise_port is not None:
            reading += self._noise_std_rad * self._noise_port.Eval(context)
        output.SetFromVector(reading)


def AddImu(builder: DiagramBuilder, body_poses: OutputPort, chassis_body_index,
           config: ImuConfig | None = None, name: str = "imu",
           noise_period_s: float = robot.CONTROL_PERIOD_S) -> Imu:
    """Adds an `Imu` named `name` reading `body_poses`, with its noise source if noisy.

    With noise, a `RandomSource` of unit Gaussians named `{name}_noise` sampling every
    `noise_period_s` feeds the IMU's `noise` port; it is seeded by `SetRandomContext`.

    Args:
        builder: the diagram builder.
        body_poses: the plant's `body_poses` output port.
        chassis_body_index: the chassis's BodyIndex in the plant.
        config: the noise; None for `ImuConfig()` (noise-free).
        name: the IMU's system name.
        noise_period_s: how often a new noise sample is drawn (s).

    Returns:
        The added IMU.
    """
    imu = builder.AddNamedSystem(name, Imu(chassis_body_index, config))
    builder.Connect(body_poses, imu.GetInputPort("body_poses"))
    if imu.noise_std_rad > 0.0:
        source = builder.AddNamedSystem(
            f"{name}_noise", RandomSource(RandomDistribution.kGaussian, IMU_SIZE, noise_period_s))
        builder.Connect(source.get_output_port(0), imu.GetInputPort("noise"))
    return imu
