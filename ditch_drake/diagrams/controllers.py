"""The controllers a rollout can be driven by, by name: the one list that the command line,
batch evaluation and the demo read.

This module imports nothing heavy, so that `ditch-drake --help` lists the names at once; the
configs themselves are built by `controller_config`.
"""

CONTROLLERS: dict[str, str] = {
    "learned": "the behavioural-cloning policy of a checkpoint (--checkpoint; default: the environment's shipped model)",
    "dwa": "the move_base-style baseline: slope costmap, Dijkstra global plan, DWA local planner",
    "expert": "the scripted shallow-angle expert that made the demonstrations (its style drawn from the seed)",
    "edge_angle": "the scripted shallow-angle driver with fixed angles (the physics reference)",
    "head_on": "the scripted driver straight into the ditch, perpendicular to its edge (rolls over)",
}


def controller_config(name: str, checkpoint: str = "", seed: int = 0):
    """The `ControllerConfig` of a controller name.

    Args:
        name: one of `CONTROLLERS`.
        checkpoint: the learned policy's shipped name or file (other controllers ignore it).
        seed: the episode's seed; the expert draws its style from it, so that a replay and an
            evaluation record of the same seed drive alike.

    Raises:
        ConfigError: an unknown name, naming the known ones.
    """
    from ditch_drake.diagrams.rollout import DwaBaselineConfig, ExpertConfig, LearnedPolicyConfig
    from ditch_drake.errors import ConfigError
    from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig

    configs = {
        "learned": lambda: LearnedPolicyConfig(checkpoint=checkpoint),
        "dwa": DwaBaselineConfig,
        "expert": lambda: ExpertConfig(style_seed=seed),
        "edge_angle": EdgeAngleDriverConfig,
        "head_on": lambda: EdgeAngleDriverConfig(wall_angle_deg=90.0, climb_angle_deg=None),
    }
    if name not in configs:
        raise ConfigError(f"unknown controller {name!r}; expected one of {list(CONTROLLERS)}")
    return configs[name]()
