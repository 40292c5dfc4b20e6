"""`ditch-drake bench`: every speed and memory figure the project tracks, as one JSON object.

Keys end with their unit (`_ms`, `_s`, `_rtf`, `_mib`). Later work adds its figures
here, keeping the existing keys stable.
"""

import resource
import time

import numpy as np

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import ConstantCommandConfig, MakeRolloutDiagram, RolloutConfig
from ditch_drake.perf.closed_loop import (
    CLOSED_LOOP_EPISODES,
    TRAVERSAL_S,
    WARMUP_S,
    MakeClosedLoopDiagram,
    timed_run,
)
from ditch_drake.spec import robot
from ditch_drake.world.environments import environment_names, get_environment, load_environments


def measure_plant_rtf(environment: str, seed: int = 0, duration_s: float = TRAVERSAL_S,
                      environments_file: str = "", repeats: int = 3) -> dict:
    """Real-time factor of the plant driven by the scripted shallow-angle driver, and of its
    walled variant's (`<env>_walled`, if the environment has one) in the same run.

    One process, no visualization: `duration_s` of a traversal from the first task's
    seeded start, simulated seconds over wall seconds; the median of `repeats` runs, the
    open and the walled field taking turns run by run, so that their ratio holds on a host
    whose speed drifts. Also times the diagram builds.
    """
    names = [environment, *walled_variants(environment, environments_file)]
    figures, diagrams = {}, {}
    for name in names:
        start = time.perf_counter()
        diagrams[name], _ = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=name,
                                                                               environments_file=environments_file)))
        figures[f"scene_build_{name}_s"] = time.perf_counter() - start
    rates: dict[str, list[float]] = {name: [] for name in names}
    for _ in range(repeats):
        for name in names:
            wall_s, sim_s, _ = timed_run(diagrams[name], seed, duration_s)
            rates[name].append(sim_s / wall_s)
    return {**{f"plant_{name}_rtf": float(np.median(rates[name])) for name in names}, **figures}


def walled_variants(environment: str, environments_file: str = "") -> list[str]:
    """The packaged (or the file's) environments based on `environment` that are fenced."""
    library = {**(load_environments(environments_file) if environments_file else {}),
               **{name: get_environment(name) for name in environment_names(variants=True)}}
    return [name for name, candidate in library.items()
            if candidate.based_on == environment and candidate.terrain.walls]


def measure_closed_loops(
    environments: list[str], seed: int = 0, duration_s: float = TRAVERSAL_S, episodes: int = CLOSED_LOOP_EPISODES,
    environments_file: str = "",
) -> dict:
    """Real-time factor with every perception block running at 10 Hz and a fixed command.

    Also the mean wall time of one control step's observation update (lidar render and
    cloud, normal image, IMU, goal, stacker): the closed loop's wall time minus the
    plant-only wall time for the same simulated span, per control step.

    Both figures are the steady state after the first control step (`WARMUP_S`), timed
    apart as `observation_first_step_<env>_ms`: the first render of a Context's
    `RenderEngineVtk` sets up its pipeline (measured: 20-60 ms in a process's first
    Context, about 15 ms in each later one), a cost a batch evaluation pays once per
    worker rig, whose Simulator and Context serve every rollout.

    The fixed command drives straight at the ditch, so one episode ends (rollover) after
    about 60 control steps, about 0.2 s of wall time: one such episode is at the mercy of
    whatever else the machine does in that fraction of a second. So the figures are the
    medians over `episodes` episodes from the seeded starts `seed`, `seed` + 1, ... (each
    with its own Simulator and Context, like separate rollouts), and the first step's cost
    the median of the episodes' first steps. The environments take turns episode by
    episode (the first episode of each, then the second of each, ...), so each median
    draws on the whole measurement's span instead of a few seconds of it: a slow spell of
    the shared host (they last seconds to minutes here) then moves a few episodes of every
    environment rather than all of one.

    Returns:
        For each environment, in the given order, `closed_loop_<env>_rtf`,
        `observation_update_<env>_ms` and `observation_first_step_<env>_ms`.
    """
    if episodes < 1:
        raise ValueError(f"episodes={episodes!r} must be >= 1")
    command = ConstantCommandConfig([robot.MAX_SPEED_MPS, 0.0])
    diagrams = {}
    for environment in environments:
        scene_config = SceneConfig(environment=environment, environments_file=environments_file)
        plant_only, _ = MakeRolloutDiagram(RolloutConfig(scene=scene_config, controller=command))
        diagrams[environment] = (MakeClosedLoopDiagram(scene_config, command), plant_only)
    rtfs, observation_ms, first_step_ms = ({environment: [] for environment in environments} for _ in range(3))
    for episode_seed in range(seed, seed + episodes):
        for environment, (loop, plant_only) in diagrams.items():
            loop_wall, loop_time, loop_warmup_wall = timed_run(loop, episode_seed, duration_s, WARMUP_S)
            plant_wall, plant_time, plant_warmup_wall = timed_run(plant_only, episode_seed, duration_s, WARMUP_S)
            steps = loop_time / robot.CONTROL_PERIOD_S
            rtfs[environment].append(loop_time / loop_wall)
            observation_ms[environment].append(1e3 * (loop_wall - plant_wall * loop_time / plant_time) / steps)
            first_step_ms[environment].append(1e3 * (loop_warmup_wall - plant_warmup_wall))
    figures = {}
    for environment in environments:
        figures[f"closed_loop_{environment}_rtf"] = float(np.median(rtfs[environment]))
        figures[f"observation_update_{environment}_ms"] = float(np.median(observation_ms[environment]))
        figures[f"observation_first_step_{environment}_ms"] = float(np.median(first_step_ms[environment]))
    return figures


def measure_blocks() -> dict:
    """One control step of each expensive block, in ms (medians, one process)."""
    from ditch_drake.perf.bench_dwa import measure_dwa_ms
    from ditch_drake.perf.bench_lidar import measure_lidar_ms
    from ditch_drake.perf.bench_mppi import measure_mppi_ms
    from ditch_drake.perf.bench_normal_image import measure_normal_image_ms
    from ditch_drake.perf.bench_training import (
        measure_ensemble_policy_step_ms,
        measure_onnxruntime_policy_step_ms,
        measure_policy_step_ms,
    )

    lidar = measure_lidar_ms("wide")
    normal_image = measure_normal_image_ms(repeats=30)
    figures = {
        "lidar_render_and_cloud_ms": lidar["lidar_render_and_cloud_ms"],
        "normal_image_organized_ms": normal_image["normal_image_organized_ms"],
        "normal_image_pca_reference_ms": normal_image["normal_image_pca_ms"],
        "policy_step_ms": measure_policy_step_ms()["policy_step_ms"],
    }
    # Five clones in one forward pass (the shared controller's ensemble); beside it, their image
    # branch in bfloat16 (`precision: bfloat16_image`; None on a CPU without native bfloat16), and
    # in the same rounds one member alone and the five one after another (unbatched).
    ensemble = measure_ensemble_policy_step_ms()
    figures.update({key: ensemble[key] for key in ("ensemble_policy_step_ms", "ensemble_policy_step_bfloat16_ms",
                                                   "ensemble_member_policy_step_ms", "ensemble_members_in_turn_ms")})
    # The same network in ONNX Runtime (`runtime: onnxruntime`), float32 and int8, where the `onnx`
    # extra is installed.
    onnxruntime_step = measure_onnxruntime_policy_step_ms()
    if onnxruntime_step:
        figures["policy_step_onnxruntime_ms"] = onnxruntime_step["policy_step_onnxruntime_ms"]
        figures["policy_step_onnxruntime_int8_ms"] = onnxruntime_step["policy_step_onnxruntime_int8_ms"]
    # The DWA baseline on the real lidar: costmap update + local plan apart from the global plan.
    dwa = measure_dwa_ms()
    figures.update({key: dwa[key] for key in ("dwa_update_ms", "dwa_update_cpu_ms", "dwa_update_p90_ms",
                                              "dwa_global_plan_ms", "dwa_global_plan_cpu_ms", "dwa_step_ms")})
    # The rollover-aware MPPI on its own replayed drive (map fusion + attitude-predicting plan).
    mppi = measure_mppi_ms()
    figures.update({key: mppi[key] for key in ("mppi_update_ms", "mppi_update_cpu_ms", "mppi_update_p90_ms")})
    # The generalist's perceived crossing side on a replayed approach to the wide ditch.
    from ditch_drake.perf.bench_crossing_side import measure_crossing_side_ms

    side = measure_crossing_side_ms()
    figures.update({key: side[key] for key in ("crossing_side_ms", "crossing_side_cpu_ms", "crossing_side_p90_ms")})
    return figures


def measure_rollouts_per_minute(rollouts: int = 4, environment: str = "wide") -> dict:
    """Full learned-policy rollouts per minute of `ditch-drake evaluate` on all cores (a fresh
    temporary results file; diagram builds included, as in a real evaluation)."""
    import tempfile
    from pathlib import Path

    from ditch_drake.evaluation.batch import evaluate, make_specs

    specs = make_specs("learned", environment, environment, tasks=[1], rollouts=rollouts)
    with tempfile.TemporaryDirectory() as folder:
        report = evaluate(specs, Path(folder) / "bench.jsonl", progress=False)
    return {"evaluate_rollouts_per_min": report.rollouts_per_minute}


def measure_gym_figures() -> dict:
    """The Gymnasium environment's steps per second and its time per step over the closed
    loop's (`ditch_drake.perf.bench_gym`); none without the `gym` extra, which says so on stderr."""
    import importlib.util
    import sys

    if importlib.util.find_spec("gymnasium") is None:
        print("bench: gymnasium is not installed (pip install -e '.[gym]'): no gym_* figures", file=sys.stderr)
        return {}
    from ditch_drake.perf.bench_gym import measure_gym_env

    return measure_gym_env()


def measure_host_reference_ms(repeats: int = 5) -> float:
    """Median wall time (ms) of a fixed single-threaded CPU workload: a pure-Python loop
    and elementwise numpy arithmetic. It measures the machine, not the project: on a
    shared virtual machine its speed changes from minute to minute (the same loop took
    43 ms and 84 ms within one minute here), and every other figure moves with it. The
    bench times it at its start and its end so that a run's figures can be read against
    the host's state then."""
    values = np.linspace(0.0, 1.0, 100_000)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        total = 0
        for i in range(500_000):
            total += i
        for _ in range(20):
            np.sin(values)
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def run_bench(environments: list[str] | None = None, training: bool = False, environments_file: str = "") -> dict:
    """All figures, in a stable key order; `training` adds SMOTE's slow training-memory run
    (`bench_training.measure_smote_memory`). `environments_file` adds its environments to the
    packaged ones that `environments` may name."""
    figures: dict[str, float] = {"host_reference_start_ms": measure_host_reference_ms()}
    environments = environments or environment_names()
    for name in environments:
        get_environment(name, environments_file or None)  # A bad name fails before minutes of measuring.
    for name in environments:
        figures.update(measure_plant_rtf(name, environments_file=environments_file))
    figures["plant_min_rtf"] = min(figures[f"plant_{name}_rtf"] for name in environments)
    figures.update(measure_closed_loops(environments, environments_file=environments_file))
    figures["closed_loop_min_rtf"] = min(figures[f"closed_loop_{name}_rtf"] for name in environments)
    figures.update(measure_blocks())
    from ditch_drake.perf.bench_training import (
        measure_streaming_memory,
        measure_training_throughput,
        shipped_model_figures,
    )

    figures.update(measure_training_throughput())
    figures.update(shipped_model_figures())
    # Training streamed from a synthetic dataset folder of 16 k and 128 k samples (fresh processes).
    figures.update(measure_streaming_memory())
    figures.update(measure_rollouts_per_minute())
    figures.update(measure_gym_figures())
    from ditch_drake.perf.bench_scene import (
        measure_benchmark_rollouts_per_min,
        measure_diagram_rss,
        measure_scene_build,
    )

    figures["scene_build_max_s"] = measure_scene_build()["scene_build_max_s"]
    rss = measure_diagram_rss()
    figures.update({key: value for key, value in rss.items() if key.endswith("_mib")})
    figures.update(measure_benchmark_rollouts_per_min())
    if training:
        from ditch_drake.perf.bench_training import measure_smote_memory

        figures.update(measure_smote_memory())
    figures["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    figures["host_reference_end_ms"] = measure_host_reference_ms()
    return figures
