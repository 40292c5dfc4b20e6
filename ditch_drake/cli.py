"""The `ditch-drake` command line.

Every command's heavy imports (Drake, torch) happen inside the command, so that the parser
and every `--help` answer at once. A user's mistake (a bad value, a bad file) ends in exit
code 2 and one line `ditch-drake: error: ...`; Ctrl-C ends in 130 and SIGTERM in 143, after
the command has kept what finished.
"""

import argparse
import json
import os
import shlex
import sys
import time

from ditch_drake.common.errors import ConfigError, ResultsError, TerrainError
from ditch_drake.common.parallel import check_workers, interrupt_exit_code, terminate_as_interrupt
from ditch_drake.common.seeds import check_seed
from ditch_drake.diagrams.controllers import controller_descriptions, controller_names

# The single-episode commands (demo, replay, view, teleop) share these defaults. Seed 0 of the
# wide ditch's task 1 is the one evaluation rollout (of 30) in which the shipped Wide policy
# rolls over (docs/learning.md); the defaults show a typical crossing, and the README says so.
DEFAULT_ENVIRONMENT = "wide"
DEFAULT_TASK = 1
DEFAULT_SEED = 1


def _user_errors() -> tuple[type[Exception], ...]:
    from ditch_drake.demos.dataset import DatasetError
    from ditch_drake.learning.checkpoint import CheckpointError

    return ConfigError, TerrainError, DatasetError, CheckpointError, ResultsError


def _print_table(rows: list[dict], columns: list[str], file=None) -> None:
    widths = [max(len(column), *(len(str(row[column])) for row in rows)) for column in columns]
    print("  ".join(column.ljust(width) for column, width in zip(columns, widths)), file=file)
    for row in rows:
        print("  ".join(str(row[column]).ljust(width) for column, width in zip(columns, widths)), file=file)


def _checkpoint_for(args, environment: str) -> str:
    """The learned policy's checkpoint: --checkpoint, else the environment's shipped model."""
    from ditch_drake.learning.checkpoint import environment_model

    return args.checkpoint or environment_model(environment, getattr(args, "environments", None) or "")


def _check_task(environment: str, task: int, environments_file: str = "") -> None:
    from ditch_drake.world.environments import get_environment

    tasks = get_environment(environment, environments_file or None).tasks
    if not 0 <= task < len(tasks):
        raise ConfigError(f"--task {task}: {environment!r} has tasks 0..{len(tasks) - 1} "
                          f"({', '.join(f'{i} {t.name}' for i, t in enumerate(tasks))})")


def _scenario(args, default_controller: str = "learned"):
    """The Scenario of a single-episode command: the defaults, then --scenario FILE (and
    --scenario-name), then the options given on the command line, then --override."""
    from dataclasses import replace

    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.diagrams.scenario import Scenario, check_scenario, load_scenario

    scenario = load_scenario(args.scenario, args.scenario_name) if args.scenario else Scenario(
        controller=controller_config(default_controller))
    for option, name in (("env", "environment"), ("task", "task"), ("seed", "seed"),
                         ("environments", "environments_file")):
        value = getattr(args, option, None)
        if value is not None:  # evaluate's --env and --task repeat: the scenario takes the first.
            scenario = replace(scenario, **{name: value[0] if isinstance(value, list) else value})
    if getattr(args, "controller", None) is not None:
        scenario = replace(scenario, controller=controller_config(args.controller))
    if getattr(args, "checkpoint", None) and hasattr(scenario.controller, "checkpoint"):
        scenario = replace(scenario, controller=replace(scenario.controller, checkpoint=args.checkpoint))
    if getattr(args, "time_limit", None) is not None:
        scenario = replace(scenario, episode=replace(scenario.episode, time_limit_s=args.time_limit))
    if args.override:
        scenario = load_scenario(override=args.override, defaults=scenario)
    check_scenario(scenario)
    if getattr(scenario.controller, "checkpoint", None) == "":  # Named, so that records and pages say which.
        from ditch_drake.learning.checkpoint import environment_model

        scenario = replace(scenario, controller=replace(scenario.controller,
                                                        checkpoint=environment_model(
                                                            scenario.environment, scenario.environments_file)))
    return scenario


def _controller_label(scenario, name: str | None = None) -> str:
    """The controller's registered name (the one asked for, where several share a config type)."""
    from ditch_drake.diagrams.controllers import entry_for_config

    name = name or entry_for_config(scenario.controller).name
    checkpoint = getattr(scenario.controller, "checkpoint", None)
    return name if checkpoint is None else f"{name} ({checkpoint})"


def cmd_scenario(args) -> int:
    """Prints a Scenario as YAML: the default one (a template), or the one the options make."""
    from ditch_drake.diagrams.scenario import scenario_yaml

    print(scenario_yaml(_scenario(args)), end="")
    return 0


def cmd_demo(args) -> int:
    """The main job: the shipped policy, the DWA baseline and a head-on driver through one ditch;
    an outcome table and the policy's rollout as a standalone HTML page."""
    _check_task(args.env, args.task, args.environments)
    check_seed(args.seed)
    checkpoint = _checkpoint_for(args, args.env)
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.replay import ReplayConfig, record_replay
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig, RunEpisode

    scene = SceneConfig(environment=args.env, task=args.task, environments_file=args.environments or "")
    rows = []

    def row(name, outcome, wall_s):
        rows.append({"controller": name, "outcome": outcome.status, "sim_time_s": f"{outcome.time_s:.1f}",
                     "path_m": f"{outcome.path_length_m:.1f}", "peak_tilt_deg": f"{outcome.peak_tilt_deg:.0f}",
                     "wall_s": f"{wall_s:.1f}"})

    print(f"[1/3] learned policy ({checkpoint} model), recorded as {args.html}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    replay = record_replay(ReplayConfig(
        rollout=RolloutConfig(scene=scene, controller=controller_config("learned", checkpoint, args.seed)),
        seed=args.seed, out=args.html), progress="learned policy")
    row(f"learned policy ({checkpoint} model)", replay.outcome, time.perf_counter() - start)
    for step, (name, controller) in enumerate((("DWA baseline (move_base-style)", "dwa"),
                                               ("head-on scripted driver (reference)", "head_on")), start=2):
        print(f"[{step}/3] {name}", file=sys.stderr, flush=True)
        start = time.perf_counter()
        diagram, built = MakeRolloutDiagram(RolloutConfig(scene=scene,
                                                          controller=controller_config(controller, "", args.seed)))
        row(name, RunEpisode(Simulator(diagram), diagram, built, args.seed, progress=controller),
            time.perf_counter() - start)
    print(f"environment {args.env}, task {args.task} ({built.task.name}), seed {args.seed}")
    _print_table(rows, ["controller", "outcome", "sim_time_s", "path_m", "peak_tilt_deg", "wall_s"])
    print(f"recording of the learned policy's rollout: {replay.html_path} (open it in any browser)")
    return 0


def cmd_view(args) -> int:
    """Opens the scene in meshcat and drives it in real time (the scripted driver unless told otherwise)."""
    scenario = _scenario(args, default_controller="edge_angle")
    from pydrake.geometry import StartMeshcat
    from pydrake.systems.analysis import ApplySimulatorConfig, Simulator

    from ditch_drake.diagrams.rollout import RunEpisode
    from ditch_drake.diagrams.scenario import MakeScenarioDiagram

    meshcat = StartMeshcat()
    diagram, scene = MakeScenarioDiagram(scenario, meshcat=meshcat)
    simulator = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator, simulator)
    simulator.set_target_realtime_rate(args.realtime_rate)
    print(f"meshcat: open {meshcat.web_url()} to watch  (Ctrl-C to stop)", flush=True)
    outcome = RunEpisode(simulator, diagram, scene, scenario.seed)
    print(f"outcome: {outcome.status} after {outcome.time_s:.1f} s")
    if args.wait:
        input("press Enter to close")
    return 0


def cmd_calibrate(args) -> int:
    check_workers(args.workers, "--workers")
    if args.trials < 1:
        raise ConfigError(f"--trials {args.trials}: expected >= 1 (seeded trials per driven case)")
    check_seed(args.seed, args.trials)
    from ditch_drake.validation.calibration import CalibrationConfig, run_calibration

    config = CalibrationConfig(trials=args.trials, seed=args.seed, workers=args.workers,
                               environments_file=args.environments or "")
    if args.time_step is not None:
        if not args.time_step > 0:
            raise ConfigError(f"--time-step {args.time_step}: expected a positive plant step in s")
        config.time_step_s = args.time_step
    start = time.perf_counter()
    report = run_calibration(config, args.env or None, progress=not args.json or sys.stderr.isatty())
    report["wall_s"] = time.perf_counter() - start
    text = json.dumps(report, indent=None if args.json else 2)
    print(text)
    return 0 if report["all_ok"] else 1


def cmd_bench(args) -> int:
    from ditch_drake.perf.bench import run_bench

    figures = run_bench(args.env or None, training=args.training, environments_file=args.environments or "")
    if args.json:
        print(json.dumps(figures))
    else:
        _print_table([{"figure": key, "value": f"{value:.3f}"} for key, value in figures.items()], ["figure", "value"])
    return 0


def cmd_collect(args) -> int:
    check_workers(args.workers, "--workers")
    check_seed(args.seed, args.demos if args.demos > 0 else 1)
    if args.learner is None and args.labeller != "latched":
        raise ConfigError(f"--labeller {args.labeller}: a labeller needs --learner (a DAgger round)")
    from dataclasses import replace

    from ditch_drake.demos.collect import LABELLER_VARIATION, CollectConfig, collect

    config = CollectConfig(environment=args.env, demos=args.demos, seed=args.seed, out=args.out, workers=args.workers,
                           environments_file=args.environments or "")
    config = replace(config, variation=replace(config.variation, lead_in=args.lead_in))
    if args.learner is not None:
        config = replace(config, learner=args.learner, variation=replace(
            LABELLER_VARIATION, replan_each_step=args.labeller == "replanning", lead_in=args.lead_in))
    report = collect(config)
    print(json.dumps(report, indent=2))
    if report["interrupted"]:
        print(f"interrupted: {report['recorded']} demonstrations recorded by this run, "
              f"{report['kept_before'] + report['recorded']} of {args.demos} in {args.out}; "
              "run the same command again to continue", file=sys.stderr)
        return report["exit_code"]
    return 0 if not report["unfilled_slots"] else 1


def cmd_teleop(args) -> int:
    """A person drives (arrow keys or gamepad in the meshcat page); a success is kept."""
    _check_task(args.env, args.task, args.environments)
    check_seed(args.seed)
    from pydrake.geometry import StartMeshcat

    from ditch_drake.demos.collect import next_free_demo_path, record_person_demonstration
    from ditch_drake.demos.dataset import save_demonstration

    meshcat = StartMeshcat()
    print(f"meshcat: open {meshcat.web_url()} and steer with the arrow keys (or a gamepad) in that tab", flush=True)
    demonstration = record_person_demonstration(args.env, args.task, meshcat, args.seed, args.realtime_rate,
                                                args.environments or "")
    status = demonstration.metadata["outcome"]["status"]
    if status != "reached_goal":
        print(f"outcome: {status}; not kept")
        return 1
    print(f"outcome: reached_goal; saved {save_demonstration(next_free_demo_path(args.out), demonstration)}")
    return 0


def cmd_dataset_info(args) -> int:
    from ditch_drake.demos.dataset import dataset_summary, load_dataset
    from ditch_drake.spec.actions import ANGULAR_RATES_RADPS

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
    from dataclasses import replace

    from ditch_drake.learning.config import TrainConfig

    # Every setting is checked here, before minutes of loading: a bad value fails at once.
    config = TrainConfig.from_options(
        epochs=args.epochs, seed=args.seed, patience=args.patience, batch_size=args.batch_size,
        max_batches_per_epoch=args.batches_per_epoch, synthetic_fraction=args.synthetic_fraction,
        num_threads=args.threads)
    if args.max_demos is not None and args.max_demos < 1:
        raise ConfigError(f"--max-demos {args.max_demos}: expected >= 1 demonstrations per directory")
    from ditch_drake.demos.dataset import load_dataset, to_array_set
    from ditch_drake.learning.train import available_precision, train

    from ditch_drake.pipelines.stages import training_device

    device = training_device(args.device)
    precision = available_precision(device) if args.precision == "auto" else args.precision
    config = replace(config, device=device, precision=precision)
    demonstrations = []
    for directory in args.data:  # Several directories train the amalgam model.
        demonstrations += load_dataset(directory, max_demos=args.max_demos)
    result = train(to_array_set(demonstrations), config, output_path=args.out, resume=args.resume)
    best = next((record for record in result.history if record["epoch"] == result.best_epoch), {})
    print(json.dumps({"out": str(result.output_path) if result.output_path else None,
                      "resume_file": str(result.resume_file) if result.resume_file else None,
                      "best_epoch": result.best_epoch, "stopped_early": result.stopped_early,
                      "interrupted": result.interrupted, "best": best}, default=float))
    if result.interrupted:
        print("interrupted: " + (f"the best finished epoch is in {result.output_path}" if result.output_path
                                 else "no epoch had finished, so no checkpoint was written")
              + (f"; --resume continues from {result.resume_file}" if result.resume_file else ""), file=sys.stderr)
        return result.exit_code
    return 0


def cmd_replay(args) -> int:
    """One seeded rollout recorded as a standalone HTML page (opens offline in any browser)."""
    if args.time_limit is not None and not args.time_limit > 0:
        raise ConfigError(f"--time-limit {args.time_limit}: expected a positive episode timeout in s")
    if args.seed is not None:
        check_seed(args.seed)
    scenario = _scenario(args)
    from ditch_drake.diagrams.replay import ReplayConfig, record_replay

    label = _controller_label(scenario, args.controller)
    config = ReplayConfig(rollout=scenario.rollout_config(), seed=scenario.seed, out=args.out)
    try:
        result = record_replay(config, progress=label.split(" ")[0])
    except OSError as error:  # An unwritable output (ReplayOutputError) or no such checkpoint file.
        print(f"ditch-drake: error: {error}", file=sys.stderr)
        return 2
    outcome = result.outcome
    print(f"{label} in {scenario.environment} task {scenario.task} seed {scenario.seed}: {outcome.status} after "
          f"{outcome.time_s:.1f} s, {outcome.path_length_m:.1f} m; wrote {result.html_path} "
          f"({result.html_bytes / 2**20:.1f} MiB, {result.snapshots} lidar snapshots)")
    return 0


def cmd_checkpoint_info(args) -> int:
    """What each checkpoint was trained on and how it validated."""
    from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path

    checkpoints = {name: load_checkpoint(resolve_checkpoint_path(name), allow_untrained=True)
                   for name in args.checkpoints}
    rows = [{"checkpoint": name, **checkpoint.summary()} for name, checkpoint in checkpoints.items()]
    _print_table(rows, list(rows[0]))
    if args.confusion:
        for name, checkpoint in checkpoints.items():
            matrix = checkpoint.metrics.get("val_confusion_matrix") or []
            print(f"\n{name}: validation confusion matrix (row: demonstrated label, column: predicted)")
            _print_table([{"label": str(label), **{str(j): str(v) for j, v in enumerate(row)}}
                          for label, row in enumerate(matrix)], ["label", *map(str, range(len(matrix)))])
    return 0


def _evaluation_exit_code(report, out) -> int:
    """0, or the interrupt's exit code after saying how far a stopped run got and how to go on."""
    if report.interrupted:
        print(f"interrupted: {report.recorded} rollouts recorded by this run, {report.skipped + report.recorded} of "
              f"{report.requested} in {out}; run the same command again to continue", file=sys.stderr)
        return report.exit_code
    return 0


def cmd_evaluate(args) -> int:
    """Seeded rollouts of one controller in one or more environments, appended to a results file."""
    check_workers(args.workers, "--workers")
    from ditch_drake.evaluation.batch import evaluate, load_results, make_specs
    from ditch_drake.evaluation.results import current_records
    from ditch_drake.evaluation.summary import group_by, summarize
    from ditch_drake.world.environments import environment_names, get_environment

    controller, environments_file, time_limit_s = args.controller or "learned", args.environments or "", 120.0
    if args.scenario or args.override:
        # The scenario gives the controller's full config, the environments file and the episode's limit.
        scenario = _scenario(args)
        if scenario.environments and not args.env:
            raise ConfigError("evaluate runs environments from a file: put the scenario's inline environments in a "
                              "YAML file and pass --environments FILE --env NAME")
        controller, environments_file = scenario.controller, scenario.environments_file
        time_limit_s = scenario.episode.time_limit_s
        environments = args.env or [scenario.environment]
    else:
        environments = args.env or ([] if environments_file else environment_names())
        if not environments:
            from ditch_drake.world.environments import load_environments

            environments = list(load_environments(environments_file))
    if args.time_limit is not None:
        time_limit_s = args.time_limit
    specs, plan = [], []
    for environment in environments:
        get_environment(environment, environments_file or None)  # A bad file or name first, before its model.
        checkpoint = _checkpoint_for(args, environment) if controller == "learned" else ""
        specs += make_specs(controller, checkpoint, environment, args.task, args.rollouts, args.seed, time_limit_s,
                            environments_file)
        tasks = len(args.task) if args.task else len(get_environment(environment, environments_file or None).tasks)
        plan.append(f"{environment}: {tasks} tasks x {args.rollouts} rollouts = {tasks * args.rollouts}")
    print(f"{specs[0].controller}: " + "; ".join(plan) + f" (seeds {args.seed}..{args.seed + args.rollouts - 1})",
          file=sys.stderr, flush=True)
    report = evaluate(specs, args.out, workers=args.workers, backend=args.backend, address=args.address)
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    keys = {spec.key for spec in specs}
    records, _ = current_records([record for record in load_results([args.out]) if record.key in keys])
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
    print(json.dumps({"out": str(args.out), "requested": report.requested, "skipped": report.skipped,
                      "recorded": report.recorded, "successes_recorded": report.successes,
                      "errors_recorded": report.errors, "wall_s": round(report.wall_s, 1),
                      "rollouts_per_minute": round(report.rollouts_per_minute, 2),
                      "interrupted": report.interrupted}))
    return _evaluation_exit_code(report, args.out)


def cmd_experiment(args) -> int:
    """The paper's pipeline from an experiment file: collect, train, evaluate, report."""
    from ditch_drake.pipelines.experiment import load_experiment, run_experiment

    config = load_experiment(args.file)
    stages = tuple(args.stage) if args.stage else ("collect", "train", "evaluate", "report")
    command = " ".join(["ditch-drake experiment", str(args.file)] + [f"--only {env}" for env in args.only or []]
                       + [f"--study {study}" for study in args.study or []]
                       + [f"--stage {stage}" for stage in args.stage or []])
    try:
        timings = run_experiment(config, only=args.only, stages=stages, command=command, only_studies=args.study)
    except KeyboardInterrupt as error:
        print("interrupted; finished work is kept, run the same command again to continue", file=sys.stderr)
        return interrupt_exit_code(error)
    print(json.dumps({name: round(value, 1) for name, value in timings.items()}))
    return 0


def cmd_benchmark(args) -> int:
    """A controller over a split's procedural ditches (or the paper's four), appended to a results file."""
    check_workers(args.workers, "--workers")
    from ditch_drake.benchmark.run import BenchmarkConfig, benchmark_specs, run_benchmark
    from ditch_drake.benchmark.splits import check_split
    from ditch_drake.evaluation.batch import load_results
    from ditch_drake.evaluation.results import current_records
    from ditch_drake.evaluation.summary import summarize

    check_split(args.split)
    check_seed(args.seed, max(1, args.rollouts))
    config = BenchmarkConfig(split=args.split, controller=args.controller, checkpoint=args.checkpoint or "",
                             geometries=args.geometries, rollouts=args.rollouts, seed=args.seed, out=args.out,
                             ranges=args.ranges or "", time_limit_s=args.time_limit, workers=args.workers,
                             backend=args.backend, address=args.address)
    if args.rollouts < 1:
        raise ConfigError(f"--rollouts {args.rollouts}: expected a positive integer")
    specs = benchmark_specs(config)
    environments = sorted({spec.environment for spec in specs})
    print(f"{specs[0].controller} on split {args.split}: {len(environments)} ditches x 3 tasks x {args.rollouts} "
          f"rollouts = {len(specs)} (seeds {args.seed}..{args.seed + args.rollouts - 1})", file=sys.stderr, flush=True)
    report = run_benchmark(config, specs=specs)
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    keys = {spec.key for spec in specs}
    records, _ = current_records([record for record in load_results([args.out]) if record.key in keys])
    summary = summarize(records) if records else None
    print(json.dumps({"out": str(args.out), "split": args.split, "controller": specs[0].controller,
                      "checkpoint": specs[0].checkpoint, "geometries": len(environments),
                      "requested": report.requested, "skipped": report.skipped, "recorded": report.recorded,
                      "successes": summary.successes if summary else 0, "trials": summary.trials if summary else 0,
                      "wilson95": [round(summary.low, 3), round(summary.high, 3)] if summary else None,
                      "errors_recorded": report.errors, "wall_s": round(report.wall_s, 1),
                      "rollouts_per_minute": round(report.rollouts_per_minute, 2), "interrupted": report.interrupted}))
    return _evaluation_exit_code(report, args.out)


def cmd_benchmark_report(args) -> int:
    """The benchmark's page: success per split and controller, against the ditch's parameters,
    failure regions and the failed geometries with their replay commands."""
    from pathlib import Path

    from ditch_drake.benchmark.results_page import write_benchmark_report

    missing = [entry for entry in args.results if not Path(entry).exists()]
    if missing:
        raise ConfigError(f"no results file at {', '.join(missing)}")
    page = write_benchmark_report(args.results, args.out, args.figures, title=args.title,
                                  command="ditch-drake " + " ".join(shlex.quote(a) for a in sys.argv[1:]))
    print(f"wrote {page}", file=sys.stderr)
    return 0


def cmd_train_generalist(args) -> int:
    """The generalist: demonstrations and DAgger over the train split, the best round on val."""
    check_workers(args.workers, "--workers")
    check_seed(args.seed)
    from ditch_drake.pipelines.generalist import GeneralistConfig, train_generalist
    from ditch_drake.benchmark.splits import split_seeds

    split_seeds("train", args.train_geometries)
    split_seeds("val", args.val_geometries)
    config = GeneralistConfig(out=args.out, work_dir=args.work_dir, train_geometries=args.train_geometries,
                              demos_per_task=args.demos_per_task, dagger_rounds=args.dagger_rounds,
                              val_geometries=args.val_geometries, dagger_stride=args.dagger_stride,
                              epochs=args.epochs, seed=args.seed, mirror=args.mirror,
                              canonical_side=args.canonical_side, workers=args.workers,
                              ranges=args.ranges or "", train_ranges=args.train_ranges or "")
    try:
        summary = train_generalist(config)
    except KeyboardInterrupt as error:
        print("interrupted; finished stages are kept, run the same command again to continue", file=sys.stderr)
        return interrupt_exit_code(error)
    print(json.dumps(summary))
    return 0


def cmd_report(args) -> int:
    """The results page and its figures from the current records of results files, its success
    tables also printed; by default beside the results, and never over a file git tracks unless
    `--out` / `--figures` names it."""
    from pathlib import Path

    from ditch_drake.evaluation.report import (
        default_outputs,
        figures_beside,
        load_report_data,
        tracked_by_git,
        write_report,
    )

    missing = [entry for entry in args.results if not Path(entry).exists()]
    if missing:
        print(f"ditch-drake: error: no results file or folder at {', '.join(missing)}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else default_outputs(args.results)[0]
    figures = Path(args.figures) if args.figures else figures_beside(out)
    for path, flag, given in ((out, "--out", args.out), (figures, "--figures", args.figures)):
        if not given and tracked_by_git(path):
            print(f"ditch-drake: error: the default {flag} {path} is tracked by git: name it with {flag} to "
                  "overwrite it, or choose another path", file=sys.stderr)
            return 2
    data = load_report_data(args.results)
    for note in data.notes:
        print(f"note: {note}", file=sys.stderr)
    command = shlex.join(["ditch-drake", "report", *map(str, args.results), "--out", str(out), "--figures",
                          str(figures), *(["--title", args.title] if args.title != "Results" else [])])
    page = write_report(args.results, out, figures, title=args.title, command=command, data=data)
    print(data.markdown_tables())
    print(f"wrote {page} (figures in {figures})")
    return 0


def cmd_figure(args) -> int:
    from ditch_drake.docs_tools.figures import diagram_figure, normal_image_figure
    from ditch_drake.world.environments import environment_names

    if args.kind == "diagram":
        print(diagram_figure(args.out))
        return 0
    if args.kind == "cost-curves":
        from ditch_drake.docs_tools.figures import cost_curve_figure

        print(cost_curve_figure(args.out))
        return 0
    if args.kind == "screenshot":
        from pathlib import Path

        from ditch_drake.docs_tools.browser import screenshot

        print(screenshot(args.html, Path(args.out) / f"{Path(args.html).stem}.png"))
        return 0
    if args.kind == "dwa":
        from ditch_drake.docs_tools.baseline_page import dwa_figure

        for name in environment_names() if not args.env or "all" in args.env else args.env:
            print(dwa_figure(name, args.out, task=0, seed=args.seed))
        return 0
    if args.kind == "mppi":
        from ditch_drake.docs_tools.mppi_figure import mppi_figure

        for name in args.env or ["wide_walled"]:
            print(mppi_figure(name, args.out, task=1, seed=args.seed))
        return 0
    for name in args.env or environment_names():
        print(normal_image_figure(name, args.out, args.seed))
    return 0


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows every option's default (unless its help already says it), and keeps the
    environments list of the epilogs as written."""

    def _get_help_string(self, action):
        if "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)


def _environments_epilog() -> str:
    """The packaged environments and their tasks, by index and name."""
    from ditch_drake.world.environments import load_environments

    lines = ["environments and their tasks (--env NAME --task INDEX):"]
    # Read without proving the walls (`get_environment` does that when one is used): --help stays quick.
    for name, environment in load_environments(prove_walls=False).items():
        tasks = environment.tasks
        lines.append(f"  {name}: " + ", ".join(f"{index} {task.name}" for index, task in enumerate(tasks)))
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    from ditch_drake.pipelines.experiment import study_names
    from ditch_drake.learning.config import TrainConfig
    from ditch_drake.world.environments import environment_names

    environments, variants = environment_names(), environment_names(variants=True)
    epilog = _environments_epilog()
    parser = _Parser(prog="ditch-drake", description=__doc__.split("\n\n")[0], epilog=epilog)
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE_OR_FILE",
                        help="a module or .py file that registers controllers of your own (repeatable; "
                             "docs/extending.md), imported before anything else (default: none)")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")

    def add(name: str, help: str, with_environments: bool = False) -> argparse.ArgumentParser:
        return commands.add_parser(name, help=help, description=help, epilog=epilog if with_environments else None)

    def add_env(sub, many=False):
        if many:
            sub.add_argument("--env", action="append", metavar="NAME",
                             help=f"environment (repeatable; default: all of {environments})")
        else:
            sub.add_argument("--env", default=DEFAULT_ENVIRONMENT, metavar="NAME",
                             help=f"environment, one of {variants}")

    def add_episode(sub):
        add_env(sub)
        sub.add_argument("--task", type=int, default=DEFAULT_TASK, help="task index (the list below)")
        sub.add_argument("--seed", type=int, default=DEFAULT_SEED,
                         help="the episode's seed (start jitter, sensor noise, expert style)")

    def add_environments_file(sub):
        sub.add_argument("--environments", default=None, metavar="FILE",
                         help="a YAML file of environments in the packaged schema (ditch_drake/world/environments.yaml; "
                              "docs/extending.md); --env names one of them (default: the packaged environments)")

    def add_scenario_file(sub, what: str):
        sub.add_argument("--scenario", default=None, metavar="FILE",
                         help=f"a Scenario YAML file (`ditch-drake scenario --print` writes a template): {what} "
                              "(default: none, the built-in scenario)")
        sub.add_argument("--scenario-name", default=None, metavar="NAME",
                         help="the scenario of that name within --scenario's file (default: the whole file)")
        sub.add_argument("--override", default=None, metavar="YAML",
                         help="YAML in the Scenario schema applied last, e.g. \"{controller: !DwaBaselineConfig "
                              "{planner: {costmap: {lethal_slope_deg: 60}}}}\" (default: none)")
        add_environments_file(sub)

    def add_scenario(sub, controller_default: str):
        """The single-episode options of a Scenario: each one given overrides the scenario's."""
        add_scenario_file(sub, "the options below override it")
        sub.add_argument("--env", default=None, metavar="NAME",
                         help=f"environment (default: the scenario's; built in: {DEFAULT_ENVIRONMENT}; packaged: "
                              f"{variants})")
        sub.add_argument("--task", type=int, default=None,
                         help=f"task index, the list below (default: the scenario's; built in: {DEFAULT_TASK})")
        sub.add_argument("--seed", type=int, default=None,
                         help=f"the episode's seed (start jitter, sensor noise, expert style; default: the "
                              f"scenario's; built in: {DEFAULT_SEED})")
        sub.add_argument("--controller", default=None, choices=controller_names(),
                         help=f"{controllers_help} (default: the scenario's; built in: {controller_default})")
        sub.add_argument("--checkpoint", default=None,
                         help="the learned policy, a shipped name or a .pt file (default: the scenario's, else the "
                              "environment's shipped model)")
        sub.add_argument("--time-limit", type=float, default=None,
                         help="episode timeout in s (default: the scenario's; built in: 120)")

    def add_workers(sub, what: str):
        sub.add_argument("--workers", type=int, default=None,
                         help=f"worker processes for the {what} (default None: one per core; 0: in this process)")

    controllers_help = "; ".join(f"{name}: {text}" for name, text in controller_descriptions().items())

    scenario = add("scenario", "print a Scenario as YAML: the default one (a template to edit), or the one the "
                               "options make", with_environments=True)
    scenario.add_argument("--print", action="store_true", help="print it (the only action; kept for clarity)")
    add_scenario(scenario, "learned")
    scenario.set_defaults(run=cmd_scenario)

    demo = add("demo", "the main job: shipped policy, DWA baseline and a head-on driver through a ditch; outcome "
                       "table and an HTML recording", with_environments=True)
    add_episode(demo)
    add_environments_file(demo)
    demo.add_argument("--checkpoint", default=None,
                      help="the learned policy, a shipped name or a .pt file (default: the environment's shipped model)")
    demo.add_argument("--html", default="results/demo.html", help="where the recording goes")
    demo.set_defaults(run=cmd_demo)

    view = add("view", "open the scene in meshcat and drive through it in real time", with_environments=True)
    add_scenario(view, "edge_angle")
    view.add_argument("--realtime-rate", type=float, default=1.0, help="simulated seconds per wall-clock second")
    view.add_argument("--wait", action="store_true", help="keep meshcat open until Enter")
    view.set_defaults(run=cmd_view)

    calibrate = add("calibrate", "the physics calibration benchmark (exit 1 if it falls short)")
    add_env(calibrate, many=True)
    add_environments_file(calibrate)
    calibrate.add_argument("--json", action="store_true", help="one JSON object on stdout")
    calibrate.add_argument("--trials", type=int, default=10, help="seeded trials per driven case")
    calibrate.add_argument("--seed", type=int, default=0, help="first seed; trial i uses seed + i")
    add_workers(calibrate, "trials")
    calibrate.add_argument("--time-step", type=float, default=None,
                           help="plant step in s (default None: the scene's)")
    calibrate.set_defaults(run=cmd_calibrate)

    collect = add("collect", "record expert demonstrations (resumable; Ctrl-C keeps what finished)")
    add_env(collect)
    add_environments_file(collect)
    collect.add_argument("--demos", type=int, default=40, help="successful demonstrations, spread over the tasks")
    collect.add_argument("--seed", type=int, default=0, help="demonstration i's first attempt uses seed + i")
    collect.add_argument("--out", required=True, help="directory of demo_NNN.npz files")
    add_workers(collect, "demonstrations")
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

    teleop = add("teleop", "record your own demonstration: steer in meshcat", with_environments=True)
    add_episode(teleop)
    add_environments_file(teleop)
    teleop.add_argument("--out", required=True, help="directory of demo_NNN.npz files")
    teleop.add_argument("--realtime-rate", type=float, default=1.0, help="simulated seconds per wall-clock second")
    teleop.set_defaults(run=cmd_teleop)

    info = add("dataset-info", "counts per label and task, class imbalance")
    info.add_argument("path", help="a directory of demonstrations")
    info.add_argument("--json", action="store_true", help="one JSON object on stdout")
    info.set_defaults(run=cmd_dataset_info)

    replay = add("replay", "record one rollout as a standalone HTML page (meshcat animation)", with_environments=True)
    add_scenario(replay, "learned")
    replay.add_argument("--out", default="results/replay.html", help="the HTML page to write")
    replay.set_defaults(run=cmd_replay)

    info = add("checkpoint-info", "training data and validation metrics of checkpoints")
    info.add_argument("checkpoints", nargs="+", help="shipped model names or .pt files")
    info.add_argument("--confusion", action="store_true", help="also the validation confusion matrices")
    info.set_defaults(run=cmd_checkpoint_info)

    evaluation = add("evaluate", "seeded rollouts in parallel, appended to a results file (rerun to resume; "
                                 "Ctrl-C keeps what finished)", with_environments=True)
    evaluation.add_argument("--controller", default=None, choices=controller_names(),
                            help=f"{controllers_help} (default: the scenario's, else learned)")
    add_scenario_file(evaluation, "its controller with all its parameters, environment, environments file and "
                                  "time limit")
    evaluation.add_argument("--checkpoint", default=None,
                            help="the learned policy, a shipped name or a .pt file (default: each environment's "
                                 "shipped model)")
    add_env(evaluation, many=True)
    evaluation.add_argument("--task", type=int, action="append", default=None,
                            help="task index (repeatable; default None: every task of the environment)")
    evaluation.add_argument("--rollouts", type=int, default=10,
                            help="seeded rollouts per task (3 tasks x 10 rollouts = 30 per environment)")
    evaluation.add_argument("--seed", type=int, default=0, help="first seed; rollout i of each task uses seed + i")
    evaluation.add_argument("--time-limit", type=float, default=None,
                            help="episode timeout in s (default: the scenario's; built in: 120)")
    evaluation.add_argument("--out", default="results/evaluate.jsonl", help="results file (JSON Lines), appended")
    add_workers(evaluation, "rollouts")
    evaluation.add_argument("--backend", default="local", choices=["local", "ray"],
                            help="local process pool, or a Ray cluster (pip install -e '.[ray]')")
    evaluation.add_argument("--address", default=None, help="Ray cluster address (default None: start Ray here)")
    evaluation.set_defaults(run=cmd_evaluate)

    benchmark = add("benchmark", "a controller over the procedural ditches of a split (train, val, test) or the paper's "
                                 "four, appended to a results file (rerun to resume; Ctrl-C keeps what finished)")
    benchmark.add_argument("--split", default="test",
                           help="train (seeds 0-199), val (1000-1049), test (2000-2099; for reporting only, never a "
                                "choice) or paper (the four packaged environments)")
    benchmark.add_argument("--controller", default="expert", choices=controller_names(), help=controllers_help)
    benchmark.add_argument("--checkpoint", default=None,
                           help="the learned policy, a shipped name or a .pt file (default: generalist)")
    benchmark.add_argument("--geometries", type=int, default=None,
                           help="the split's first N ditches (default: all of them)")
    benchmark.add_argument("--rollouts", type=int, default=1, help="seeded rollouts per task (3 tasks per ditch)")
    benchmark.add_argument("--seed", type=int, default=0, help="first rollout seed; rollout i of each task uses seed + i")
    benchmark.add_argument("--ranges", default=None,
                           help="a ranges YAML file (default: the packaged ditch_drake/benchmark/ranges.yaml)")
    benchmark.add_argument("--time-limit", type=float, default=120.0, help="episode timeout in s")
    benchmark.add_argument("--out", default="results/benchmark/benchmark.jsonl",
                           help="results file (JSON Lines), appended; the ditches go to <stem>.ditches.yaml beside it")
    add_workers(benchmark, "rollouts")
    benchmark.add_argument("--backend", default="local", choices=["local", "ray"],
                           help="local process pool, or a Ray cluster (pip install -e '.[ray]')")
    benchmark.add_argument("--address", default=None, help="Ray cluster address (default None: start Ray here)")
    benchmark.set_defaults(run=cmd_benchmark)

    benchmark_report = add("benchmark-report", "the benchmark's page from its results files: success per split with "
                                               "Wilson intervals, against slope, width, depth and curvature, failure "
                                               "regions, the failed ditches with replay commands")
    benchmark_report.add_argument("results", nargs="+", help="benchmark results files (*.jsonl)")
    benchmark_report.add_argument("--out", default="results/benchmark/report.md", help="the Markdown page")
    benchmark_report.add_argument("--figures", default=None,
                                  help="folder of the PNG figures (default: <page stem>_img beside the page)")
    benchmark_report.add_argument("--title", default="Procedural ditch benchmark", help="the page's title")
    benchmark_report.set_defaults(run=cmd_benchmark_report)

    generalist = add("train-generalist", "the generalist policy: expert demonstrations and DAgger over the train "
                                         "split's ditches, the best round on the val split (resumable)")
    generalist.add_argument("--out", default="ditch_drake/models/generalist.pt", help="the chosen checkpoint")
    generalist.add_argument("--work-dir", default="data/generalist",
                            help="demonstrations, each round's checkpoint and the val results")
    generalist.add_argument("--train-geometries", type=int, default=40, help="the train split's first N ditches")
    generalist.add_argument("--demos-per-task", type=int, default=1, help="expert demonstrations per task")
    generalist.add_argument("--dagger-rounds", type=int, default=4, help="DAgger rounds after the first clone")
    generalist.add_argument("--val-geometries", type=int, default=25, help="the val split's first N ditches")
    generalist.add_argument("--dagger-stride", type=int, default=3,
                            help="train on every k-th control step of the DAgger rollouts (memory)")
    generalist.add_argument("--epochs", type=int, default=12, help="most epochs per training")
    generalist.add_argument("--mirror", action="store_true",
                            help="also train on the left-right reflection of each rollout whose crossing turns "
                                 "clearly to one side (ditch_drake/pipelines/generalist.py)")
    generalist.add_argument("--canonical-side", action="store_true",
                            help="reflect every step that crosses turned left along the edge, and tell the clone "
                                 "the side to cross on from a map of the ditch (systems/crossing_side.py)")
    generalist.add_argument("--seed", type=int, default=0, help="seeds demonstrations, training and val rollouts")
    generalist.add_argument("--ranges", default=None, help="the val split's ranges YAML file (default: the benchmark's)")
    generalist.add_argument("--train-ranges", default=None,
                            help="the train ditches' ranges YAML file (default: the packaged generalist_train_ranges.yaml)")
    add_workers(generalist, "demonstrations and val rollouts")
    generalist.set_defaults(run=cmd_train_generalist)

    experiment = add("experiment", "the paper's pipeline from an experiment YAML: collect, train, evaluate, report")
    experiment.add_argument("file", help="experiment file, e.g. experiments/paper.yaml")
    experiment.add_argument("--only", action="append", metavar="ENV",
                            help="only the models and evaluations that involve this environment (repeatable)")
    studies = study_names()
    experiment.add_argument("--study", action="append", choices=studies, metavar="STUDY",
                            help=f"only this study's models and evaluations (repeatable; one of {', '.join(studies)}; "
                                 "default: all)")
    experiment.add_argument("--stage", action="append", choices=["collect", "train", "evaluate", "report"],
                            help="run only this stage (repeatable; default: all, in order)")
    experiment.set_defaults(run=cmd_experiment)

    report = commands.add_parser("report", help="results page (Markdown) and figures from results files")
    report.add_argument("results", nargs="+", help="results files or folders of them (*.jsonl)")
    report.add_argument("--out", default=None,
                        help="the Markdown page (default: beside the first results entry: <folder>/report.md, or "
                             "<file stem>_report.md; a default path that git tracks is refused, name it to overwrite)")
    report.add_argument("--figures", default=None,
                        help="folder of the PNG figures (default: <page stem>_img beside the page)")
    report.add_argument("--title", default="Results", help="the page's title")
    report.set_defaults(run=cmd_report)

    defaults = TrainConfig()
    training = add("train", "behavioural cloning from demonstrations (Ctrl-C keeps the best finished epoch)")
    training.add_argument("--data", action="append", required=True, metavar="DIR",
                          help="demonstration directory (repeat for an amalgam of environments)")
    training.add_argument("--out", required=True, help="checkpoint path (.pt)")
    training.add_argument("--seed", type=int, default=defaults.seed,
                          help="seeds the split, SMOTE, initialization, shuffling and dropout")
    training.add_argument("--max-demos", type=int, default=None,
                          help="use the first N demonstrations of each directory (default None: all)")
    training.add_argument("--epochs", type=int, default=defaults.epochs, help="most epochs to run")
    training.add_argument("--patience", type=int, default=defaults.patience,
                          help="epochs without a better validation accuracy before stopping")
    training.add_argument("--batch-size", type=int, default=defaults.batch_size, help="samples per optimizer step")
    training.add_argument("--batches-per-epoch", type=int, default=defaults.max_batches_per_epoch,
                          help="batches drawn (without replacement) from the shuffled training set per epoch")
    training.add_argument("--synthetic-fraction", type=float, default=defaults.smote.max_synthetic_fraction,
                          help="at most this many SMOTE samples per real training sample")
    training.add_argument("--threads", type=int, default=None, help="torch threads (default None: all cores)")
    training.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                          help="auto: CUDA when torch sees a GPU, else the CPU (a CUDA run is not bitwise "
                               "reproducible on the CPU)")
    training.add_argument("--precision", choices=["auto", "fp32", "bf16"], default="auto",
                          help="bf16: training steps under bfloat16 autocast; auto: bf16 on a CPU with native "
                               "bf16 (AVX512-BF16 or AMX), else fp32")
    training.add_argument("--resume", action="store_true",
                          help="continue an interrupted run from its .resume file beside --out")
    training.set_defaults(run=cmd_train)

    figure = add("figure", "figures for docs/: surface-normal images per environment, the diagram, a browser "
                           "screenshot of a recording, the DWA baseline at the ditch, the DWA baselines' slope cost, "
                           "the MPPI baseline at the hinge (task 1)")
    figure.add_argument("kind", choices=["normal-images", "diagram", "screenshot", "dwa", "cost-curves", "mppi"],
                        help="which figure")
    figure.add_argument("--html", default="results/demo.html", help="screenshot: the recording to open in Chromium")
    add_env(figure, many=True)
    figure.add_argument("--out", default="docs/img", help="folder of the figures")
    figure.add_argument("--seed", type=int, default=0, help="the episode's seed")
    figure.set_defaults(run=cmd_figure)

    bench = add("bench", "speed and memory figures as one JSON object (--json)")
    add_env(bench, many=True)
    add_environments_file(bench)
    bench.add_argument("--json", action="store_true", help="one JSON object on stdout")
    bench.add_argument("--training", action="store_true",
                       help="also the training pipeline's peak memory on a synthetic 40-demo set (minutes)")
    bench.set_defaults(run=cmd_bench)
    return parser


def import_extensions(references: list[str]) -> None:
    """Imports each module or .py file of `--import`, so that the controllers it registers
    are choices of every command. A file's folder joins `sys.path`, so that the worker
    processes of a batch evaluation import it too.

    Raises:
        ConfigError: a module or file that cannot be imported, with the reason.
    """
    import importlib
    from pathlib import Path

    for reference in references:
        try:
            if reference.endswith(".py"):
                path = Path(reference).resolve()
                if not path.is_file():
                    raise FileNotFoundError(f"no such file {path}")
                sys.path.insert(0, str(path.parent))
                importlib.import_module(path.stem)
            else:
                importlib.import_module(reference)
        except (ImportError, FileNotFoundError, SyntaxError) as error:
            raise ConfigError(f"--import {reference}: {type(error).__name__}: {error}; expected an importable "
                              "module or .py file that registers controllers") from error


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    extensions = argparse.ArgumentParser(add_help=False)
    extensions.add_argument("--import", dest="imports", action="append", default=[])
    known, _ = extensions.parse_known_args(argv)
    try:
        import_extensions(known.imports)
    except ConfigError as error:
        print(f"ditch-drake: error: {error}", file=sys.stderr)
        return 2
    args = build_parser().parse_args(argv)
    try:
        with terminate_as_interrupt():
            return args.run(args)
    except KeyboardInterrupt as error:
        print("ditch-drake: interrupted", file=sys.stderr)
        return interrupt_exit_code(error)
    except BrokenPipeError:
        # The reader went away (`ditch-drake dataset-info ... | head`): stop quietly, and keep
        # Python's exit-time flush of stdout from raising again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as error:
        if not isinstance(error, _user_errors()):
            raise
        print(f"ditch-drake: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
