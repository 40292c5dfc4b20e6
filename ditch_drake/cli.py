"""The `ditch-drake` command line."""

import argparse
import json
import os
import shlex
import sys
import time
from dataclasses import replace

from ditch_drake.actions import ANGULAR_RATES_RADPS
from ditch_drake.demos.dataset import DatasetError
from ditch_drake.environments import ConfigError, environment_names
from ditch_drake.evaluation.results import ResultsError
from ditch_drake.learning.checkpoint import CheckpointError
from ditch_drake.terrain import TerrainError


def _print_table(rows: list[dict], columns: list[str]) -> None:
    widths = [max(len(column), *(len(str(row[column])) for row in rows)) for column in columns]
    print("  ".join(column.ljust(width) for column, width in zip(columns, widths)))
    for row in rows:
        print("  ".join(str(row[column]).ljust(width) for column, width in zip(columns, widths)))


def cmd_demo(args) -> int:
    """The main job: the shipped policy, the DWA baseline and a head-on driver through one ditch;
    an outcome table and the policy's rollout as a standalone HTML page."""
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.replay import ReplayConfig, record_replay
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode

    scene = SceneConfig(environment=args.env, task=args.task)
    checkpoint = args.checkpoint or args.env
    rows = []

    def row(name, outcome, wall_s):
        rows.append({"controller": name, "outcome": outcome.status, "sim_time_s": f"{outcome.time_s:.1f}",
                     "path_m": f"{outcome.path_length_m:.1f}", "peak_tilt_deg": f"{outcome.peak_tilt_deg:.0f}",
                     "wall_s": f"{wall_s:.1f}"})

    start = time.perf_counter()
    replay = record_replay(ReplayConfig(
        rollout=RolloutConfig(scene=scene, controller=_controller_config("learned", checkpoint)),
        seed=args.seed, out=args.html))
    row(f"learned policy ({checkpoint} model)", replay.outcome, time.perf_counter() - start)
    for name, controller in (("DWA baseline (move_base-style)", "dwa"),
                             ("head-on scripted driver (reference)", "head_on")):
        start = time.perf_counter()
        diagram, built = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=_controller_config(controller, "")))
        row(name, RunEpisode(Simulator(diagram), diagram, built, args.seed), time.perf_counter() - start)
    print(f"environment {args.env}, task {args.task} ({built.task.name}), seed {args.seed}")
    _print_table(rows, ["controller", "outcome", "sim_time_s", "path_m", "peak_tilt_deg", "wall_s"])
    print(f"recording of the learned policy's rollout: {replay.html_path} (open it in any browser)")
    return 0


def cmd_view(args) -> int:
    """Opens the scene in meshcat and drives it with the scripted driver in real time."""
    from pydrake.geometry import StartMeshcat
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode

    meshcat = StartMeshcat()
    diagram, scene = MakeRolloutDiagram(RolloutConfig(scene=SceneConfig(environment=args.env, task=args.task)),
                                        meshcat=meshcat)
    simulator = Simulator(diagram)
    simulator.set_target_realtime_rate(args.realtime_rate)
    print(f"meshcat: {meshcat.web_url()}  (Ctrl-C to stop)", flush=True)
    try:
        outcome = RunEpisode(simulator, diagram, scene, args.seed)
        print(f"outcome: {outcome.status} after {outcome.time_s:.1f} s")
        if args.wait:
            input("press Enter to close")
    except KeyboardInterrupt:
        print("stopped")
    return 0


def cmd_calibrate(args) -> int:
    from ditch_drake.calibration import CalibrationConfig, run_calibration

    config = CalibrationConfig(trials=args.trials, seed=args.seed, workers=args.workers)
    if args.time_step is not None:
        config.time_step_s = args.time_step
    start = time.perf_counter()
    report = run_calibration(config, args.env or None, progress=not args.json or sys.stderr.isatty())
    report["wall_s"] = time.perf_counter() - start
    text = json.dumps(report, indent=None if args.json else 2)
    print(text)
    return 0 if report["all_ok"] else 1


def cmd_bench(args) -> int:
    from ditch_drake.bench import run_bench

    figures = run_bench(args.env or None, training=args.training)
    if args.json:
        print(json.dumps(figures))
    else:
        _print_table([{"figure": key, "value": f"{value:.3f}"} for key, value in figures.items()], ["figure", "value"])
    return 0


def cmd_collect(args) -> int:
    from ditch_drake.demos.collect import LABELLER_VARIATION, CollectConfig, collect

    config = CollectConfig(environment=args.env, demos=args.demos, seed=args.seed, out=args.out, workers=args.workers)
    config = replace(config, variation=replace(config.variation, lead_in=args.lead_in))
    if args.learner is not None:
        config = replace(config, learner=args.learner, variation=replace(
            LABELLER_VARIATION, replan_each_step=args.labeller == "replanning", lead_in=args.lead_in))
    elif args.labeller != "latched":
        raise ConfigError(f"--labeller {args.labeller}: a labeller needs --learner (a DAgger round)")
    report = collect(config)
    print(json.dumps(report, indent=2))
    return 0 if not report["unfilled_slots"] else 1


def cmd_teleop(args) -> int:
    """A person drives (arrow keys or gamepad in the meshcat page); a success is kept."""
    from pydrake.geometry import StartMeshcat

    from ditch_drake.demos.collect import next_free_demo_path, record_person_demonstration
    from ditch_drake.demos.dataset import save_demonstration

    meshcat = StartMeshcat()
    print(f"meshcat: {meshcat.web_url()}  steer with the arrow keys (or a gamepad) in that tab", flush=True)
    demonstration = record_person_demonstration(args.env, args.task, meshcat, args.seed, args.realtime_rate)
    status = demonstration.metadata["outcome"]["status"]
    if status != "reached_goal":
        print(f"outcome: {status}; not kept")
        return 1
    print(f"outcome: reached_goal; saved {save_demonstration(next_free_demo_path(args.out), demonstration)}")
    return 0


def cmd_dataset_info(args) -> int:
    from ditch_drake.demos.dataset import dataset_summary, load_dataset

    summary = dataset_summary(load_dataset(args.path))
    if args.json:
        print(json.dumps(summary))
        return 0
    print(f"{args.path}: {summary['demonstrations']} demonstrations, {summary['steps']} steps")
    print("per task: " + ", ".join(f"{name} {count}" for name, count in summary["per_task"].items()))
    print("outcomes: " + ", ".join(f"{name} {count}" for name, count in sorted(summary["per_outcome"].items())))
    print("driven by: " + ", ".join(f"{name} {count}" for name, count in summary["per_driver"].items()))
    rows = [{"label": label, "w_radps": f"{rate:+.2f}", "steps": count,
             "share": f"{count / max(1, summary['steps']):.1%}"}
            for label, (rate, count) in enumerate(zip(ANGULAR_RATES_RADPS, summary["per_label"]))]
    _print_table(rows, ["label", "w_radps", "steps", "share"])
    print(f"straight (label 8) share {summary['straight_fraction']:.1%}; "
          f"majority/minority ratio {summary['majority_to_minority_ratio']:.1f}")
    return 0


def cmd_train(args) -> int:
    from ditch_drake.demos.dataset import load_dataset, to_array_set
    from ditch_drake.learning.train import TrainConfig, available_precision, train

    device = _training_device(args.device)  # Before minutes of loading: a bad device fails at once.
    precision = available_precision(device) if args.precision == "auto" else args.precision
    demonstrations = []
    for directory in args.data:  # Several directories train the amalgam model.
        demonstrations += load_dataset(directory, max_demos=args.max_demos)
    defaults = TrainConfig()
    config = TrainConfig(
        epochs=args.epochs, seed=args.seed, patience=args.patience, batch_size=args.batch_size,
        max_batches_per_epoch=args.batches_per_epoch,
        smote=replace(defaults.smote, max_synthetic_fraction=args.synthetic_fraction),
        num_threads=args.threads, device=device, precision=precision)
    result = train(to_array_set(demonstrations), config, output_path=args.out, resume=args.resume)
    best = next((record for record in result.history if record["epoch"] == result.best_epoch), {})
    print(json.dumps({"out": str(result.output_path), "best_epoch": result.best_epoch,
                      "stopped_early": result.stopped_early, "interrupted": result.interrupted,
                      "best": best}, default=float))
    return 130 if result.interrupted else 0


def _training_device(requested: str) -> str:
    import torch

    from ditch_drake.learning.train import available_device

    if requested == "auto":
        return available_device()
    if requested == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: torch sees no CUDA device; use --device cpu or auto")
    return requested


def _controller_config(name: str, checkpoint: str):
    from ditch_drake.diagrams.rollout import DwaBaselineConfig, ExpertConfig, LearnedPolicyConfig
    from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig

    configs = {"learned": lambda: LearnedPolicyConfig(checkpoint=checkpoint), "dwa": DwaBaselineConfig,
               "expert": ExpertConfig, "edge_angle": EdgeAngleDriverConfig,
               "head_on": lambda: EdgeAngleDriverConfig(wall_angle_deg=90.0, climb_angle_deg=None)}
    if name not in configs:
        raise ConfigError(f"unknown controller {name!r}; expected one of {list(configs)}")
    return configs[name]()


def cmd_replay(args) -> int:
    """One seeded rollout recorded as a standalone HTML page (opens offline in any browser)."""
    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.replay import ReplayConfig, record_replay
    from ditch_drake.diagrams.rollout import RolloutConfig
    from ditch_drake.systems.episode_monitor import EpisodeConfig

    scene = SceneConfig(environment=args.env, task=args.task, episode=EpisodeConfig(time_limit_s=args.time_limit))
    config = ReplayConfig(rollout=RolloutConfig(scene=scene, controller=_controller_config(args.controller,
                                                                                           args.checkpoint)),
                          seed=args.seed, out=args.out)
    try:
        result = record_replay(config)
    except OSError as error:  # An unwritable output (ReplayOutputError) or no such checkpoint file.
        print(f"ditch-drake: error: {error}", file=sys.stderr)
        return 2
    outcome = result.outcome
    print(f"{args.controller} in {args.env} task {args.task} seed {args.seed}: {outcome.status} after "
          f"{outcome.time_s:.1f} s, {outcome.path_length_m:.1f} m; wrote {result.html_path} "
          f"({result.html_bytes / 2**20:.1f} MiB, {result.snapshots} lidar snapshots)")
    return 0


def cmd_checkpoint_info(args) -> int:
    """What each checkpoint was trained on and how it validated."""
    from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path

    checkpoints = {name: load_checkpoint(resolve_checkpoint_path(name)) for name in args.checkpoints}
    rows = [{"checkpoint": name, **checkpoint.summary()} for name, checkpoint in checkpoints.items()]
    _print_table(rows, list(rows[0]))
    if args.confusion:
        for name, checkpoint in checkpoints.items():
            matrix = checkpoint.metrics.get("val_confusion_matrix") or []
            print(f"\n{name}: validation confusion matrix (row: demonstrated label, column: predicted)")
            _print_table([{"label": str(label), **{str(j): str(v) for j, v in enumerate(row)}}
                          for label, row in enumerate(matrix)], ["label", *map(str, range(len(matrix)))])
    return 0


def cmd_evaluate(args) -> int:
    """Seeded rollouts of one controller in one or more environments, appended to a results file."""
    from ditch_drake.evaluation.batch import evaluate, load_results, make_specs
    from ditch_drake.evaluation.summary import group_by, summarize

    specs = []
    for environment in args.env or environment_names():
        specs += make_specs(args.controller, args.checkpoint, environment, args.task, args.rollouts, args.seed,
                            args.time_limit)
    report = evaluate(specs, args.out, workers=args.workers, backend=args.backend, address=args.address)
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    keys = {spec.key for spec in specs}
    records = [record for record in load_results([args.out]) if record.key in keys]
    rows = []
    for (controller, checkpoint, environment, task), group in group_by(
            records, "controller", "checkpoint", "environment", "task").items():
        summary = summarize(group)
        rows.append({"controller": controller, "checkpoint": checkpoint or "-", "env": environment, "task": task,
                     "success": f"{summary.successes}/{summary.trials}", "around": summary.around,
                     "wilson95": f"{summary.low:.2f}-{summary.high:.2f}",
                     "failures": " ".join(f"{k}:{v}" for k, v in sorted(summary.failure_regions.items())) or "-",
                     "errors": summary.errors})
    if rows:
        _print_table(rows, ["controller", "checkpoint", "env", "task", "success", "around", "wilson95", "failures",
                            "errors"])
    print(json.dumps({"out": str(args.out), "skipped": report.skipped, "recorded": report.recorded,
                      "successes_recorded": report.successes, "errors_recorded": report.errors,
                      "wall_s": round(report.wall_s, 1), "rollouts_per_minute": round(report.rollouts_per_minute, 2),
                      "interrupted": report.interrupted}))
    return 130 if report.interrupted else 0


def cmd_experiment(args) -> int:
    """The paper's pipeline from an experiment file: collect, train, evaluate, report."""
    from ditch_drake.evaluation.experiment import load_experiment, run_experiment

    config = load_experiment(args.file)
    stages = tuple(args.stage) if args.stage else ("collect", "train", "evaluate", "report")
    try:
        command = " ".join(["ditch-drake experiment", str(args.file)] + [f"--only {env}" for env in args.only or []]
                           + [f"--stage {stage}" for stage in args.stage or []])
        timings = run_experiment(config, only=args.only, stages=stages, command=command)
    except KeyboardInterrupt:
        print("interrupted; finished work is kept, run the same command again to continue", file=sys.stderr)
        return 130
    print(json.dumps({name: round(value, 1) for name, value in timings.items()}))
    return 0


def cmd_report(args) -> int:
    """The results page and its figures from results files."""
    from ditch_drake.evaluation.report import write_report

    command = "ditch-drake report " + " ".join(args.results) + f" --out {args.out} --figures {args.figures}"
    if args.title != "Results":
        command += f" --title {shlex.quote(args.title)}"
    print(write_report(args.results, args.out, args.figures, title=args.title, command=command))
    return 0


def cmd_figure(args) -> int:
    from ditch_drake.figures import diagram_figure, normal_image_figure

    if args.kind == "diagram":
        print(diagram_figure(args.out))
        return 0
    if args.kind == "screenshot":
        from pathlib import Path

        from ditch_drake.browser import screenshot

        print(screenshot(args.html, Path(args.out) / f"{Path(args.html).stem}.png"))
        return 0
    if args.kind == "dwa":
        from ditch_drake.baseline import dwa_figure

        for name in environment_names() if not args.env or "all" in args.env else args.env:
            print(dwa_figure(name, args.out, task=0, seed=args.seed))
        return 0
    for name in args.env or environment_names():
        print(normal_image_figure(name, args.out, args.seed))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ditch-drake", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    def add_env(sub, many=False):
        if many:
            sub.add_argument("--env", action="append", metavar="NAME",
                             help=f"environment (repeatable; default: all of {environment_names()})")
        else:
            sub.add_argument("--env", default="wide", metavar="NAME", help=f"one of {environment_names()}")

    demo = commands.add_parser("demo", help="the main job: shipped policy, DWA baseline and a head-on driver "
                                             "through a ditch; outcome table and an HTML recording")
    add_env(demo)
    demo.add_argument("--task", type=int, default=1)
    # Seed 0 of this task is the one evaluation rollout (of 30) in which the shipped Wide policy
    # rolls over (docs/learning.md); the main job shows a typical crossing, and says so in the README.
    demo.add_argument("--seed", type=int, default=1)
    demo.add_argument("--checkpoint", default=None, help="the learned policy (default: the environment's shipped model)")
    demo.add_argument("--html", default="results/demo.html", help="where the recording goes")
    demo.set_defaults(run=cmd_demo)

    view = commands.add_parser("view", help="open the scene in meshcat and drive through it")
    add_env(view)
    view.add_argument("--task", type=int, default=0)
    view.add_argument("--seed", type=int, default=0)
    view.add_argument("--realtime-rate", type=float, default=1.0)
    view.add_argument("--wait", action="store_true", help="keep meshcat open until Enter")
    view.set_defaults(run=cmd_view)

    calibrate = commands.add_parser("calibrate", help="the physics calibration benchmark (exit 1 if it falls short)")
    add_env(calibrate, many=True)
    calibrate.add_argument("--json", action="store_true", help="one JSON object on stdout")
    calibrate.add_argument("--trials", type=int, default=10)
    calibrate.add_argument("--seed", type=int, default=0)
    calibrate.add_argument("--workers", type=int, default=0, help="processes (0: one per core)")
    calibrate.add_argument("--time-step", type=float, default=None, help="plant step in s (default: the scene's)")
    calibrate.set_defaults(run=cmd_calibrate)

    collect = commands.add_parser("collect", help="record expert demonstrations (resumable)")
    add_env(collect)
    collect.add_argument("--demos", type=int, default=40)
    collect.add_argument("--seed", type=int, default=0)
    collect.add_argument("--out", required=True, help="directory of demo_NNN.npz files")
    collect.add_argument("--workers", type=int, default=0, help="processes (0: one per core)")
    collect.add_argument("--learner", default=None, metavar="CHECKPOINT",
                         help="DAgger: this policy drives, the expert labels; every rollout is kept "
                              "(--demos rollouts, one per seed)")
    collect.add_argument("--labeller", choices=["latched", "replanning"], default="latched",
                         help="with --learner: the expert keeps the plan it chose before the wall (latched) "
                              "or decides it afresh from the current pose every step (replanning)")
    collect.add_argument("--lead-in", action="store_true",
                         help="the expert first makes room along the ditch when the crossing would not fit "
                              "before the ditch's end (EdgeAngleDriverConfig.lead_in)")
    collect.set_defaults(run=cmd_collect)

    teleop = commands.add_parser("teleop", help="record your own demonstration: steer in meshcat")
    add_env(teleop)
    teleop.add_argument("--task", type=int, default=0)
    teleop.add_argument("--seed", type=int, default=0)
    teleop.add_argument("--out", required=True, help="directory of demo_NNN.npz files")
    teleop.add_argument("--realtime-rate", type=float, default=1.0)
    teleop.set_defaults(run=cmd_teleop)

    info = commands.add_parser("dataset-info", help="counts per label and task, class imbalance")
    info.add_argument("path", help="a directory of demonstrations")
    info.add_argument("--json", action="store_true")
    info.set_defaults(run=cmd_dataset_info)

    replay = commands.add_parser("replay", help="record one rollout as a standalone HTML page (meshcat animation)")
    replay.add_argument("--controller", default="learned", choices=["expert", "learned", "dwa", "edge_angle", "head_on"],
                        help="the learned policy (default; --checkpoint picks it), the scripted expert, the DWA "
                             "baseline, or a scripted edge-angle / head-on driver")
    replay.add_argument("--checkpoint", default="wide", help="the learned policy: a shipped name or a .pt file")
    add_env(replay)
    replay.add_argument("--task", type=int, default=1)
    replay.add_argument("--seed", type=int, default=0)
    replay.add_argument("--time-limit", type=float, default=120.0, help="episode timeout (s)")
    replay.add_argument("--out", default="results/replay.html")
    replay.set_defaults(run=cmd_replay)

    info = commands.add_parser("checkpoint-info", help="training data and validation metrics of checkpoints")
    info.add_argument("checkpoints", nargs="+", help="shipped model names or .pt files")
    info.add_argument("--confusion", action="store_true", help="also the validation confusion matrices")
    info.set_defaults(run=cmd_checkpoint_info)

    evaluation = commands.add_parser("evaluate", help="seeded rollouts in parallel, appended to a results file")
    evaluation.add_argument("--controller", default="learned", help="learned, dwa, expert or edge_angle")
    evaluation.add_argument("--checkpoint", default="wide", help="the learned policy: a shipped name or a .pt file")
    add_env(evaluation, many=True)
    evaluation.add_argument("--task", type=int, action="append", default=None, help="task index (repeatable; default all)")
    evaluation.add_argument("--rollouts", type=int, default=10, help="seeded rollouts per task")
    evaluation.add_argument("--seed", type=int, default=0, help="first seed; rollout i uses seed + i")
    evaluation.add_argument("--time-limit", type=float, default=120.0, help="episode timeout (s)")
    evaluation.add_argument("--out", default="results/evaluate.jsonl", help="results file (JSON Lines), appended")
    evaluation.add_argument("--workers", type=int, default=None, help="worker processes (default: all cores)")
    evaluation.add_argument("--backend", default="local", choices=["local", "ray"],
                            help="local process pool, or a Ray cluster (pip install -e '.[ray]')")
    evaluation.add_argument("--address", default=None, help="Ray cluster address (default: start Ray here)")
    evaluation.set_defaults(run=cmd_evaluate)

    experiment = commands.add_parser("experiment", help="the paper's pipeline from an experiment YAML")
    experiment.add_argument("file", help="experiment file, e.g. experiments/paper.yaml")
    experiment.add_argument("--only", action="append", metavar="ENV",
                            help="only the models and evaluations that involve this environment (repeatable)")
    experiment.add_argument("--stage", action="append", choices=["collect", "train", "evaluate", "report"],
                            help="run only this stage (repeatable; default all, in order)")
    experiment.set_defaults(run=cmd_experiment)

    report = commands.add_parser("report", help="results page (Markdown) and figures from results files")
    report.add_argument("results", nargs="+", help="results files or folders of them (*.jsonl)")
    report.add_argument("--out", default="docs/results.md")
    report.add_argument("--figures", default="docs/img", help="folder of the PNG figures")
    report.add_argument("--title", default="Results")
    report.set_defaults(run=cmd_report)

    training = commands.add_parser("train", help="behavioural cloning from demonstrations")
    training.add_argument("--data", action="append", required=True, metavar="DIR",
                          help="demonstration directory (repeat for an amalgam of environments)")
    training.add_argument("--out", required=True, help="checkpoint path (.pt)")
    training.add_argument("--seed", type=int, default=0)
    training.add_argument("--max-demos", type=int, default=None, help="use the first N demonstrations of each directory")
    from ditch_drake.learning.train import TrainConfig

    defaults = TrainConfig()
    training.add_argument("--epochs", type=int, default=defaults.epochs)
    training.add_argument("--patience", type=int, default=defaults.patience)
    training.add_argument("--batch-size", type=int, default=defaults.batch_size)
    training.add_argument("--batches-per-epoch", type=int, default=defaults.max_batches_per_epoch,
                          help="batches drawn (without replacement) from the shuffled training set per epoch")
    training.add_argument("--synthetic-fraction", type=float, default=defaults.smote.max_synthetic_fraction,
                          help="at most this many SMOTE samples per real training sample")
    training.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    training.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                          help="auto: CUDA when torch sees a GPU, else the CPU (a CUDA run is not bitwise "
                               "reproducible on the CPU)")
    training.add_argument("--precision", choices=["auto", "fp32", "bf16"], default="auto",
                          help="bf16: training steps under bfloat16 autocast; auto: bf16 on a CPU with native "
                               "bf16 (AVX512-BF16 or AMX), else fp32")
    training.add_argument("--resume", action="store_true", help="continue an interrupted run")
    training.set_defaults(run=cmd_train)

    figure = commands.add_parser("figure", help="figures for docs/: surface-normal images per environment, the diagram, "
                                 "the DWA baseline at the ditch")
    figure.add_argument("kind", choices=["normal-images", "diagram", "screenshot", "dwa"])
    figure.add_argument("--html", default="results/demo.html", help="screenshot: the recording to open in Chromium")
    add_env(figure, many=True)
    figure.add_argument("--out", default="docs/img")
    figure.add_argument("--seed", type=int, default=0)
    figure.set_defaults(run=cmd_figure)

    bench = commands.add_parser("bench", help="speed and memory figures")
    add_env(bench, many=True)
    bench.add_argument("--json", action="store_true", help="one JSON object on stdout")
    bench.add_argument("--training", action="store_true",
                       help="also the training pipeline's peak memory on a synthetic 40-demo set (minutes)")
    bench.set_defaults(run=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (ConfigError, TerrainError, DatasetError, CheckpointError, ResultsError) as error:
        print(f"ditch-drake: error: {error}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`ditch-drake dataset-info ... | head`): stop quietly, and keep
        # Python's exit-time flush of stdout from raising again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
