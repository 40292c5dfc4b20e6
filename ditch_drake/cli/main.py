"""The `ditch-drake` command line.

Every command's heavy imports (Drake, torch) happen inside the command, so that the parser
and every `--help` answer at once. A user's mistake (a bad value, a bad file) ends in exit
code 2 and one line `ditch-drake: error: ...`; Ctrl-C ends in 130 and SIGTERM in 143, after
the command has kept what finished.
"""

import argparse
import os
import sys

from ditch_drake.cli import (
    dataset_commands,
    episode_commands,
    evaluation_commands,
    export_commands,
    tool_commands,
    training_commands,
)
from ditch_drake.cli.options import Commands, Parser, environments_epilog
from ditch_drake.common.errors import ConfigError, ResultsError, TerrainError
from ditch_drake.common.parallel import interrupt_exit_code, terminate_as_interrupt

# In the order `ditch-drake --help` lists them.
COMMANDS = (
    episode_commands.add_scenario_command,
    episode_commands.add_demo,
    episode_commands.add_view,
    tool_commands.add_calibrate,
    training_commands.add_collect,
    episode_commands.add_teleop,
    dataset_commands.add_dataset,
    episode_commands.add_replay,
    training_commands.add_checkpoint_info,
    export_commands.add_export_policy,
    evaluation_commands.add_evaluate,
    evaluation_commands.add_benchmark,
    evaluation_commands.add_benchmark_report,
    training_commands.add_train_generalist,
    evaluation_commands.add_experiment,
    evaluation_commands.add_report,
    evaluation_commands.add_paired,
    training_commands.add_train,
    training_commands.add_gate_signals,
    training_commands.add_gate_thresholds,
    training_commands.add_gate_auc,
    training_commands.add_gate_peaks,
    tool_commands.add_figure,
    tool_commands.add_bench,
    tool_commands.add_reference,
)


def _user_errors() -> tuple[type[Exception], ...]:
    from ditch_drake.demos.dataset import DatasetError
    from ditch_drake.learning.checkpoint import CheckpointError

    return ConfigError, TerrainError, DatasetError, CheckpointError, ResultsError


def build_parser() -> argparse.ArgumentParser:
    epilog = environments_epilog()
    parser = Parser(prog="ditch-drake", description=__doc__.split("\n\n")[0], epilog=epilog)
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE_OR_FILE",
                        help="a module or .py file that registers controllers of your own (repeatable; "
                             "docs/tutorials/your_controller.md), imported before anything else (default: none)")
    commands = Commands(parser, parser.add_subparsers(dest="command", required=True, parser_class=Parser,
                                                      metavar="COMMAND"), epilog)
    for add in COMMANDS:
        add(commands)
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
        except Exception as error:  # A module may raise anything at import, ConfigError included.
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
