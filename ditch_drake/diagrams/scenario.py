"""Everything one run needs, as one Scenario, in the manner of Drake's `examples/hardware_sim`.

A `Scenario` names the environment (a packaged one, one of an environments file, or one
defined inline in the scenario itself), the task, the seed, the controller (any registered
controller's config, written with its YAML tag, e.g. `controller: !DwaBaselineConfig {...}`),
the episode's limits, Drake's own `MultibodyPlantConfig` and `SimulatorConfig`, and the
control schedule. `load_scenario` reads it with `yaml_load_typed` from a file, a scenario name
within that file, and an override text, so that one parameter changes from the command line:

    ditch-drake replay --scenario my.yaml --override "{controller: !DwaBaselineConfig {}}"

`ditch-drake scenario --print` prints the default Scenario as a template.
"""

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorConfig

from ditch_drake.common.checks import check_finite_positive, check_no_nan
from ditch_drake.common.config_yaml import _check_node, compose_yaml, read_yaml_text
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.seeds import check_seed
from ditch_drake.diagrams.controllers import controller_config_types
from ditch_drake.diagrams.ditch_scene import DefaultPlantConfig, SceneConfig, StartJitter
from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.spec.schedule import ScheduleConfig
from ditch_drake.systems.episode_monitor import EpisodeConfig, EpisodeOutcome
from ditch_drake.world.environments import Environment


def _controller_union():
    return typing.Union[controller_config_types()]  # noqa: UP007  (built from the registry at run time)


@dataclass
class Scenario:
    """One run: where, which task, which controller, and how it is simulated.

    Attributes:
        environment: the environment's name: one of `environments`, else of
            `environments_file`, else a packaged one.
        environments_file: a YAML file of environments in the packaged schema ("": none).
        environments: environments defined inline, each in the schema of one entry of the
            packaged `ditch_drake/world/environments.yaml`.
        task: the environment's task index.
        seed: seeds the start jitter, sensor noise and the expert's style.
        controller: a registered controller's config (`ditch_drake.diagrams.controllers`).
        episode: when the episode ends (time limit, goal radius, rollover and stuck rules).
        plant: Drake's plant settings (a discrete plant: time_step > 0).
        simulator: Drake's simulator settings.
        schedule: the control period and each stage's offset within a step.
        start_jitter: the seeded start-pose perturbation.
    """

    environment: str = "wide"
    environments_file: str = ""
    environments: dict[str, Environment] = field(default_factory=dict)
    task: int = 1
    seed: int = 1
    controller: typing.Any = field(default_factory=LearnedPolicyConfig)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)
    plant: MultibodyPlantConfig = field(default_factory=DefaultPlantConfig)
    simulator: SimulatorConfig = field(default_factory=SimulatorConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    start_jitter: StartJitter = field(default_factory=StartJitter)

    def scene_config(self) -> SceneConfig:
        return SceneConfig(environment=self.environment, task=self.task, environments_file=self.environments_file,
                           environments=self.environments, plant=self.plant, start_jitter=self.start_jitter,
                           episode=self.episode, schedule=self.schedule)

    def rollout_config(self) -> RolloutConfig:
        return RolloutConfig(scene=self.scene_config(), controller=self.controller)


def _schema() -> type:
    """`Scenario` with its controller typed as the union of every controller registered now."""
    Scenario.__dataclass_fields__["controller"].type = _controller_union()
    return Scenario


def _load(schema: type, where: str, defaults: Scenario, text: str, scenario_name: str | None):
    root = compose_yaml(text, where)
    if root is None:
        raise ConfigError(f"{where} is empty; expected a mapping of Scenario's fields"
                          + (f" under {scenario_name!r}" if scenario_name else ""))
    if scenario_name is not None:
        if not isinstance(root, yaml.MappingNode):
            raise ConfigError(f"{where}: expected a mapping of scenario names")
        names = [key.value for key, _ in root.value]
        if scenario_name not in names:
            raise ConfigError(f"{where} has no scenario {scenario_name!r}; expected one of {names}")
        root = {key.value: value for key, value in root.value}[scenario_name]
    _check_node(root, schema, where, "")
    try:
        return yaml_load_typed(schema=schema, data=text, child_name=scenario_name, defaults=defaults)
    except (RuntimeError, ValueError, TypeError, AssertionError) as error:
        message = " ".join(str(error).split())
        if "tag" in message.lower() or "variant" in message.lower():
            message += (f"; expected a controller tag among "
                        f"{['!' + kind.__name__ for kind in controller_config_types()]}")
        raise ConfigError(f"invalid {where}: {message}") from error


def load_scenario(filename: str | Path | None = None, scenario_name: str | None = None,
                  override: str | None = None, defaults: Scenario | None = None) -> Scenario:
    """A Scenario from `defaults` (None: `Scenario()`), then `filename` (the whole file, or the
    entry `scenario_name` of it), then the YAML `override` text (the same schema; only the
    fields it names change).

    Raises:
        ConfigError: an unreadable or empty file, an unknown key, a wrong type, an unknown
            controller tag or a value out of range, naming the file, the key and its line.
    """
    schema = _schema()
    scenario = dataclasses.replace(defaults) if defaults is not None else Scenario()
    if filename:
        path = Path(filename)
        text = read_yaml_text(path, "scenario file")
        scenario = _load(schema, f"scenario file {path}", scenario, text, scenario_name)
    elif scenario_name is not None:
        raise ConfigError(f"scenario name {scenario_name!r} needs a scenario file")
    if override:
        scenario = _load(schema, "--override text", scenario, override, None)
    check_scenario(scenario)
    return scenario


def check_scenario(scenario: Scenario) -> None:
    """Raises ConfigError for values out of range: seed, task, episode, plant, controller."""
    from ditch_drake.diagrams.controllers import check_controller_config
    from ditch_drake.world.environments import get_environment, get_task

    check_seed(scenario.seed, where="scenario seed")
    environment = get_environment(scenario.environment, scenario.environments_file or None, scenario.environments)
    get_task(environment, scenario.task)
    check_finite_positive(scenario.episode.time_limit_s, "scenario episode.time_limit_s")
    check_finite_positive(scenario.episode.goal_radius_m, "scenario episode.goal_radius_m", "metres")
    check_no_nan(scenario.episode, "scenario episode")
    if not scenario.plant.time_step > 0:
        raise ConfigError(f"scenario plant.time_step={scenario.plant.time_step}: expected > 0 (a discrete plant)")
    check_controller_config(scenario.controller)


def scenario_yaml(scenario: Scenario | None = None) -> str:
    """A Scenario as YAML (the default one: a template to copy and edit)."""
    return yaml_dump_typed(scenario if scenario is not None else Scenario(), schema=_schema())


def MakeScenarioDiagram(scenario: Scenario, meshcat=None):
    """The rollout diagram of a scenario, and its scene handles."""
    return MakeRolloutDiagram(scenario.rollout_config(), meshcat=meshcat)


def RunScenario(scenario: Scenario, meshcat=None, progress: str | None = None) -> EpisodeOutcome:
    """Builds and simulates one episode of `scenario` with its simulator settings."""
    diagram, scene = MakeScenarioDiagram(scenario, meshcat)
    simulator = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator, simulator)
    return RunEpisode(simulator, diagram, scene, scenario.seed, progress=progress)

