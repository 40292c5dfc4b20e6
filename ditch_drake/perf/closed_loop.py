"""The closed loop the speed figures time: a scene with every perception block under a fixed
command, and one seeded run of a diagram timed apart from its first control step."""

import time

from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder

from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.observation import AddObservation
from ditch_drake.diagrams.rollout import AddController, ConstantCommandConfig, StartEpisode

TRAVERSAL_S = 30.0
# The first control step: every stage's tick (offsets up to 4 ms) has run once.
WARMUP_S = 0.005
# Fixed-command episodes per environment in `measure_closed_loops` (its figures are medians).
CLOSED_LOOP_EPISODES = 7


def MakeClosedLoopDiagram(scene_config: SceneConfig, command: ConstantCommandConfig) -> Diagram:
    """The scene of `scene_config` with every observation block running (lidar, normal image, IMU,
    goal, stacker; nothing reads their stacks) and `command` driving."""
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, scene_config)
    AddObservation(builder, scene)
    AddController(builder, scene, command)
    return builder.Build()


def timed_run(diagram, seed: int, duration_s: float, warmup_s: float = 0.0) -> tuple[float, float, float]:
    """One seeded run (which may end early): wall seconds and simulated seconds after
    `warmup_s`, and the wall seconds of the untimed first `warmup_s`.

    An episode's start (`StartEpisode`, untimed), then two timed `AdvanceTo`s: the warm-up and
    the measurement are timed apart, which `RunEpisode`'s one advance cannot do.
    """
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    StartEpisode(simulator, diagram, seed)
    start = time.perf_counter()
    simulator.AdvanceTo(warmup_s)
    warmup_wall_s = time.perf_counter() - start
    start_time = context.get_time()
    start = time.perf_counter()
    simulator.AdvanceTo(duration_s)
    return time.perf_counter() - start, context.get_time() - start_time, warmup_wall_s
