"""Collecting demonstrations with the scripted expert, resumably and in parallel.

Demonstration i is episode i of a dataset store (`ditch_drake.demos.store`), written
atomically the moment it ends: by its worker in the local pool, or, on Ray
(`CollectConfig.backend`), by this process, to which each task returns its demonstration (a
worker on another node cannot write into this machine's folder). Ctrl-C or SIGTERM stops the
workers at once (`ditch_drake.common.parallel`, `ditch_drake.common.ray_tasks`) and the report
says how many were kept, so the same command run again records only the missing ones.
"""

import collections
import dataclasses
import time
from concurrent.futures import as_completed
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, System
from tqdm import tqdm

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import (
    WorkerPool,
    check_workers,
    deferred_interrupts,
    interrupt_exit_code,
    terminate_as_interrupt,
    worker_count,
)
from ditch_drake.common.ray_tasks import check_backend, failure_message, raised_by_task, run_ray_tasks
from ditch_drake.common.seeds import check_seed
from ditch_drake.demos.dataset import Demonstration, demonstration_paths, log_to_arrays, standard_metadata
from ditch_drake.demos.store import EPISODE_FILE, DatasetError, DatasetStore, is_store
from ditch_drake.diagrams.controllers import get_controller
from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene, SceneConfig
from ditch_drake.diagrams.observation import AddObservation, ConnectObservation, Observation, ObservationConfig
from ditch_drake.diagrams.rollout import AddLearnedPolicy, ExpertConfig, RunEpisode
from ditch_drake.diagrams.shared_controller import AddSharedControl, SharedControlControllerConfig
from ditch_drake.learning.checkpoint import (
    checkpoint_digest,
    environment_model,
    load_checkpoint,
    resolve_checkpoint_path,
)
from ditch_drake.learning.inference import load_policy
from ditch_drake.spec import robot
from ditch_drake.systems.demo_recorder import DemoRecorder
from ditch_drake.systems.driver_recorder import DriverRecorder
from ditch_drake.systems.expert import ExpertVariation, draw_expert_style
from ditch_drake.systems.meshcat_teleop import MeshcatTeleop
from ditch_drake.systems.shared_control import FALLBACK, SharedControl
from ditch_drake.systems.teleop import ActionQuantizer
from ditch_drake.world.environments import get_environment

ATTEMPTS_PER_DEMO = 5

LABELLER_VARIATION = ExpertVariation(wall_angle_deg=[20.0, 20.0], climb_angle_deg=[35.0, 35.0],
                                     approach_margin_m=[2.5, 2.5], reaction_delay_steps=0, steering_noise_radps=0.0)
"""The expert as a DAgger labeller: the middle of the demonstrators' style, with no delay
and no noise, so that a label is the expert's answer to exactly the recorded observation."""

SHARED_LABELS = ("executed", "expert")
"""What a shared collection records as a step's label (`CollectConfig.shared_labels`)."""

ROLLOVER_TRIM_S = 1.0
"""Dropped from the end of a learner's rollout that rolled over: by then the chassis is
past saving, and no command is the right answer to those observations."""


@dataclass
class CollectConfig:
    """What `collect` gathers.

    Attributes:
        environment: environment name.
        demos: how many successful demonstrations, spread over the tasks (demo i
            drives task i mod the number of tasks).
        seed: demo i's first attempt uses seed + i; a failed attempt k uses
            seed + i + 1000 k (failed demonstrations are not kept).
        out: the dataset folder (`ditch_drake.demos.store`); demonstration i is its episode i.
        workers: processes (None: one per core; 0: in this process). With Ray: at most this
            many demonstrations at once (None or 0: as many as the cluster takes).
        observation: perception settings.
        variation: the expert's per-demonstration variation.
        learner: None records the expert's demonstrations (successes only). A checkpoint
            (a shipped model's name or a path) makes this a DAgger round: the learned
            policy drives, the expert only labels what it sees (use `LABELLER_VARIATION`),
            and every rollout is kept, one per seed, whatever its outcome (a rollover's
            last `ROLLOVER_TRIM_S` dropped).
        environments_file: a YAML file of environments that `environment` may name ("": packaged).
        environments: several environments (of `environments_file` or packaged) instead of
            `environment`: demonstration i drives the i-th (environment, task) pair, in order
            environment by environment, wrapping round (`slot_pairs`).
        backend: "local" (a process pool on this machine) or "ray" (a Ray cluster; the
            optional `ray` extra): each demonstration a Ray task, returned to this process,
            which writes it into `out`. A task whose worker dies is retried once by Ray, then
            its slot is reported unfilled. The environments file and the learner's checkpoint
            must be at the same path on every node (a shared filesystem); give the
            checkpoint as an absolute path (a relative one is looked up in each worker's
            folder, which on a local Ray is this process's).
        address: the Ray cluster's address (None or "local": start Ray on this machine).
        shared: None, or the shared controller (`SharedControlControllerConfig`: the gated
            policy's checkpoint, the gate's thresholds, the fallback, "expert" or "mppi") that
            drives every rollout, kept one per seed whatever its outcome, as a DAgger round's
            (a rollover's last `ROLLOVER_TRIM_S` dropped). Each step is stored with its driver:
            `intervention` is true where the fallback drove. Not with `learner`.
        shared_labels: with `shared`, the label stored for each step, one of `SHARED_LABELS`:
            "executed" (the label the robot executed: the policy's where it drove, the
            fallback's where it took over; what Sirius and ThriftyDAgger aggregate) or
            "expert" (the expert fallback's label at every step, as a DAgger labeller gives it
            for the learner's states; needs fallback "expert").
    """

    environment: str = "wide"
    demos: int = 40
    seed: int = 0
    out: str = "data/demos/wide"
    workers: int | None = None
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    variation: ExpertVariation = field(default_factory=ExpertVariation)
    learner: str | None = None
    environments_file: str = ""
    environments: list[str] = field(default_factory=list)
    backend: str = "local"
    address: str | None = None
    shared: SharedControlControllerConfig | None = None
    shared_labels: str = "executed"

    def expert_variation(self) -> ExpertVariation:
        """The variation the expert's style is drawn from: the shared fallback's, or `variation`."""
        return self.shared.expert.variation if self.shared is not None else self.variation


@dataclass
class DemonstrationRig:
    """A scene with perception, the expert through the action quantizer, and the recorder."""

    diagram: Diagram
    scene: DitchScene
    observation: Observation
    source: System | None  # The raw-command source: an `ExpertDriver`, a `MeshcatTeleop` (None: MPPI).
    recorder: DemoRecorder
    gate: SharedControl | None = None  # A shared rig's gate, and who drove each step:
    drivers: DriverRecorder | None = None


def MakeDemonstrationDiagram(scene_config: SceneConfig, style_seed: int,
                             observation_config: ObservationConfig | None = None,
                             variation: ExpertVariation | None = None, meshcat: Meshcat | None = None,
                             person_drives: bool = False, learner: str | None = None,
                             shared: SharedControlControllerConfig | None = None,
                             shared_labels: str = "executed") -> DemonstrationRig:
    """The expert (or, with `person_drives`, a person through `meshcat`) drives through
    `ActionQuantizer`, whose label the recorder stores.

    With `learner` (a checkpoint name or path) the learned policy drives instead, on the
    same observation blocks the recorder reads, and the expert's quantized command is only
    recorded: the labels of a DAgger round.

    With `shared` the shared controller drives (`_add_shared`): its policy on the recorder's
    observation blocks, its gate's choice executed and recorded, and who drove each step.
    """
    if person_drives and meshcat is None:
        raise ConfigError("a person drives through meshcat: pass a Meshcat")
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, scene_config, meshcat)
    schedule = scene.schedule
    observation = AddObservation(builder, scene, observation_config)
    if shared is not None:
        return _add_shared(builder, scene, observation, shared, style_seed, shared_labels, meshcat)
    if person_drives:
        source = builder.AddNamedSystem("meshcat_teleop", MeshcatTeleop(
            meshcat, period_s=schedule.control_period_s, offset_s=schedule.controller_offset_s))
        quantizer = builder.AddNamedSystem("action_quantizer", ActionQuantizer())
        builder.Connect(source.GetOutputPort("raw_command"), quantizer.GetInputPort("raw_command"))
    else:
        # The registry's expert: `ExpertDriver` ("expert") through the action quantizer.
        command = get_controller("expert").add(builder, scene, ExpertConfig(
            style_seed=style_seed, variation=variation or ExpertVariation()))
        quantizer = command.get_system()
        source = builder.GetSubsystemByName("expert")
    if learner is None:
        builder.Connect(quantizer.GetOutputPort("command"), scene.drive.GetInputPort("command"))
    else:
        policy = AddLearnedPolicy(builder, scene, observation, learner)
        builder.Connect(policy.GetOutputPort("command"), scene.drive.GetInputPort("command"))
    recorder = _add_recorder(builder, scene, observation, quantizer.GetOutputPort("label"),
                             source.GetOutputPort("raw_command"))
    diagram = builder.Build()
    diagram.set_name(f"demonstration_{scene_config.environment}")
    return DemonstrationRig(diagram, scene, observation, source, recorder)


def _add_recorder(builder: DiagramBuilder, scene: DitchScene, observation: Observation, label, raw_command
                  ) -> DemoRecorder:
    """The "demo_recorder" on `observation`, storing the `label` and `raw_command` ports' values."""
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    schedule = scene.schedule
    recorder = builder.AddNamedSystem("demo_recorder", DemoRecorder(
        chassis.index(), period_s=schedule.control_period_s, offset_s=schedule.recorder_offset_s))
    ConnectObservation(builder, observation, recorder)
    builder.Connect(label, recorder.GetInputPort("label"))
    builder.Connect(raw_command, recorder.GetInputPort("raw_command"))
    builder.Connect(scene.plant.get_body_poses_output_port(), recorder.GetInputPort("body_poses"))
    return recorder


def check_shared_collection(shared: SharedControlControllerConfig, shared_labels: str,
                            meshcat: Meshcat | None = None) -> None:
    """Raises ConfigError naming the first bad value of a shared collection's settings."""
    shared.validate(meshcat)
    if shared_labels not in SHARED_LABELS:
        raise ConfigError(f"shared_labels {shared_labels!r}: expected one of {list(SHARED_LABELS)}")
    if shared_labels == "expert" and shared.gate.fallback != "expert":
        raise ConfigError(f"shared_labels 'expert' with fallback {shared.gate.fallback!r}: the expert's labels come "
                          "from the expert fallback; expected fallback 'expert' or shared_labels 'executed'")


def _add_shared(builder: DiagramBuilder, scene: DitchScene, observation: Observation,
                shared: SharedControlControllerConfig, style_seed: int, shared_labels: str,
                meshcat: Meshcat | None) -> DemonstrationRig:
    """The rest of a shared rig: the gate's command drives; the recorder stores its executed
    label ("executed") or the expert fallback's ("expert") with the executed command, and a
    "driver_recorder" who drove each step (the demonstration's `intervention`)."""
    check_shared_collection(shared, shared_labels, meshcat)
    if shared.gate.fallback == "expert" and shared.expert.style_seed is None:
        shared = dataclasses.replace(shared, expert=dataclasses.replace(shared.expert, style_seed=style_seed))
    gate = AddSharedControl(builder, scene, shared, observation, meshcat)
    command = gate.GetOutputPort("command")
    builder.Connect(command, scene.drive.GetInputPort("command"))
    if shared_labels == "expert":
        label = builder.GetSubsystemByName("action_quantizer").GetOutputPort("label")
    else:  # The policy's commands are the table's own and the fallbacks' quantized: snapping leaves them as they are.
        label = builder.AddNamedSystem("executed_label", ActionQuantizer()).GetOutputPort("label")
        builder.Connect(command, label.get_system().GetInputPort("raw_command"))
    recorder = _add_recorder(builder, scene, observation, label, command)
    schedule = scene.schedule
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    drivers = builder.AddNamedSystem("driver_recorder", DriverRecorder(
        chassis.index(), period_s=schedule.control_period_s, offset_s=schedule.recorder_offset_s))
    builder.Connect(gate.GetOutputPort("who_drives"), drivers.GetInputPort("who_drives"))
    builder.Connect(scene.plant.get_body_poses_output_port(), drivers.GetInputPort("body_poses"))
    source = next((builder.GetSubsystemByName(name) for name in ("expert", "meshcat_teleop")
                   if builder.HasSubsystemNamed(name)), None)
    diagram = builder.Build()
    diagram.set_name(f"shared_demonstration_{scene.environment_name}")
    return DemonstrationRig(diagram, scene, observation, source, recorder, gate, drivers)


def _run_and_record(rig: DemonstrationRig, environment: str, task: int, seed: int, realtime_rate: float = 0.0,
                    **metadata) -> Demonstration:
    """Runs one seeded episode on `rig` and packs the recorder's log with its metadata.

    An `expert_style` in `metadata` is set on the rig's expert before the run.
    """
    simulator = Simulator(rig.diagram)
    simulator.set_target_realtime_rate(realtime_rate)
    style = metadata.get("expert_style")

    def set_style(root_context) -> None:
        rig.source.set_style(root_context, style)

    outcome = RunEpisode(simulator, rig.diagram, rig.scene, seed, before_start=None if style is None else set_style)
    if style is not None:
        metadata["expert_style"] = asdict(style)
    root = simulator.get_context()
    arrays = log_to_arrays(rig.recorder.log(rig.recorder.GetMyContextFromRoot(root)))
    if rig.drivers is not None:
        drivers = rig.drivers.log(rig.drivers.GetMyContextFromRoot(root)).drivers()
        if len(drivers) != len(arrays["label"]):  # Both tick at the recorder's offset.
            raise RuntimeError(f"{len(drivers)} drivers recorded for {len(arrays['label'])} steps")
        arrays["intervention"] = drivers == FALLBACK
        switches = rig.gate.GetOutputPort("switches").Eval(rig.gate.GetMyContextFromRoot(root))[0]
        metadata["intervened_steps"] = int(arrays["intervention"].sum())
        metadata["switches"] = int(switches)
    task_info = {"index": task, "name": rig.scene.task.name, "start": rig.scene.task.start, "goal": rig.scene.task.goal}
    return Demonstration(arrays, standard_metadata(
        environment=environment, task=task_info, seed=seed, outcome=asdict(outcome),
        control_period_s=rig.scene.schedule.control_period_s, **metadata))


def record_demonstration(environment: str, task: int, seed: int,
                         observation_config: ObservationConfig | None = None,
                         variation: ExpertVariation | None = None,
                         rig: DemonstrationRig | None = None, learner: str | None = None) -> Demonstration:
    """Runs one expert episode; returns the demonstration, successful or not (see metadata).

    `rig` reuses a diagram built for this environment and task (its expert's reaction
    delay must match the seed's style, its learner `learner`); None builds one. With
    `learner` the learned policy drives and the expert labels (`MakeDemonstrationDiagram`).
    """
    if rig is None:
        rig = MakeDemonstrationDiagram(SceneConfig(environment=environment, task=task), seed,
                                       observation_config, variation, learner=learner)
    driver = {} if learner is None else {"driver": "learner (DAgger; the expert labels)", "learner": learner,
                                         "learner_sha256": checkpoint_digest(learner)}
    return _run_and_record(rig, environment, task, seed, expert_style=draw_expert_style(seed, variation), **driver)


def with_labelling_expert(shared: SharedControlControllerConfig, lead_in: bool = False
                          ) -> SharedControlControllerConfig:
    """`shared` with its expert fallback taking over as DAgger's labeller labels
    (`LABELLER_VARIATION`: the demonstrators' middle style, no delay, no noise), as a shared
    collection records it."""
    variation = replace(LABELLER_VARIATION, lead_in=lead_in)
    return replace(shared, expert=replace(shared.expert, variation=variation))


def record_shared_demonstration(environment: str, task: int, seed: int, shared: SharedControlControllerConfig,
                                shared_labels: str = "executed", observation_config: ObservationConfig | None = None,
                                rig: DemonstrationRig | None = None, environments_file: str = "",
                                meshcat: Meshcat | None = None, realtime_rate: float = 0.0) -> Demonstration:
    """Runs one episode of the shared controller; returns it with each step's driver in its
    `intervention` array (true where the fallback drove) and the gate in its metadata.

    `rig` reuses a diagram built by `MakeDemonstrationDiagram` with the same `shared` (its
    expert fallback's reaction delay that of the seed's style); None builds one (on `meshcat`,
    which a "teleop" fallback needs).
    """
    if rig is None:
        rig = MakeDemonstrationDiagram(SceneConfig(environment=environment, task=task,
                                                   environments_file=environments_file),
                                       seed, observation_config, meshcat=meshcat, shared=shared,
                                       shared_labels=shared_labels)
    fallback = shared.gate.fallback
    policy = shared.policy.checkpoint or environment_model(get_environment(
        environment, environments_file or None).based_on or environment)
    metadata = {"driver": f"shared: the policy gated by its {shared.gate.signal}, fallback {fallback}",
                "learner": policy, "learner_sha256": checkpoint_digest(policy),
                "shared_gate": asdict(shared.gate), "shared_labels": shared_labels}
    if fallback == "expert":
        metadata["expert_style"] = draw_expert_style(seed, shared.expert.variation)
    return _run_and_record(rig, environment, task, seed, realtime_rate, **metadata)


def record_person_demonstration(environment: str, task: int, meshcat: Meshcat, seed: int = 0,
                                realtime_rate: float = 1.0, environments_file: str = "",
                                shared: SharedControlControllerConfig | None = None) -> Demonstration:
    """A person steers with the arrow keys or a gamepad in the meshcat page, in real time.

    With `shared` (its fallback "teleop") the gated policy drives and the person steers only
    while the gate hands over: the page marks those steps (`DriverIndicator`), and the
    demonstration stores them as interventions (`record_shared_demonstration`).
    """
    if shared is not None:
        return record_shared_demonstration(environment, task, seed, shared, environments_file=environments_file,
                                           meshcat=meshcat, realtime_rate=realtime_rate)
    rig = MakeDemonstrationDiagram(SceneConfig(environment=environment, task=task, environments_file=environments_file),
                                   seed, meshcat=meshcat, person_drives=True)
    return _run_and_record(rig, environment, task, seed, realtime_rate, driver="person (meshcat teleop)")


# A collection worker's built rigs, most recently used last, reused across its
# demonstrations: building a scene costs up to a second or more, about a demonstration's
# simulation. Keyed by everything the diagram is built from; a rig holds no episode state
# (each demonstration simulates in a fresh Context). A collection over many environments
# keeps only the last few (each holds a scene, a renderer and perhaps a network).
MAX_WORKER_RIGS = 4
_WORKER_RIGS: collections.OrderedDict[tuple, DemonstrationRig] = collections.OrderedDict()
# Demonstrations a pool's worker processes run before a fresh pool replaces them: a worker's
# memory grows with every diagram it has built and dropped (`ditch_drake.evaluation.batch`).
DEMOS_PER_WORKER = 40


def slot_pairs(config: CollectConfig) -> list[tuple[str, int]]:
    """The (environment, task) pairs demonstration i drives the (i mod count)-th of."""
    names = config.environments or [config.environment]
    return [(name, task) for name in names
            for task in range(len(get_environment(name, config.environments_file or None).tasks))]


def _worker_rig(config: CollectConfig, environment: str, task: int, reaction_delay_steps: int) -> DemonstrationRig:
    key = (environment, task, reaction_delay_steps, repr(config.observation), repr(config.variation),
           config.learner, config.environments_file, repr(config.shared), config.shared_labels)
    if key in _WORKER_RIGS:
        _WORKER_RIGS.move_to_end(key)
        return _WORKER_RIGS[key]
    while len(_WORKER_RIGS) >= MAX_WORKER_RIGS:
        _WORKER_RIGS.popitem(last=False)
    # Any seed with this delay builds the same diagram; each demonstration sets its own style.
    variation = config.expert_variation()
    style_seed = next(seed for seed in range(10_000)
                      if draw_expert_style(seed, variation).reaction_delay_steps == reaction_delay_steps)
    _WORKER_RIGS[key] = MakeDemonstrationDiagram(SceneConfig(environment=environment, task=task,
                                                             environments_file=config.environments_file),
                                                 style_seed, config.observation, config.variation,
                                                 learner=config.learner, shared=config.shared,
                                                 shared_labels=config.shared_labels)
    return _WORKER_RIGS[key]


def trim_rollover(demonstration: Demonstration) -> Demonstration:
    """The demonstration without its last `ROLLOVER_TRIM_S` if it ended in a rollover."""
    if demonstration.metadata["outcome"]["status"] != "rolled_over":
        return demonstration
    keep = max(1, len(demonstration) - round(ROLLOVER_TRIM_S / robot.CONTROL_PERIOD_S))
    arrays = {name: values[:keep] for name, values in demonstration.arrays.items()}
    return Demonstration(arrays, {**demonstration.metadata, "trimmed_steps": len(demonstration) - keep})


def _record_slot(config: CollectConfig, index: int) -> tuple[dict, Demonstration | None]:
    """Records demonstration `index`: its slot's result (seed, steps, failed attempts, status;
    seed None for an unfilled slot) and the demonstration to keep (None: none succeeded).
    A Ray task's whole work: the demonstration comes back to the process that writes the store."""
    pairs = slot_pairs(config)
    environment, task = pairs[index % len(pairs)]
    if config.learner is not None or config.shared is not None:
        seed = config.seed + index
        delay = draw_expert_style(seed, config.expert_variation()).reaction_delay_steps
        rig = _worker_rig(config, environment, task, delay)
        if config.shared is not None:
            recorded = record_shared_demonstration(environment, task, seed, config.shared, config.shared_labels,
                                                   config.observation, rig, config.environments_file)
        else:
            recorded = record_demonstration(environment, task, seed, config.observation, config.variation, rig,
                                            config.learner)
        demonstration = trim_rollover(recorded)
        return ({"index": index, "seed": seed, "steps": len(demonstration), "failures": [],
                 "status": demonstration.metadata["outcome"]["status"]}, demonstration)
    failures = []
    for attempt in range(ATTEMPTS_PER_DEMO):
        seed = config.seed + index + 1000 * attempt
        rig = _worker_rig(config, environment, task, draw_expert_style(seed, config.variation).reaction_delay_steps)
        demonstration = record_demonstration(environment, task, seed, config.observation, config.variation, rig)
        status = demonstration.metadata["outcome"]["status"]
        if status == "reached_goal":
            return ({"index": index, "seed": seed, "steps": len(demonstration), "failures": failures,
                     "status": status}, demonstration)
        failures.append({"seed": seed, "status": status})
    return _unfilled(index, failures), None


def _unfilled(index: int, failures: list[dict], error: str = "") -> dict:
    """The result of slot `index` when no demonstration was kept (`error`: why its task gave none)."""
    return {"index": index, "seed": None, "steps": 0, "failures": failures, "status": None,
            **({"error": error} if error else {})}


def _collect_slot(config: CollectConfig, index: int) -> dict:
    """A local worker's task: records slot `index` and writes its demonstration into the store."""
    result, demonstration = _record_slot(config, index)
    if demonstration is not None:
        DatasetStore.open(config.out).append(demonstration, index)
    return result


def _collect_on_ray(config: CollectConfig, store: DatasetStore, missing: list[int], keep) -> None:
    """Runs the `missing` slots as Ray tasks (`_record_slot`), writes each demonstration that
    comes back into `store` here, and passes its slot's result to `keep`.

    A task whose worker died twice (Ray retries once) leaves its slot unfilled, with the
    error in its result; an exception the recording raised is raised here, as from the
    local pool.
    """

    def write(call: tuple, returned: tuple[dict, Demonstration | None]) -> None:
        result, demonstration = returned
        with deferred_interrupts():  # Stored and counted together: a stop lands before or after.
            if demonstration is not None:
                store.append(demonstration, call[1])
            keep(result)

    def lost(call: tuple, error: Exception) -> None:
        raised = raised_by_task(error)
        if raised is not None:
            raise raised from (error if raised is not error else None)
        keep(_unfilled(call[1], [], failure_message(error)))

    if config.environments_file:  # Relative to this process's folder, not to a worker's on another node.
        config = replace(config, environments_file=str(Path(config.environments_file).resolve()))
    run_ray_tasks(_record_slot, [(config, index) for index in missing], config.address, config.workers, write, lost,
                  calls_per_worker=DEMOS_PER_WORKER)


def _existing_episode(store: DatasetStore, index: int, set_aside: list[str]) -> bool:
    """Whether episode `index` is stored whole.

    An episode folder without its `episode.json` (torn: not written by this store's writer,
    which renames whole episodes into place) is renamed to `<name>.torn[.N]` (kept for
    inspection, never overwritten) and its slot is recorded again.
    """
    path = store.episode_path(index)
    if not path.exists():
        return False
    if (path / EPISODE_FILE).is_file():
        return True
    target = path.with_name(path.name + ".torn")
    suffix = 1
    while target.exists():
        target = path.with_name(f"{path.name}.torn.{suffix}")
        suffix += 1
    path.rename(target)
    set_aside.append(str(target))
    return False


def collect(config: CollectConfig, progress: bool = True) -> dict:
    """Collects the missing episodes of the dataset folder `config.out`; returns a report.

    Interrupted and rerun, it keeps the episodes already written and records only the
    missing ones; a torn episode folder is renamed aside, not overwritten. Ctrl-C
    (KeyboardInterrupt) or SIGTERM stops it within a second or two: the report then has
    `interrupted` True and the shell's `exit_code` (130 or 143), and is not re-raised.
    The same holds on Ray (`config.backend`); there a slot whose task's worker died twice is
    unfilled, its reason in the report's `task_errors`.

    Raises:
        ConfigError: an unknown environment or backend, counts or seeds out of range, Ray
            asked for but not installed, a malformed or unreachable Ray address, an output
            path that is a file or holds the older .npz format, or a learner checkpoint
            that is missing.
    """
    slot_pairs(config)  # An unknown environment fails here, naming it.
    if not isinstance(config.demos, int) or config.demos <= 0:
        raise ConfigError(f"demos={config.demos!r} must be a positive integer")
    check_workers(config.workers)
    check_backend(config.backend, config.address)  # An unreachable cluster fails here, before the folder is made.
    check_seed(config.seed, config.demos)
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output path {out} is a file; expected a dataset folder")
    if out.is_dir() and not is_store(out) and demonstration_paths(out):
        raise ConfigError(f"output path {out} holds demo_NNN.npz files of the older format; expected a dataset "
                          f"folder: convert it with `ditch-drake dataset convert {out} NEW_FOLDER`, then collect "
                          "into NEW_FOLDER")
    if config.learner is not None:
        if config.shared is not None:
            raise ConfigError(f"learner {config.learner!r} with shared: the shared controller's policy drives "
                              "(shared.policy.checkpoint); expected one of the two")
        load_checkpoint(resolve_checkpoint_path(config.learner))  # A bad checkpoint fails here, not in a worker.
    if config.shared is not None:
        check_shared_collection(config.shared, config.shared_labels)
        if config.shared.policy.checkpoint:
            # A bad checkpoint fails here, not in a worker.
            load_policy(config.shared.policy.checkpoint, num_threads=None)
    try:
        store = DatasetStore.create(out)
    except DatasetError as error:
        raise ConfigError(str(error)) from error
    store.remove_stale_episodes()
    start = time.perf_counter()
    set_aside: list[str] = []
    missing = [index for index in range(config.demos) if not _existing_episode(store, index, set_aside)]
    workers = worker_count(config.workers)
    results = []
    label = config.environment if not config.environments else f"{len(config.environments)} environments"
    bar = tqdm(total=len(missing), desc=f"collect {label}", disable=not progress)

    def keep(result: dict) -> None:
        results.append(result)
        bar.update(1)
        if config.learner is None and config.shared is None:
            bar.set_postfix(failed=sum(len(r["failures"]) for r in results))
        else:
            bar.set_postfix(learner_reached_goal=sum(r["status"] == "reached_goal" for r in results))

    interrupted, exit_code = False, 0
    try:
        with terminate_as_interrupt():
            if config.backend == "ray" and missing:
                _collect_on_ray(config, store, missing, keep)
            elif workers == 0 or not missing:
                for index in missing:
                    keep(_collect_slot(config, index))
            else:
                chunk = workers * DEMOS_PER_WORKER
                for begin in range(0, len(missing), chunk):
                    part = missing[begin:begin + chunk]
                    with WorkerPool(min(workers, len(part))) as pool:
                        for future in as_completed([pool.submit(_collect_slot, config, index) for index in part]):
                            keep(future.result())
    except KeyboardInterrupt as error:
        interrupted, exit_code = True, interrupt_exit_code(error)
    finally:
        bar.close()
    failures = [failure for result in results for failure in result["failures"]]
    wall_s = time.perf_counter() - start
    recorded = sum(result["seed"] is not None for result in results)
    return {
        "environment": config.environment if not config.environments else config.environments,
        "out": str(config.out),
        "kept_before": config.demos - len(missing),
        "torn_episodes_set_aside": set_aside,
        "recorded": recorded,
        "unfilled_slots": [result["index"] for result in results if result["seed"] is None],
        "discarded": len(failures),
        "discarded_by_status": {status: sum(f["status"] == status for f in failures)
                                for status in sorted({f["status"] for f in failures})},
        "steps_recorded": sum(result["steps"] for result in results),
        "recorded_by_status": {status: sum(r["status"] == status for r in results)
                               for status in sorted({r["status"] for r in results if r["status"]})},
        "wall_s": wall_s,
        "demos_per_minute": 60.0 * recorded / wall_s if recorded else 0.0,
        "task_errors": {result["index"]: result["error"] for result in results if "error" in result},
        "interrupted": interrupted,
        "exit_code": exit_code,
    }
