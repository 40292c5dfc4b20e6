"""What a rollout diagram costs to build and to keep (issue 22): `scene_build_max_s` and
`diagram_rss_mib`.

    python -m ditch_drake.perf.bench_scene               # the bench's keys and details
    python -m ditch_drake.perf.bench_scene --breakdown   # where a diagram's memory goes
    python -m ditch_drake.perf.bench_scene --profile sine  # where a build's time goes

- `scene_build_max_s`: the slowest `MakeRolloutDiagram` (learned controller) over 20
  ditches: the four packaged ones and the benchmark generator's train-split ditches of
  seeds 0..15 (`ditch_drake.benchmark.generator.sample_ditch`), after one warm-up build.
- `benchmark_rollouts_per_min`: `ditch-drake benchmark` rollouts per minute of the generalist
  on all cores (`measure_benchmark_rollouts_per_min`).
- `diagram_rss_mib`: the resident memory that each additional cached rollout diagram
  (learned controller; diagram, Simulator, one started episode, as a batch worker keeps it)
  adds, the worse of "wide" and "sine". Each is measured in a fresh subprocess
  (`--rss <env>`), building `RSS_DIAGRAMS` diagrams and taking the growth from the first
  to the last over the count between, so that the bench process's own state (and the
  first diagram's one-time costs: imports, the renderer's setup) does not count.

The figures are dominated by the number of collision geometries: SceneGraph's collision
filter costs memory and time with its square (`DitchTerrain.collision_pieces`).
"""

import json
import os
import subprocess
import sys
import time

PACKAGED = ("wide", "narrow", "sine", "crater")
GENERATED_SEEDS = range(16)
RSS_ENVIRONMENTS = ("wide", "sine")
RSS_DIAGRAMS = 3


def rss_mib() -> float:
    """This process's resident set size (MiB), from /proc/self/statm."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def build_cases() -> list[tuple[str, object, str]]:
    """(name, Environment or None for a packaged one, checkpoint) of the 20 ditches."""
    from ditch_drake.benchmark.generator import sample_ditch

    cases = [(name, None, name) for name in PACKAGED]
    for seed in GENERATED_SEEDS:
        ditch = sample_ditch(seed)
        # Any shipped model will do for timing a build: they have the same inputs.
        cases.append((ditch.name, ditch.environment, "wide"))
    return cases


def _rollout_config(name: str, environment, checkpoint: str):
    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig, RolloutConfig

    scene = SceneConfig(environment=name, environments={name: environment} if environment is not None else {})
    return RolloutConfig(scene=scene, controller=LearnedPolicyConfig(checkpoint=checkpoint))


def measure_scene_build() -> dict:
    """`scene_build_max_s` and the slowest ditch's name (`scene_build_max_env`), plus each build."""
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram

    MakeRolloutDiagram(_rollout_config("wide", None, "wide"))  # warm-up: imports, model loads
    times = {}
    for name, environment, checkpoint in build_cases():
        config = _rollout_config(name, environment, checkpoint)
        start = time.perf_counter()
        MakeRolloutDiagram(config)
        times[name] = time.perf_counter() - start
    slowest = max(times, key=times.get)
    return {"scene_build_max_s": times[slowest], "scene_build_max_env": slowest,
            "scene_build_s": times}


def measure_diagram_rss_here(environment: str, diagrams: int = RSS_DIAGRAMS) -> dict:
    """RSS growth (MiB) per additional cached rollout diagram of `environment`, in this process."""
    import torch
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, StartEpisode

    torch.set_num_threads(1)  # as a batch worker (`rollout_worker.initialize_worker`)
    kept, after = [], []
    for index in range(diagrams):
        diagram, scene = MakeRolloutDiagram(_rollout_config(environment, None, environment))
        simulator = Simulator(diagram)
        StartEpisode(simulator, diagram, seed=index)
        simulator.AdvanceTo(0.5)  # a few control steps: the renderer and the policy run
        kept.append((diagram, scene, simulator))
        after.append(rss_mib())
    return {"environment": environment, "rss_after_each_mib": after,
            "diagram_rss_mib": (after[-1] - after[0]) / (diagrams - 1)}


# `--breakdown`: where a diagram's memory goes, by what its terrain registers for collision and
# whether SceneGraph's cached copy of its model is released after each episode start.
BREAKDOWN_VARIANTS = {
    "default": "a winding ditch's convex sections, cache released (as shipped)",
    "mitred": "collision boxes with mitred bends, cache released",
    "revolved": "collision boxes = the visual boxes (bends revolved), cache released",
    "revolved_cached": "collision boxes = the visual boxes, cache kept (before issue 22)",
    "no_terrain_collision": "terrain registered for illustration and perception only",
}


def _apply_variant(variant: str) -> None:
    """Switches this (subprocess's) terrain and episode start to a `BREAKDOWN_VARIANTS` variant."""
    from ditch_drake.diagrams import rollout
    from ditch_drake.world.terrain import DitchTerrain

    if variant == "mitred":
        DitchTerrain.collision_pieces = lambda terrain: terrain.box_pieces(mitre_bends=True)
    if variant in ("revolved", "revolved_cached"):
        DitchTerrain.collision_pieces = DitchTerrain.box_pieces
    if variant == "revolved_cached":
        rollout.ReleaseSceneGraphModelCache = lambda diagram: None
    if variant == "no_terrain_collision":
        DitchTerrain.collision_pieces = lambda terrain: []


def measure_breakdown(environments=("wide", "sine")) -> dict:
    """`diagram_rss_<env>_<variant>_mib` for each `BREAKDOWN_VARIANTS` variant, each in a fresh subprocess."""
    figures = {}
    for environment in environments:
        for variant in BREAKDOWN_VARIANTS:
            result = subprocess.run([sys.executable, "-m", "ditch_drake.perf.bench_scene", "--rss", environment,
                                     variant], capture_output=True, text=True, check=True)
            figures[f"diagram_rss_{environment}_{variant}_mib"] = json.loads(
                result.stdout.strip().splitlines()[-1])["diagram_rss_mib"]
    return figures


def measure_diagram_rss(environments=RSS_ENVIRONMENTS) -> dict:
    """`diagram_rss_mib`: the worst of `environments`, each in a fresh subprocess."""
    figures = {}
    for environment in environments:
        result = subprocess.run([sys.executable, "-m", "ditch_drake.perf.bench_scene", "--rss", environment],
                                capture_output=True, text=True, check=True)
        figures[environment] = json.loads(result.stdout.strip().splitlines()[-1])["diagram_rss_mib"]
    worst = max(figures, key=figures.get)
    return {"diagram_rss_mib": figures[worst], "diagram_rss_env": worst,
            **{f"diagram_rss_{name}_mib": value for name, value in figures.items()}}


def measure_benchmark_rollouts_per_min(geometries: int = 4) -> dict:
    """`benchmark_rollouts_per_min`: `ditch-drake benchmark` of the learned generalist over the
    val split's first `geometries` ditches (3 tasks each), one rollout per task, on all cores, in
    a fresh results file: ditch sampling and diagram builds included, as in a real run. (The val
    split, not test: a timing is no result, but the test split is only ever run for the report.)"""
    import tempfile
    from pathlib import Path

    from ditch_drake.benchmark.run import GENERALIST, BenchmarkConfig, run_benchmark

    with tempfile.TemporaryDirectory() as folder:
        report = run_benchmark(BenchmarkConfig(split="val", controller="learned", checkpoint=GENERALIST,
                                               geometries=geometries, rollouts=1,
                                               out=str(Path(folder) / "bench.jsonl")), progress=False)
    return {"benchmark_rollouts_per_min": report.rollouts_per_minute}


def measure_scene_figures() -> dict:
    """The two bench keys (and the details beside them)."""
    return {**measure_scene_build(), **measure_diagram_rss(), **measure_benchmark_rollouts_per_min()}


def profile_scene_build(environment: str = "sine", lines: int = 12) -> str:
    """cProfile of one `MakeRolloutDiagram` (learned controller) of a packaged environment,
    after a warm-up build: the calls that take the time, by cumulative time."""
    import cProfile
    import io
    import pstats

    from ditch_drake.diagrams.rollout import MakeRolloutDiagram

    config = _rollout_config(environment, None, environment)
    MakeRolloutDiagram(_rollout_config("wide", None, "wide"))
    profiler = cProfile.Profile()
    profiler.runcall(MakeRolloutDiagram, config)
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(lines)
    return text.getvalue()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--rss"]:
        _apply_variant(argv[2] if len(argv) > 2 else "default")
        print(json.dumps(measure_diagram_rss_here(argv[1])))
        return
    if argv[:1] == ["--profile"]:
        print(profile_scene_build(*argv[1:2]))
        return
    if argv[:1] == ["--breakdown"]:
        print(json.dumps(measure_breakdown(), indent=2))
        return
    print(json.dumps(measure_scene_figures(), indent=2))


if __name__ == "__main__":
    main()
