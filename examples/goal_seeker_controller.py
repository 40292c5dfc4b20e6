"""Your own controller: a config class, a LeafSystem with a `command` output, one registry line.

This one steers straight at the goal, whatever lies between: a ditch whose walls are too
steep for a head-on approach rolls it over, which makes it a useful lower bound. Import this
module and every command that runs a controller knows `goal_seeker`:

    python examples/goal_seeker_controller.py         # one rollout in the wide ditch

and from Python:

    import goal_seeker_controller  # registers it
    from ditch_drake.evaluation.batch import evaluate, make_specs
    evaluate(make_specs(goal_seeker_controller.GoalSeekerConfig(), "", "wide", rollouts=2), "seeker.jsonl")

(docs/tutorials/your_controller.md walks through it.)
"""

from dataclasses import dataclass

from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ditch_drake.diagrams.controllers import ControllerSite, register_controller
from ditch_drake.systems.goal import distance_bearing


@dataclass
class GoalSeekerConfig:
    """Attributes:
    speed_mps: forward speed (m/s).
    heading_gain: turn rate per radian of bearing to the goal (1/s).
    max_turn_radps: the largest turn rate (rad/s).
    """

    speed_mps: float = 1.0
    heading_gain: float = 1.0
    max_turn_radps: float = 0.85


class GoalSeeker(LeafSystem):
    """Turns toward the goal at the control rate.

    .. pydrake_system::

        name: GoalSeeker
        input_ports:
        - body_poses
        output_ports:
        - command

    Ports:
        body_poses: the plant's body poses X_WB (the registry connects it by name).
        command: [v m/s, w rad/s], held between control ticks.
    """

    def __init__(self, config: GoalSeekerConfig, site: ControllerSite):
        super().__init__()
        self._config = config
        self._goal_xy = [float(value) for value in site.goal_xy[:2]]
        self._chassis_index = int(site.chassis_body_index)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        command = self.DeclareDiscreteState(2)
        self.DeclarePeriodicDiscreteUpdateEvent(site.schedule.control_period_s, site.schedule.controller_offset_s,
                                                self._update)
        self.DeclareStateOutputPort("command", command)

    def _update(self, context, state) -> None:
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        _, bearing = distance_bearing(X_WB, self._goal_xy)
        limit = self._config.max_turn_radps
        turn = max(-limit, min(limit, self._config.heading_gain * bearing))
        state.get_mutable_vector().SetFromVector([self._config.speed_mps, turn])


register_controller("goal_seeker", GoalSeekerConfig, GoalSeeker,
                    "steers straight at the goal, whatever lies between (an example controller)")

if __name__ == "__main__":
    from ditch_drake.diagrams.scenario import RunScenario, Scenario

    outcome = RunScenario(Scenario(environment="wide", task=0, controller=GoalSeekerConfig()))
    print(f"goal_seeker in wide, task 0: {outcome.status} after {outcome.time_s:.1f} s, "
          f"peak tilt {outcome.peak_tilt_deg:.0f} deg")
