"""One rollout of a spec, in whatever process runs it: the worker side of batch evaluation.

Each worker builds a diagram once per (controller config, environment, task, episode
settings) and reuses it for every seed: building the sine ditch costs seconds, more than some
rollouts. It keeps the `MAX_WORKER_RIGS` most recently used: each holds a scene, a renderer
and a network (about 100 MB). Every rollout starts from a fresh random Context
(`RunEpisode`), so its record depends only on its spec, not on what the worker ran before.
"""

import collections
import importlib
import time
from dataclasses import asdict, replace

from pydrake.systems.analysis import Simulator

from ditch_drake.common.config_yaml import config_from_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import entry_for_config
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import CROSSING_SIDE_SOURCES, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.evaluation.results import RolloutRecord, RolloutSpec
from ditch_drake.learning.checkpoint import checkpoint_digest
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.world.regions import failure_region

# A worker process's built rollout diagrams, most recently used last, by everything they are
# built from. Specs are handed out in order, so a worker meets the same rig for the seeds of
# one task in a row.
MAX_WORKER_RIGS = 4
_WORKER_RIGS: collections.OrderedDict[tuple, tuple] = collections.OrderedDict()


def spec_config(spec: RolloutSpec):
    """The controller config a spec names, as recorded (before its seed's draws).

    Its class is imported by its "module:Class" path, so a controller registered by a
    user's module (imported there) is found in a fresh worker process too.
    """
    module, _, qualified_name = spec.controller_type.partition(":")
    kind = importlib.import_module(module)
    for part in qualified_name.split("."):
        kind = getattr(kind, part)
    return config_from_yaml(kind, spec.controller_config, f"controller config of {spec.controller!r}")


def spec_controller_config(spec: RolloutSpec):
    """The controller config a spec names, as the episode of its seed builds it."""
    config = spec_config(spec)
    return entry_for_config(config).for_seed(config, spec.seed)


def rollout_config(spec: RolloutSpec) -> RolloutConfig:
    """The diagram configuration of a spec."""
    scene = SceneConfig(environment=spec.environment, task=spec.task, environments_file=spec.environments_file,
                        episode=replace(EpisodeConfig(), time_limit_s=spec.time_limit_s,
                                        goal_radius_m=spec.goal_radius_m))
    return RolloutConfig(scene=scene, controller=spec_controller_config(spec))


def _rig(spec: RolloutSpec):
    config = rollout_config(spec)
    # The config as this seed builds it: the expert's style (drawn from the seed) is part of
    # its diagram's structure; every other controller's is the same for all seeds.
    key = (spec.controller_type, repr(config.controller), spec.environment, spec.environments_file, spec.task,
           spec.time_limit_s, spec.goal_radius_m)
    if key in _WORKER_RIGS:
        _WORKER_RIGS.move_to_end(key)
    else:
        while len(_WORKER_RIGS) >= MAX_WORKER_RIGS:
            _WORKER_RIGS.popitem(last=False)
        diagram, scene = MakeRolloutDiagram(config)
        _WORKER_RIGS[key] = (diagram, scene, Simulator(diagram))
    return _WORKER_RIGS[key]


def run_rollout(spec: RolloutSpec) -> RolloutRecord:
    """Runs one rollout; an exception becomes a record with status "error"."""
    common = spec_fields(spec)
    start = time.perf_counter()
    side_source = ""
    try:
        digest = checkpoint_digest(spec.checkpoint)
        if digest != spec.checkpoint_sha256:
            raise ConfigError(f"checkpoint {spec.checkpoint!r} has digest {digest}, not {spec.checkpoint_sha256} as "
                              "when the evaluation started: the file changed during the run")
        diagram, scene, simulator = _rig(spec)
        side_source = crossing_side_source(diagram)
        RunEpisode(simulator, diagram, scene, spec.seed)
        fields = outcome_fields(diagram, scene, simulator.get_context())
    except Exception as error:
        return error_record(spec, f"{type(error).__name__}: {error}", time.perf_counter() - start, side_source)
    return RolloutRecord(**common, **fields, wall_s=time.perf_counter() - start, crossing_side_source=side_source)


def crossing_side_source(diagram) -> str:
    """Where a rollout diagram's clone is told its crossing side: "perceived" or "oracle" by
    the block it holds ("perceived_crossing_side", "oracle_crossing_side"), else ""."""
    for source in CROSSING_SIDE_SOURCES:
        if diagram.HasSubsystemNamed(f"{source}_crossing_side"):
            return source
    return ""


def spec_privileged(spec: RolloutSpec) -> list[str]:
    """What the controller of `spec` declares it reads beyond its sensors, its pose and the goal
    (`ControllerEntry.privileged_inputs`); [] for a config that does not load (its rollout's
    error record says why)."""
    try:
        config = spec_controller_config(spec)
        return list(entry_for_config(config).privileged_inputs(config))
    except (ConfigError, ImportError, AttributeError):
        return []


def outcome_fields(diagram, scene, root_context) -> dict:
    """The record fields that say what an episode did, read from a rollout diagram's Context:
    the episode monitor's outcome, where it ended relative to the ditch ("" on success), the
    "halt_counter"'s halts by region (`RolloutRecord`'s status .. halts_by_region), and the
    instruments' counts where the diagram has them (side_*, the shared controller's handovers)."""
    outcome = scene.monitor.outcome(scene.monitor.GetMyContextFromRoot(root_context))
    counter = diagram.GetSubsystemByName("halt_counter")
    region = "" if outcome.success else failure_region(scene.terrain, scene.task.start[:2], outcome.final_xy)
    return dict(
        status=outcome.status, success=outcome.success, time_s=outcome.time_s, path_length_m=outcome.path_length_m,
        peak_abs_roll_deg=outcome.peak_abs_roll_deg, peak_abs_pitch_deg=outcome.peak_abs_pitch_deg,
        peak_tilt_deg=outcome.peak_tilt_deg, min_stability_margin_deg=outcome.min_stability_margin_deg,
        final_x_m=float(outcome.final_xy[0]), final_y_m=float(outcome.final_xy[1]), failure_region=region,
        halts_by_region=counter.halts_by_region(counter.GetMyContextFromRoot(root_context)),
        **side_agreement_fields(diagram, root_context), **shared_control_fields(diagram, root_context))


def side_agreement_fields(diagram, root_context) -> dict:
    """The "crossing_side_agreement"'s counts (`RolloutRecord`'s side_* fields), where the
    diagram has one (a perceived crossing side), else none."""
    if not diagram.HasSubsystemNamed("crossing_side_agreement"):
        return {}
    agreement = diagram.GetSubsystemByName("crossing_side_agreement")
    return agreement.summary(agreement.GetMyContextFromRoot(root_context))


def shared_control_fields(diagram, root_context) -> dict:
    """The shared controller's handovers (`RolloutRecord`'s handover_fraction, switches and
    handover_regions), where the diagram has its "shared_control" gate and "handover_counter",
    else none."""
    if not (diagram.HasSubsystemNamed("shared_control") and diagram.HasSubsystemNamed("handover_counter")):
        return {}
    gate = diagram.GetSubsystemByName("shared_control")
    counter = diagram.GetSubsystemByName("handover_counter")
    switches = gate.GetOutputPort("switches").Eval(gate.GetMyContextFromRoot(root_context))[0]
    return {**counter.summary(counter.GetMyContextFromRoot(root_context)), "switches": round(float(switches))}


def initialize_worker() -> None:
    # Each worker is one of `workers` processes sharing the cores: one thread each.
    import torch

    torch.set_num_threads(1)


def spec_fields(spec: RolloutSpec) -> dict:
    """The record fields that repeat the spec, and what its controller declares privileged."""
    return {"key": spec.key, **asdict(spec), "privileged": spec_privileged(spec)}


def error_record(spec: RolloutSpec, message: str, wall_s: float = float("nan"),
                 crossing_side_source: str = "") -> RolloutRecord:
    """The record of a rollout that raised; `crossing_side_source` where its diagram was built."""
    nan = float("nan")
    return RolloutRecord(**spec_fields(spec), status="error", success=False, time_s=nan,
                         path_length_m=nan, peak_abs_roll_deg=nan, peak_abs_pitch_deg=nan, peak_tilt_deg=nan,
                         min_stability_margin_deg=nan, final_x_m=nan, final_y_m=nan, failure_region="",
                         wall_s=wall_s, error=message, crossing_side_source=crossing_side_source)
