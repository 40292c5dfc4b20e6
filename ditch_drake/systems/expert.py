"""The scripted expert: a careful driver with seeded, human-like variation."""

from dataclasses import dataclass, field

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import Adder, DiscreteTimeDelay, MatrixGain, RandomSource

from ditch_drake.common.config_yaml import WRITTEN_WHEN_SET
from ditch_drake.spec import robot, schedule
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver, EdgeAngleDriverConfig
from ditch_drake.systems.window_route import WindowRouteDriver
from ditch_drake.world.terrain import DitchTerrain
from ditch_drake.world.windows import has_steep_sections


@dataclass
class ExpertVariation:
    """Ranges of the expert's per-demonstration variation (degrees, s, rad/s).

    Attributes:
        wall_angle_deg: uniform range [low, high] of the angle to the edge going down.
        climb_angle_deg: uniform range of the angle to the edge going up.
        approach_margin_m: uniform range of how early it lines up before the hinge.
        reaction_delay_steps: the delay is drawn uniformly from 0..this many control steps.
        steering_noise_radps: standard deviation of the Gaussian noise added to the
            steering command every control step.
        replan_each_step: see `EdgeAngleDriverConfig` (True for a DAgger labeller
            that answers from the current pose).
        keep_facing_side: see `EdgeAngleDriverConfig` (True for a fallback that takes over
            a robot another driver brought into the approach zone).
        lead_in: see `EdgeAngleDriverConfig`: first make room along the ditch when the
            crossing would not fit between the robot and the ditch's end.
    """

    wall_angle_deg: list[float] = field(default_factory=lambda: [17.0, 23.0])
    climb_angle_deg: list[float] = field(default_factory=lambda: [32.0, 38.0])
    approach_margin_m: list[float] = field(default_factory=lambda: [2.0, 3.0])
    reaction_delay_steps: int = 1
    steering_noise_radps: float = 0.05
    replan_each_step: bool = False
    keep_facing_side: bool = field(default=False, metadata=WRITTEN_WHEN_SET)
    lead_in: bool = False


@dataclass
class ExpertStyle:
    """One demonstration's draw from `ExpertVariation`."""

    driver: EdgeAngleDriverConfig
    reaction_delay_steps: int
    steering_noise_radps: float


def draw_expert_style(seed: int, variation: ExpertVariation | None = None) -> ExpertStyle:
    """The expert's style for the demonstration with this seed (deterministic)."""
    variation = variation or ExpertVariation()
    rng = np.random.default_rng([seed, 0x5EED])
    driver = EdgeAngleDriverConfig(
        wall_angle_deg=float(rng.uniform(*variation.wall_angle_deg)),
        climb_angle_deg=float(rng.uniform(*variation.climb_angle_deg)),
        approach_margin_m=float(rng.uniform(*variation.approach_margin_m)),
        replan_each_step=variation.replan_each_step,
        keep_facing_side=variation.keep_facing_side,
        lead_in=variation.lead_in,
    )
    delay = int(rng.integers(0, variation.reaction_delay_steps + 1))
    return ExpertStyle(driver, delay, variation.steering_noise_radps)


class ExpertDriver(Diagram):
    """Drives like a careful person who knows the terrain: `EdgeAngleDriver` plus variation.

    Inside: the edge-angle driver with this demonstration's angles and margin (on a
    ditch whose walls are too steep in places, `WindowRouteDriver`: through the windows),
    Gaussian steering noise from a Drake `RandomSource` (seeded by
    `diagram.SetRandomContext`, so the same seed gives the same run), and a
    reaction delay of whole control steps. Its output is a *raw* command: wire it
    to an `ActionQuantizer`, which snaps it to an action label as the paper's
    teleop did.

    .. pydrake_system::

        name: ExpertDriver
        input_ports:
        - body_poses
        output_ports:
        - raw_command

    Ports:
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        raw_command: [v (m/s), w (rad/s)], updated at the control rate.
    """

    def __init__(self, terrain: DitchTerrain, goal_xy, chassis_body_index, style: ExpertStyle,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = schedule.CONTROLLER_OFFSET_S):
        super().__init__()
        builder = DiagramBuilder()
        period = period_s
        # Where a wall is too steep in places, the route through its windows (privileged, as
        # the driver: both read the analytic terrain); elsewhere the plain driver, unchanged.
        driver_class = WindowRouteDriver if has_steep_sections(terrain) else EdgeAngleDriver
        driver = builder.AddNamedSystem("edge_angle_driver", driver_class(
            terrain, goal_xy, chassis_body_index, style.driver, period_s=period_s, offset_s=offset_s))
        builder.ExportInput(driver.GetInputPort("body_poses"), "body_poses")
        noise = builder.AddNamedSystem("steering_noise", RandomSource(RandomDistribution.kGaussian, 1, period))
        to_command = builder.AddNamedSystem(
            "noise_to_command", MatrixGain(np.array([[0.0], [style.steering_noise_radps]])))
        adder = builder.AddNamedSystem("add_noise", Adder(2, 2))
        builder.Connect(noise.get_output_port(), to_command.get_input_port())
        builder.Connect(driver.GetOutputPort("command"), adder.get_input_port(0))
        builder.Connect(to_command.get_output_port(), adder.get_input_port(1))
        output = adder.get_output_port()
        if style.reaction_delay_steps > 0:
            delay = builder.AddNamedSystem(
                "reaction_delay", DiscreteTimeDelay(period, style.reaction_delay_steps, 2))
            builder.Connect(output, delay.get_input_port())
            output = delay.get_output_port()
        builder.ExportOutput(output, "raw_command")
        builder.BuildInto(self)
        self._driver = driver
        self._structure = (style.reaction_delay_steps, style.steering_noise_radps)

    def set_style(self, root_context, style: ExpertStyle) -> None:
        """Gives a built expert another demonstration's angles and margin, in `root_context`.

        The reaction delay and the noise level are part of the diagram's structure, so
        they must match the style the expert was built with.
        """
        if (style.reaction_delay_steps, style.steering_noise_radps) != self._structure:
            raise ValueError(f"style needs delay {style.reaction_delay_steps} and noise {style.steering_noise_radps}; "
                             f"this expert was built with {self._structure}")
        self._driver.set_style(self._driver.GetMyMutableContextFromRoot(root_context), style.driver)
