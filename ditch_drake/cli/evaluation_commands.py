"""Commands of evaluation: evaluate, benchmark, benchmark-report, experiment, report."""

import inspect
import json
import shlex
import sys

from ditch_drake.cli.options import (
    Commands,
    ConfigDefault,
    add_backend,
    add_checkpoint,
    add_controller,
    add_crossing_side,
    add_env,
    add_out,
    add_scenario_file,
    add_time_limit,
    add_workers,
    checkpoint_for,
    learned_with_crossing_side,
    named_checkpoint,
    print_table,
    scenario_from_options,
)
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import check_workers, interrupt_exit_code
from ditch_drake.common.seeds import check_seed

BENCHMARK = "ditch_drake.benchmark.run:BenchmarkConfig"
EVALUATE = "ditch_drake.evaluation.batch:evaluate"
BENCHMARK_PAGE = "ditch_drake.benchmark.results_page:write_benchmark_report"
REPORT_PAGE = "ditch_drake.evaluation.report:write_report"


def _evaluation_exit_code(report, out) -> int:
    """0, or the interrupt's exit code after saying how far a stopped run got and how to go on."""
    if report.interrupted:
        print(f"interrupted: {report.recorded} rollouts recorded by this run, {report.skipped + report.recorded} of "
              f"{report.requested} in {out}; run the same command again to continue", file=sys.stderr)
        return report.exit_code
    return 0


def add_evaluate(commands: Commands) -> None:
    evaluation = commands.add("evaluate", "seeded rollouts in parallel, appended to a results file (rerun to resume; "
                                          "Ctrl-C keeps what finished)", with_environments=True)
    add_controller(evaluation, default_text="the scenario's, else learned")
    add_scenario_file(evaluation, "its controller with all its parameters, environment, environments file and "
                                  "time limit")
    add_checkpoint(evaluation, "each environment's shipped model")
    add_crossing_side(evaluation)
    add_env(evaluation, many=True)
    evaluation.add_argument("--task", type=int, action="append", default=None,
                            help="task index (repeatable; default None: every task of the environment)")
    evaluation.add_argument("--rollouts", type=int, default=10,
                            help="seeded rollouts per task (3 tasks per environment)")
    evaluation.add_argument("--seed", type=int, default=0, help="first seed; rollout i of each task uses seed + i")
    add_time_limit(evaluation)
    add_out(evaluation, "results file (JSON Lines), appended", default="results/evaluate.jsonl")
    add_workers(evaluation, "rollouts", default=ConfigDefault(EVALUATE, "workers"))
    add_backend(evaluation, EVALUATE)
    evaluation.set_defaults(run=cmd_evaluate)


def cmd_evaluate(args) -> int:
    """Seeded rollouts of one controller in one or more environments, appended to a results file."""
    check_workers(args.workers, "--workers")
    from ditch_drake.evaluation.batch import evaluate, load_results, make_specs, spelled_as_recorded
    from ditch_drake.evaluation.model_labels import with_marks
    from ditch_drake.evaluation.results import current_records, read_records
    from ditch_drake.evaluation.summary import group_by, summarize
    from ditch_drake.systems.episode_monitor import EpisodeConfig
    from ditch_drake.world.environments import environment_names, get_environment

    controller, environments_file = args.controller or "learned", args.environments or ""
    time_limit_s = EpisodeConfig.time_limit_s
    if args.scenario or args.override:
        # The scenario gives the controller's full config, the environments file and the episode's limit.
        scenario = scenario_from_options(args, name_checkpoint=False)  # Each environment its own model.
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
        if controller == "learned":
            checkpoint = checkpoint_for(args, environment)
        else:  # make_specs refuses a checkpoint that the controller does not take; a config names its own.
            checkpoint = (args.checkpoint or "") if isinstance(controller, str) else ""
        # A config's empty checkpoint is each environment's own model (a name is left as it is).
        environment_controller = (controller if isinstance(controller, str)
                                  else named_checkpoint(controller, environment, environments_file))
        chosen = learned_with_crossing_side(environment_controller, checkpoint, args.crossing_side)
        specs += make_specs(chosen, checkpoint, environment, args.task, args.rollouts, args.seed, time_limit_s,
                            environments_file)
        tasks = len(args.task) if args.task else len(get_environment(environment, environments_file or None).tasks)
        plan.append(f"{environment}: {tasks} tasks x {args.rollouts} rollouts = {tasks * args.rollouts}")
    print(f"{specs[0].controller}: " + "; ".join(plan) + f" (seeds {args.seed}..{args.seed + args.rollouts - 1})",
          file=sys.stderr, flush=True)
    specs = spelled_as_recorded(specs, read_records(args.out)[0])  # The summary's keys are the records'.
    report = evaluate(specs, args.out, workers=args.workers, backend=args.backend, address=args.address)
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    keys = {spec.key for spec in specs}
    records, _ = current_records([record for record in load_results([args.out]) if record.key in keys])
    rows = []
    for (controller, checkpoint, environment, task), group in group_by(
            records, "controller", "checkpoint", "environment", "task").items():
        summary = summarize(group)
        rows.append({"controller": with_marks(controller, group[0]), "checkpoint": checkpoint or "-",
                     "env": environment, "task": task,
                     "success": f"{summary.successes}/{summary.trials}", "around": summary.around,
                     "wilson95": f"{summary.low:.2f}-{summary.high:.2f}",
                     "failures": " ".join(f"{k}:{v}" for k, v in sorted(summary.failure_regions.items())) or "-",
                     "errors": summary.errors})
    if rows:
        print_table(rows, ["controller", "checkpoint", "env", "task", "success", "around", "wilson95", "failures",
                           "errors"])
    print(json.dumps({"out": str(args.out), "requested": report.requested, "skipped": report.skipped,
                      "recorded": report.recorded, "successes_recorded": report.successes,
                      "errors_recorded": report.errors, "wall_s": round(report.wall_s, 1),
                      "rollouts_per_minute": round(report.rollouts_per_minute, 2),
                      "interrupted": report.interrupted}))
    return _evaluation_exit_code(report, args.out)


def add_benchmark(commands: Commands) -> None:
    benchmark = commands.add("benchmark", "a controller over the procedural ditches of a split (train, val, test, "
                                          "stress, search, search_val) or the paper's four, appended to a results file (rerun to resume; Ctrl-C "
                                          "keeps what finished)")
    benchmark.add_argument("--split", default=ConfigDefault(BENCHMARK, "split"),
                           help="train (seeds 0-199), val (1000-1049), test (2000-2099; for reporting only, never a "
                                "choice), stress (3000-3099, beyond the train ranges: stress_ranges.yaml; reporting "
                                "only), search (4000-4099: ditches crossable only through windows in their walls, "
                                "search_ranges.yaml; reporting only), search_val (4100-4149, for choices) or paper "
                                "(the four packaged environments)")
    add_controller(benchmark, default=ConfigDefault(BENCHMARK, "controller"))
    add_checkpoint(benchmark, "generalist")
    add_crossing_side(benchmark)
    benchmark.add_argument("--geometries", type=int, default=ConfigDefault(BENCHMARK, "geometries"),
                           help="the split's first N ditches (default: all of them)")
    benchmark.add_argument("--rollouts", type=int, default=ConfigDefault(BENCHMARK, "rollouts"),
                           help="seeded rollouts per task (3 tasks per ditch)")
    benchmark.add_argument("--seed", type=int, default=ConfigDefault(BENCHMARK, "seed"),
                           help="first rollout seed; rollout i of each task uses seed + i")
    benchmark.add_argument("--ranges", default=ConfigDefault(BENCHMARK, "ranges"),
                           help="a ranges YAML file (default: the split's packaged one, "
                                "ditch_drake/benchmark/ranges.yaml or, for stress, stress_ranges.yaml and, for search and "
                                "search_val, search_ranges.yaml)")
    benchmark.add_argument("--time-limit", type=float, default=ConfigDefault(BENCHMARK, "time_limit_s"),
                           help="episode timeout in s (default: the split's: 240 for search and search_val, whose "
                                "ways in and out may lie at opposite ends of a long ditch; 120 for the others)")
    benchmark.add_argument("--override", default=None, metavar="YAML",
                           help="YAML in the Scenario schema whose controller replaces --controller's, e.g. "
                                "\"{controller: !LearnedPolicyConfig {search: {}}}\" (a learned config naming no "
                                "checkpoint takes --checkpoint's; default: none)")
    add_out(benchmark, "results file (JSON Lines), appended; the ditches go to <stem>.ditches.yaml beside it",
            default=ConfigDefault(BENCHMARK, "out"))
    add_workers(benchmark, "rollouts", default=ConfigDefault(BENCHMARK, "workers"))
    add_backend(benchmark, BENCHMARK)
    benchmark.set_defaults(run=cmd_benchmark)


def cmd_benchmark(args) -> int:
    """A controller over a split's procedural ditches (or the paper's four), appended to a results file."""
    check_workers(args.workers, "--workers")
    from ditch_drake.benchmark.run import BenchmarkConfig, benchmark_specs, run_benchmark
    from ditch_drake.benchmark.splits import check_split
    from ditch_drake.evaluation.batch import load_results, spelled_as_recorded
    from ditch_drake.evaluation.results import current_records, read_records
    from ditch_drake.evaluation.summary import summarize

    check_split(args.split)
    check_seed(args.seed, max(1, args.rollouts))
    config = BenchmarkConfig(split=args.split, controller=args.controller, checkpoint=args.checkpoint or "",
                             crossing_side=args.crossing_side or "", geometries=args.geometries, rollouts=args.rollouts, seed=args.seed, out=args.out,
                             ranges=args.ranges or "", time_limit_s=args.time_limit, override=args.override or "",
                             workers=args.workers,
                             backend=args.backend, address=args.address)
    if args.rollouts < 1:
        raise ConfigError(f"--rollouts {args.rollouts}: expected a positive integer")
    specs = spelled_as_recorded(benchmark_specs(config), read_records(args.out)[0])  # The summary's keys are the records'.
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
                      "checkpoint": specs[0].checkpoint,
                      "privileged": records[0].privileged if records else [],
                      "crossing_side_source": records[0].crossing_side_source if records else "",
                      "geometries": len(environments),
                      "requested": report.requested, "skipped": report.skipped, "recorded": report.recorded,
                      "successes": summary.successes if summary else 0, "trials": summary.trials if summary else 0,
                      "wilson95": [round(summary.low, 3), round(summary.high, 3)] if summary else None,
                      "errors_recorded": report.errors, "wall_s": round(report.wall_s, 1),
                      "rollouts_per_minute": round(report.rollouts_per_minute, 2), "interrupted": report.interrupted}))
    return _evaluation_exit_code(report, args.out)


def add_benchmark_report(commands: Commands) -> None:
    benchmark_report = commands.add("benchmark-report", "the benchmark's page from its results files: success per "
                                                        "split with Wilson intervals, time and path length, against "
                                                        "slope, width, depth and curvature, failure regions, the failed "
                                                        "ditches with replay commands")
    benchmark_report.add_argument("results", nargs="+", help="benchmark results files (*.jsonl)")
    add_out(benchmark_report, "the Markdown page", default="results/benchmark/report.md")
    benchmark_report.add_argument("--figures", default=None,
                                  help="folder of the PNG figures (default: <page stem>_img beside the page)")
    benchmark_report.add_argument("--title", default=ConfigDefault(BENCHMARK_PAGE, "title"), help="the page's title")
    benchmark_report.set_defaults(run=cmd_benchmark_report)


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


def add_experiment(commands: Commands) -> None:
    from ditch_drake.pipelines.experiment import study_names

    experiment = commands.add("experiment", "the paper's pipeline from an experiment YAML: collect, train, evaluate, "
                                            "report")
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


def add_paired(commands: Commands) -> None:
    paired = commands.add("paired", "two runs on the same rollouts compared rollout by rollout (McNemar's exact test)")
    paired.add_argument("a", help="the first results file (*.jsonl)")
    paired.add_argument("b", help="the second results file, with rollouts of the same environments, tasks and seeds")
    for side in ("a", "b"):
        paired.add_argument(f"--{side}-where", default=None, metavar="KEY=VALUE[,KEY=VALUE]",
                            help=f"compare only the records of {side} with these values, to take one run from a file "
                                 "of several (an experiment's): KEY is controller, environment, or a gate's signal, "
                                 "budget or fallback, e.g. signal=random,budget=0.05,fallback=mppi")
    paired.set_defaults(run=cmd_paired)


def cmd_paired(args) -> int:
    """Prints one JSON object: the rollouts both files have an outcome of, where both, neither,
    or only one reached the goal, and McNemar's exact p-value (`paired_comparison`). Without
    `--a-where` a file must hold one run; with it, the selected records one outcome per rollout
    (a series of an experiment runs each environment with thresholds, so a config, of its own)."""
    import dataclasses
    from collections import Counter
    from pathlib import Path

    from ditch_drake.evaluation.model_labels import parse_selection, record_matches
    from ditch_drake.evaluation.results import read_records
    from ditch_drake.evaluation.statistics import paired_comparison

    wheres = {"a": args.a_where, "b": args.b_where}
    selections = {side: parse_selection(where, f"--{side}-where") for side, where in wheres.items() if where is not None}
    for path in (args.a, args.b):
        if not Path(path).is_file():
            raise ConfigError(f"no results file at {path}; expected a .jsonl of evaluate or benchmark")
    compared = {}
    for side, path in (("a", args.a), ("b", args.b)):
        records, _ = read_records(path)
        if side not in selections:
            runs = {(r.controller, r.controller_sha256, r.checkpoint) for r in records}
            if len(runs) > 1:
                raise ConfigError(f"{path} holds rollouts of {len(runs)} controllers or checkpoints; expected one run "
                                  f"per file (a benchmark's or an evaluate's --out), or --{side}-where to select one")
        else:
            records = [r for r in records if record_matches(r, selections[side])]
            if not records:
                raise ConfigError(f"no record of {path} has --{side}-where {wheres[side]!r}; expected a selection "
                                  "that some records match")
            repeated = [key for key, count in Counter((r.environment, r.task, r.seed) for r in records
                                                      if not r.is_error).items() if count > 1]
            if repeated:
                environment, task, seed = repeated[0]
                raise ConfigError(f"--{side}-where {wheres[side]!r} selects {len(repeated)} rollouts of {path} more "
                                  f"than once (e.g. {environment} task {task} seed {seed}); expected one run: add a "
                                  "key, e.g. signal, budget or fallback")
        compared[side] = records
    comparison = paired_comparison(compared["a"], compared["b"])
    if comparison.matched == 0:
        raise ConfigError(f"{args.a} and {args.b} share no rollout (environment, task, seed) with an outcome; "
                          "expected two runs on the same rollouts")
    where = {f"{side}_where": wheres[side] for side in selections}
    print(json.dumps({"a": args.a, "b": args.b, **where, **dataclasses.asdict(comparison)}))
    return 0


def add_report(commands: Commands) -> None:
    report = commands.add("report", "results page (Markdown) and figures from results files")
    report.add_argument("results", nargs="+", help="results files or folders of them (*.jsonl)")
    report.add_argument("--out", default=None,
                        help="the Markdown page (default: beside the first results entry: <folder>/report.md, or "
                             "<file stem>_report.md; a default path that git tracks is refused, name it to overwrite)")
    report.add_argument("--figures", default=None,
                        help="folder of the PNG figures (default: <page stem>_img beside the page)")
    report.add_argument("--title", default=ConfigDefault(REPORT_PAGE, "title"), help="the page's title")
    report.set_defaults(run=cmd_report)


def cmd_report(args) -> int:
    """The results page and its figures from the current records of results files, its success
    tables also printed; by default beside the results, and never over a file git tracks unless
    `--out` / `--figures` names it."""
    from pathlib import Path

    from ditch_drake.common.outputs import default_outputs, figures_beside, tracked_by_git
    from ditch_drake.evaluation.report import write_report
    from ditch_drake.evaluation.report_data import load_report_data

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
    default_title = inspect.signature(write_report).parameters["title"].default
    command = shlex.join(["ditch-drake", "report", *map(str, args.results), "--out", str(out), "--figures",
                          str(figures), *(["--title", args.title] if args.title != default_title else [])])
    page = write_report(args.results, out, figures, title=args.title, command=command, data=data)
    print(data.markdown_tables())
    print(f"wrote {page} (figures in {figures})")
    return 0
