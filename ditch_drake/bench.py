"""`ditch-drake bench`: every speed and memory figure the project tracks, as one JSON object.

Keys end with their unit (`_ms`, `_s`, `_rtf`, `_mib`). Later work adds its figures
here, keeping the existing keys stable.
"""

import resource
import time

from pydrake.common import RandomGenerator
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig
from ditch_drake.environments import environment_names

TRAVERSAL_S = 30.0


def measure_plant_rtf(environment: str, seed: int = 0, duration_s: float = TRAVERSAL_S) -> dict:
    """Real-time factor of the plant driven by the scripted shallow-angle driver.

    One process, no visualization: `duration_s` of a traversal from the first task's
    seeded start, simulated seconds over wall seconds. Also times the diagram build.
    """
    start = time.perf_counter()
    diagram, _ = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=environment)))
    build_s = time.perf_counter() - start
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetRandomContext(context, RandomGenerator(seed))
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(duration_s)
    wall_s = time.perf_counter() - start
    return {
        f"plant_{environment}_rtf": context.get_time() / wall_s,
        f"scene_build_{environment}_s": build_s,
    }


def run_bench(environments: list[str] | None = None) -> dict:
    """All figures, in a stable key order."""
    figures: dict[str, float] = {}
    for name in environments or environment_names():
        figures.update(measure_plant_rtf(name))
    figures["plant_min_rtf"] = min(value for key, value in figures.items() if key.startswith("plant_"))
    figures["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return figures
