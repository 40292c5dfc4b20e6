"""The calibration benchmark: does the simulation show the paper's phenomenon?

For every environment, with seeded start-pose jitter (issue "Foundation"):
- flat ground: 1.0 m/s tracked within 5 %, each of the 17 angular rates within 10 %;
- a driver heading straight at the ditch, perpendicular to the local edge, rolls
  over in at least 9 of 10 trials;
- a driver holding a shallow angle to the local edge gets to the goal without
  rollover in at least 9 of 10 trials for each of the three tasks.
It also records, without a pass mark, whether climbing out head-on from the
bottom flips the robot backwards (paper 4.1).
"""

import math
from concurrent.futures import as_completed
from dataclasses import asdict, dataclass, field

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from tqdm import tqdm

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import WorkerPool, worker_count
from ditch_drake.diagrams.ditch_scene import DefaultPlantConfig, DitchScene, SceneConfig
from ditch_drake.diagrams.rollout import (
    ConstantCommandConfig,
    MakeRolloutDiagram,
    RolloutConfig,
    RunEpisode,
    StartEpisode,
)
from ditch_drake.spec import robot
from ditch_drake.spec.actions import ANGULAR_RATES_RADPS
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig
from ditch_drake.systems.episode_monitor import EpisodeStatus
from ditch_drake.world.environments import environment_names, get_environment

SPEED_TOLERANCE = 0.05
RATE_TOLERANCE = 0.10
REQUIRED_RATE = 0.9  # 9 of 10


@dataclass
class CalibrationConfig:
    """Trials and drivers of the calibration benchmark.

    Attributes:
        trials: seeded trials per head-on environment and per shallow task.
        seed: the first trial's seed; trial i uses seed + i.
        time_step_s: the plant's discrete step.
        shallow: the driver that holds a shallow angle to the local edge.
        head_on: the driver that heads straight at the ditch.
        flat_duration_s: length of each flat-ground run; the last half is averaged.
        workers: parallel processes (None: one per core; 0: in this process).
        environments_file: a YAML file of environments that the calibrated names may come
            from ("": the packaged ones only).
    """

    trials: int = 10
    seed: int = 0
    time_step_s: float = field(default_factory=lambda: DefaultPlantConfig().time_step)
    shallow: EdgeAngleDriverConfig = field(default_factory=EdgeAngleDriverConfig)
    head_on: EdgeAngleDriverConfig = field(
        default_factory=lambda: EdgeAngleDriverConfig(wall_angle_deg=90.0, climb_angle_deg=None))
    flat_duration_s: float = 4.0
    workers: int | None = None
    environments_file: str = ""


def _scene_config(environment: str, task: int, time_step_s: float, environments_file: str = "") -> SceneConfig:
    config = SceneConfig(environment=environment, task=task, environments_file=environments_file)
    config.plant.time_step = time_step_s
    return config


def _place(scene: DitchScene, context, xy, yaw: float, z: float = 0.0) -> None:
    """Moves the chassis to (xy, yaw) keeping the seeded jitter already in `context`."""
    plant = scene.plant
    plant_context = plant.GetMyContextFromRoot(context)
    chassis = plant.GetBodyByName("chassis", scene.husky)
    X_WB = plant.EvalBodyPoseInWorld(plant_context, chassis)
    x0, y0, yaw0_deg = scene.task.start
    jitter_xy = X_WB.translation()[:2] - np.array([x0, y0])
    jitter_yaw = RollPitchYaw(X_WB.rotation()).yaw_angle() - math.radians(yaw0_deg)
    position = [*(np.asarray(xy) + jitter_xy), z + robot.WHEEL_RADIUS_M + 0.005]
    plant.SetFreeBodyPose(plant_context, chassis,
                          RigidTransform(RotationMatrix.MakeZRotation(yaw + jitter_yaw), position))


def flat_tracking(environment: str, config: CalibrationConfig) -> dict:
    """Steady-state speed and yaw rate for each of the 17 labels, far out on flat ground.

    Each label starts like an episode (`StartEpisode`: the seeded jitter, then the robot moved
    far out and the command set) but is no episode: no task, goal or outcome, a fixed
    command for a fixed time. So it advances the simulator itself, to its sample times over
    the run's second half, instead of through `RunEpisode`.
    """
    diagram, scene = MakeRolloutDiagram(RolloutConfig(
        scene=_scene_config(environment, 0, config.time_step_s, config.environments_file),
        controller=ConstantCommandConfig()))
    terrain = scene.terrain
    low, _ = terrain.bounds_xy()
    # Well clear of the ditch, heading away from it (-y), with room for a wide arc.
    spot = np.array([float(np.mean(terrain.course_xy[:, 0])), low[1] + 8.0])
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    command_source = diagram.GetSubsystemByName("constant_command")
    source_context = command_source.GetMyMutableContextFromRoot(context)
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    speeds, rates = [], []
    for label, rate in enumerate(ANGULAR_RATES_RADPS):

        def far_out(root_context, rate=rate) -> None:
            _place(scene, root_context, spot, -math.pi / 2)
            command_source.get_mutable_source_value(source_context).set_value([robot.MAX_SPEED_MPS, rate])

        StartEpisode(simulator, diagram, config.seed + label, before_start=far_out)
        samples = []
        for k in range(20):
            simulator.AdvanceTo(config.flat_duration_s * (0.5 + 0.5 * (k + 1) / 20))
            V = scene.plant.EvalBodySpatialVelocityInWorld(scene.plant.GetMyContextFromRoot(context), chassis)
            samples.append((np.linalg.norm(V.translational()[:2]), V.rotational()[2]))
        speed, measured_rate = np.mean(samples, axis=0)
        speeds.append(float(speed))
        rates.append(float(measured_rate))
    rate_errors = [
        abs(measured - commanded) / abs(commanded) if commanded != 0 else abs(measured) / ANGULAR_RATES_RADPS[9]
        for measured, commanded in zip(rates, ANGULAR_RATES_RADPS)
    ]
    speed_error = max(abs(speed - robot.MAX_SPEED_MPS) for speed in speeds) / robot.MAX_SPEED_MPS
    return {
        "flat_speed_max_error": speed_error,
        "flat_speed_ok": bool(speed_error <= SPEED_TOLERANCE),
        "flat_rate_max_error": float(max(rate_errors)),
        "flat_rates_ok": bool(max(rate_errors) <= RATE_TOLERANCE),
        "flat_rates_radps": rates,
    }


def _at_the_bottom(scene: DitchScene):
    """A `before_start` that moves the robot to the ditch bottom, facing the far wall."""
    _, course_point = scene.terrain.nearest_on_course(np.asarray(scene.task.start[:2]))
    to_goal = np.asarray(scene.task.goal) - course_point

    def place(root_context) -> None:
        _place(scene, root_context, course_point, math.atan2(to_goal[1], to_goal[0]), z=-scene.terrain.params.depth_m)

    return place


def driven_trials(environment: str, task: int, driver: EdgeAngleDriverConfig, seeds: list[int],
                  time_step_s: float, start_at_bottom: bool = False, environments_file: str = "") -> list[dict]:
    """Seeded episodes of one task; with `start_at_bottom`, from the ditch bottom facing the far wall."""
    diagram, scene = MakeRolloutDiagram(RolloutConfig(
        scene=_scene_config(environment, task, time_step_s, environments_file), controller=driver))
    simulator = Simulator(diagram)
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    before_start = _at_the_bottom(scene) if start_at_bottom else None
    records = []
    for seed in seeds:
        record = asdict(RunEpisode(simulator, diagram, scene, seed, before_start=before_start))
        if start_at_bottom:
            X_WB = scene.plant.EvalBodyPoseInWorld(scene.plant.GetMyContextFromRoot(simulator.get_context()), chassis)
            record["final_forward_z"] = float(X_WB.rotation().matrix()[2, 0])
        records.append({"seed": seed, "task": scene.task.name, **record})
    return records


def _jobs(environment: str, config: CalibrationConfig) -> list[tuple]:
    tasks = len(get_environment(environment, config.environments_file or None).tasks)
    seeds = [config.seed + i for i in range(config.trials)]
    jobs = [("flat", environment, None, None)]
    for task in range(tasks):
        jobs.append(("head_on", environment, task, seeds[task::tasks]))
        jobs.append(("shallow", environment, task, seeds))
        jobs.append(("climb_out_head_on", environment, task, seeds[task::tasks]))
    return jobs


def _run_job(job: tuple, config: CalibrationConfig):
    kind, environment, task, seeds = job
    if kind == "flat":
        return job, flat_tracking(environment, config)
    driver = config.shallow if kind == "shallow" else config.head_on
    return job, driven_trials(environment, task, driver, seeds, config.time_step_s,
                              start_at_bottom=(kind == "climb_out_head_on"), environments_file=config.environments_file)


def _rate(records: list[dict], status: EpisodeStatus) -> float:
    return sum(record["status"] == status.name.lower() for record in records) / max(1, len(records))


def run_calibration(config: CalibrationConfig | None = None, environments: list[str] | None = None,
                    progress: bool = True) -> dict:
    """Runs every environment's trials in parallel processes; returns one JSON-able dict.

    Ctrl-C kills the workers at once and re-raises: a calibration is judged whole or not at all.
    """
    config = config or CalibrationConfig()
    environments = environments or environment_names()
    for name in environments:
        get_environment(name, config.environments_file or None)  # Fails early, naming an unknown environment.
    jobs = [job for name in environments for job in _jobs(name, config)]
    if config.trials < 1:
        raise ConfigError(f"trials={config.trials}: expected >= 1 seeded trials per driven case")
    workers = worker_count(config.workers)
    results: dict[str, dict] = {name: {"head_on": [], "shallow": {}, "climb_out_head_on": []} for name in environments}

    def keep(job_and_value) -> None:
        (kind, environment, task, _), value = job_and_value
        bucket = results[environment]
        if kind == "flat":
            bucket.update(value)
        elif kind == "shallow":
            bucket["shallow"][task] = value
        else:
            bucket[kind].extend(value)

    with tqdm(total=len(jobs), desc="calibrate", disable=not progress) as bar:
        if workers == 0:
            for job in jobs:
                keep(_run_job(job, config))
                bar.update(1)
        else:
            with WorkerPool(workers) as pool:
                for future in as_completed([pool.submit(_run_job, job, config) for job in jobs]):
                    keep(future.result())
                    bar.update(1)
    report = {"time_step_s": config.time_step_s, "trials": config.trials, "seed": config.seed, "environments": {}}
    all_ok = True
    for name in environments:
        bucket = results[name]
        task_names = [task.name for task in get_environment(name, config.environments_file or None).tasks]
        shallow = {task_names[t]: _rate(records, EpisodeStatus.REACHED_GOAL) for t, records in sorted(bucket["shallow"].items())}
        shallow_times = [r["time_s"] for records in bucket["shallow"].values() for r in records
                         if r["status"] == "reached_goal"]
        head_on_rate = _rate(bucket["head_on"], EpisodeStatus.ROLLED_OVER)
        climb_out = bucket["climb_out_head_on"]
        backflips = [r for r in climb_out if r["status"] == "rolled_over" and r["final_forward_z"] > 0]
        summary = {
            "flat_speed_max_error": bucket["flat_speed_max_error"],
            "flat_speed_ok": bucket["flat_speed_ok"],
            "flat_rate_max_error": bucket["flat_rate_max_error"],
            "flat_rates_ok": bucket["flat_rates_ok"],
            "head_on_rollover_rate": head_on_rate,
            "head_on_ok": head_on_rate >= REQUIRED_RATE,
            "shallow_success_rate": shallow,
            "shallow_ok": all(rate >= REQUIRED_RATE for rate in shallow.values()),
            "shallow_crossing_time_s": [min(shallow_times), max(shallow_times)] if shallow_times else None,
            "climb_out_head_on_outcomes": sorted({r["status"] for r in climb_out}),
            "climb_out_head_on_backflip_rate": len(backflips) / max(1, len(climb_out)),
        }
        summary["ok"] = all(summary[key] for key in ("flat_speed_ok", "flat_rates_ok", "head_on_ok", "shallow_ok"))
        all_ok &= summary["ok"]
        report["environments"][name] = summary
    report["all_ok"] = all_ok
    return report
