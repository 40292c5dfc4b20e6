"""Commands of tools: calibrate, figure, bench, reference."""

import argparse
import functools
import json
import sys
import time

from ditch_drake.cli.episode_commands import DEMO_HTML
from ditch_drake.cli.options import (
    Commands,
    ConfigDefault,
    add_env,
    add_environments_file,
    add_json,
    add_out,
    add_workers,
    print_table,
)
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import check_workers
from ditch_drake.common.seeds import check_seed

CALIBRATION = "ditch_drake.validation.calibration:CalibrationConfig"


def add_calibrate(commands: Commands) -> None:
    calibrate = commands.add("calibrate", "the physics calibration benchmark (exit 1 if it falls short)")
    add_env(calibrate, many=True)
    add_environments_file(calibrate)
    add_json(calibrate)
    calibrate.add_argument("--trials", type=int, default=ConfigDefault(CALIBRATION, "trials"),
                           help="seeded trials per driven case")
    calibrate.add_argument("--seed", type=int, default=ConfigDefault(CALIBRATION, "seed"),
                           help="first seed; trial i uses seed + i")
    add_workers(calibrate, "trials", default=ConfigDefault(CALIBRATION, "workers"))
    calibrate.add_argument("--time-step", type=float, default=None, help="plant step in s (default None: the scene's)")
    calibrate.set_defaults(run=cmd_calibrate)


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


def add_figure(commands: Commands) -> None:
    figure = commands.add("figure", "figures for docs/: surface-normal images per environment, the diagram, a "
                                    "browser screenshot of a recording, the DWA baseline at the ditch, the DWA "
                                    "baselines' slope cost, the MPPI baseline at the hinge (task 1), a search for a way in and out "
                                    "(the expert and the MPPI with the window search, task 0)")
    figure.add_argument("kind", choices=["normal-images", "diagram", "screenshot", "dwa", "cost-curves", "mppi",
                                         "search"],
                        help="which figure")
    figure.add_argument("--html", default=DEMO_HTML, help="screenshot: the recording to open in Chromium")
    add_env(figure, many=True)
    add_out(figure, "folder of the figures", default="docs/img")
    figure.add_argument("--seed", type=int, default=0, help="the episode's seed")
    figure.set_defaults(run=cmd_figure)


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
    if args.kind == "search":
        from ditch_drake.docs_tools.search_figure import search_figure

        for name in args.env or ["wide_search_offset"]:
            print(search_figure(name, args.out, task=0, seed=args.seed))
        return 0
    for name in args.env or environment_names():
        print(normal_image_figure(name, args.out, args.seed))
    return 0


def add_bench(commands: Commands) -> None:
    bench = commands.add("bench", "speed and memory figures as one JSON object (--json)")
    add_env(bench, many=True)
    add_environments_file(bench)
    add_json(bench)
    bench.add_argument("--training", action="store_true",
                       help="also the training pipeline's peak memory and time with SMOTE on a synthetic 40-demo "
                            "set (minutes; without it, the streaming pipeline's with oversampling)")
    bench.set_defaults(run=cmd_bench)


def cmd_bench(args) -> int:
    from ditch_drake.perf.bench import run_bench

    figures = run_bench(args.env or None, training=args.training, environments_file=args.environments or "")
    if args.json:
        print(json.dumps(figures))
    else:
        print_table([{"figure": key, "value": "-" if value is None else f"{value:.3f}"} for key, value in figures.items()],
                    ["figure", "value"])
    return 0


def add_reference(commands: Commands) -> None:
    reference = commands.add("reference", "the reference pages (Markdown) of the command line and the config "
                                          "schemas, generated from the parser and the dataclasses")
    add_out(reference, "folder of the pages", default="docs/reference")
    reference.set_defaults(run=functools.partial(cmd_reference, parser=commands.parser))


def cmd_reference(args, parser: argparse.ArgumentParser) -> int:
    """Writes the pages of `parser` (with the controllers of any --import) and the schemas."""
    from ditch_drake.cli.reference_pages import write_reference

    for path in write_reference(args.out, parser):
        print(path)
    return 0
