"""A scene whose controller sits outside the diagram: it reads an observation and sets an action label.

What a Gymnasium environment (`ditch_drake.gym`) or any other agent loop steps: the scene,
the observation blocks the learned policy reads, and in the policy's place an
`ActionLabelInput` on the exported `action` port, with the stacks packed into one
exported `observation` dictionary (`ObservationDict`), and the crossing side a clone trained
in one side's frame is told (`AddCrossingSide`: perceived from the lidar unless the scenario's
learned controller asks for the oracle), on the exported `crossing_side` port.
"""

from pydrake.geometry import Meshcat
from pydrake.systems.framework import Diagram, DiagramBuilder

from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene
from ditch_drake.diagrams.observation import AddObservation, ConnectObservation, ObservationConfig
from ditch_drake.diagrams.rollout import AddCrossingSide, AddHaltCounter, LearnedPolicyConfig
from ditch_drake.diagrams.scenario import Scenario
from ditch_drake.systems.action_label_input import ActionLabelInput
from ditch_drake.systems.observation_dict import ObservationDict


def crossing_side_source(scenario: Scenario) -> str:
    """Where the exported crossing side comes from: the scenario's learned controller's
    `crossing_side`, else "perceived"."""
    if isinstance(scenario.controller, LearnedPolicyConfig):
        return scenario.controller.crossing_side
    return "perceived"


def observation_config(scenario: Scenario) -> ObservationConfig:
    """The perception blocks' settings: the scenario's learned-policy observation, else the defaults
    (those the demonstrations and the shipped models were made with)."""
    if isinstance(scenario.controller, LearnedPolicyConfig):
        return scenario.controller.observation
    return ObservationConfig()


def MakeExternalAgentDiagram(scenario: Scenario, meshcat: Meshcat | None = None) -> tuple[Diagram, DitchScene]:
    """The scene of `scenario` with its observation blocks, driven by the label on the exported
    `action` input port, and the exported `observation` output (see `ObservationDict`) and
    `crossing_side` output (`AddCrossingSide`: what `AddLearnedPolicy` tells a side-told clone).

    The blocks are added in the order `AddController` adds the learned policy's (scene,
    observation, the block in the policy's place, the halt counter), so a seed draws the
    same start jitter and sensor noise as in a learned rollout. The scenario's controller only
    lends its observation settings.
    """
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, scenario.scene_config(), meshcat)
    observation = AddObservation(builder, scene, observation_config(scenario))
    action = builder.AddNamedSystem("action_label_input", ActionLabelInput())
    builder.Connect(action.GetOutputPort("command"), scene.drive.GetInputPort("command"))
    AddHaltCounter(builder, scene, action.GetOutputPort("command"))
    packer = builder.AddNamedSystem("observation_dict", ObservationDict())
    ConnectObservation(builder, observation, packer)
    side = AddCrossingSide(builder, scene, observation, crossing_side_source(scenario))
    builder.ExportInput(action.GetInputPort("action"), "action")
    builder.ExportOutput(packer.GetOutputPort("observation"), "observation")
    builder.ExportOutput(side.GetOutputPort("crossing_side"), "crossing_side")
    diagram = builder.Build()
    diagram.set_name(f"external_agent_{scenario.environment}_task{scenario.task}")
    return diagram, scene
