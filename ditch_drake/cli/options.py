"""The parser, its help format, and the options several commands share.

An option whose value ends in a config dataclass's field takes its default from that field
(`ConfigDefault`), so the command line and the dataclass cannot disagree. The field is read
when it is first needed, while parsing or printing a command's help, so that building the
parser imports nothing heavy and `ditch-drake --help` answers at once.
"""

import argparse
import ast
import functools
import importlib
import importlib.util
import inspect
from pathlib import Path

from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.controllers import controller_descriptions, controller_names

SCENARIO = "ditch_drake.diagrams.scenario:Scenario"
# The Scenario's `episode`, read from its own module, lighter to import than the Scenario's.
EPISODE = "ditch_drake.systems.episode_monitor:EpisodeConfig"
LEARNED = "ditch_drake.diagrams.rollout:LearnedPolicyConfig"
# `LearnedPolicyConfig.crossing_side`'s values (`ditch_drake.diagrams.rollout.CROSSING_SIDE_SOURCES`),
# here so that `--help` need not import Drake.
CROSSING_SIDE_SOURCES = ("perceived", "oracle")


class ConfigDefault:
    """The default of a config dataclass's field, or of a function's parameter, read on first use.

    `owner` is "module:Name": a dataclass (its default instance's `field`, dotted for a nested
    one: "smote.max_synthetic_fraction") or a function (its parameter `field`'s default).
    """

    def __init__(self, owner: str, field: str):
        self.owner = owner
        self.field = field

    @functools.cached_property
    def value(self):
        """The default as the source writes it where it is a literal (or a literal of another
        class, `EpisodeConfig.time_limit_s`), else as the imported owner has it: most config
        modules import Drake and torch, seconds that a command's `--help` should not wait."""
        module, _, name = self.owner.partition(":")
        value = _literal_default(module, name, self.field)
        return self.imported_value() if value is _NOT_LITERAL else value

    def imported_value(self):
        """The default as the imported dataclass or function has it."""
        module, _, name = self.owner.partition(":")
        owner = getattr(importlib.import_module(module), name)
        if inspect.isfunction(owner):
            return inspect.signature(owner).parameters[self.field].default
        value = owner()
        for part in self.field.split("."):
            value = getattr(value, part)
        return value

    def __str__(self) -> str:  # What `%(default)s` shows in a help text.
        return str(self.value)

    def __repr__(self) -> str:
        return f"ConfigDefault({self.owner!r}, {self.field!r})"


_NOT_LITERAL = object()


@functools.cache
def _source_tree(module: str) -> ast.Module | None:
    """The syntax tree of `module`'s source, read without running it (None: no source)."""
    spec = importlib.util.find_spec(module)
    if spec is None or not (spec.origin or "").endswith(".py"):
        return None
    return ast.parse(Path(spec.origin).read_text())


def _literal_default(module: str, name: str, field: str):
    """The default of `field` in the source of class or function `name` of `module`, where it
    is a literal or `Other.attribute` of a class imported from another module; else `_NOT_LITERAL`."""
    tree = _source_tree(module)
    if tree is None or "." in field:
        return _NOT_LITERAL
    expression = None
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            expression = next((statement.value for statement in node.body if isinstance(statement, ast.AnnAssign)
                               and isinstance(statement.target, ast.Name) and statement.target.id == field), None)
        elif isinstance(node, ast.FunctionDef) and node.name == name:
            arguments = node.args
            positional = arguments.posonlyargs + arguments.args
            pairs = list(zip(positional[len(positional) - len(arguments.defaults):], arguments.defaults))
            pairs += [(argument, default) for argument, default in zip(arguments.kwonlyargs, arguments.kw_defaults)
                      if default is not None]
            expression = next((default for argument, default in pairs if argument.arg == field), None)
    if expression is None:
        return _NOT_LITERAL
    try:
        return ast.literal_eval(expression)
    except ValueError:
        pass
    if isinstance(expression, ast.Attribute) and isinstance(expression.value, ast.Name):
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.level == 0 and any(
                    alias.name == expression.value.id and alias.asname is None for alias in node.names):
                return _literal_default(node.module, expression.value.id, expression.attr)
    return _NOT_LITERAL


def resolve_defaults(namespace: argparse.Namespace) -> argparse.Namespace:
    """Replaces every `ConfigDefault` left in `namespace` (an option not given) by its value."""
    for name, value in vars(namespace).items():
        if isinstance(value, ConfigDefault):
            setattr(namespace, name, value.value)
    return namespace


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows every option's default (unless its help already says it), and keeps the
    environments list of the epilogs as written."""

    def _get_help_string(self, action):
        if "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """An argument parser with `HelpFormatter` whose parsed values carry no `ConfigDefault`."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        return resolve_defaults(namespace), extras


def environments_epilog() -> str:
    """The packaged environments and their tasks, by index and name."""
    from ditch_drake.world.environments import load_environments

    lines = ["environments and their tasks (--env NAME --task INDEX):"]
    # Read without proving the walls (`get_environment` does that when one is used): --help stays quick.
    for name, environment in load_environments(prove_walls=False).items():
        tasks = environment.tasks
        lines.append(f"  {name}: " + ", ".join(f"{index} {task.name}" for index, task in enumerate(tasks)))
    return "\n".join(lines)


class Commands:
    """The subcommands of `parser`: `add` declares one, with its help as its description."""

    def __init__(self, parser: argparse.ArgumentParser, subparsers, epilog: str):
        self.parser = parser
        self._subparsers = subparsers
        self._epilog = epilog

    def add(self, name: str, help: str, with_environments: bool = False) -> argparse.ArgumentParser:
        """A command; `with_environments` adds the environments list as its epilog."""
        return self._subparsers.add_parser(name, help=help, description=help,
                                           epilog=self._epilog if with_environments else None)


def controllers_help() -> str:
    """Every registered controller with its one-line description."""
    return "; ".join(f"{name}: {text}" for name, text in controller_descriptions().items()).replace("%", "%%")


def add_controller(sub: argparse.ArgumentParser, default=None, default_text: str | None = None) -> None:
    """`--controller`, one of the registered controllers."""
    # The descriptions say "default" (learned's does), which would hide the formatter's own.
    shown = f" (default: {default_text})" if default_text else " (default: %(default)s)" if default else ""
    sub.add_argument("--controller", default=default, choices=controller_names(), help=controllers_help() + shown)


def add_env(sub: argparse.ArgumentParser, many: bool = False, default=None) -> None:
    """`--env NAME`: one environment (`default`), or with `many` a repeatable one (default: all)."""
    from ditch_drake.world.environments import environment_names

    if many:
        sub.add_argument("--env", action="append", metavar="NAME",
                         help=f"environment (repeatable; default: all of {environment_names()})")
    else:
        sub.add_argument("--env", default=default, metavar="NAME",
                         help=f"environment, one of {environment_names(variants=True)}")


def add_episode(sub: argparse.ArgumentParser) -> None:
    """`--env`, `--task` and `--seed` of one episode, their defaults the Scenario's."""
    add_env(sub, default=ConfigDefault(SCENARIO, "environment"))
    sub.add_argument("--task", type=int, default=ConfigDefault(SCENARIO, "task"), help="task index (the list below)")
    sub.add_argument("--seed", type=int, default=ConfigDefault(SCENARIO, "seed"),
                     help="the episode's seed (start jitter, sensor noise, expert style)")


def add_environments_file(sub: argparse.ArgumentParser) -> None:
    """`--environments FILE`: environments of the user's own."""
    sub.add_argument("--environments", default=None, metavar="FILE",
                     help="a YAML file of environments in the packaged schema (ditch_drake/world/environments.yaml; "
                          "docs/tutorials/your_ditch.md); --env names one of them (default: the packaged environments)")


def add_scenario_file(sub: argparse.ArgumentParser, what: str) -> None:
    """`--scenario FILE`, `--scenario-name NAME`, `--override YAML` and `--environments FILE`."""
    sub.add_argument("--scenario", default=None, metavar="FILE",
                     help=f"a Scenario YAML file (`ditch-drake scenario --print` writes a template): {what} "
                          "(default: none, the built-in scenario)")
    sub.add_argument("--scenario-name", default=None, metavar="NAME",
                     help="the scenario of that name within --scenario's file (default: the whole file)")
    sub.add_argument("--override", default=None, metavar="YAML",
                     help="YAML in the Scenario schema applied last, e.g. \"{controller: !DwaBaselineConfig "
                          "{planner: {costmap: {lethal_slope_deg: 60}}}}\" (default: none)")
    add_environments_file(sub)


def _built_in(action: argparse.Action, field: str, owner: str = SCENARIO) -> None:
    """Shows `owner`'s `field` as `%(built_in)s` in the help of an option whose default is
    "the scenario's" (None), for a user who gives no scenario file."""
    action.built_in = ConfigDefault(owner, field)


def add_checkpoint(sub: argparse.ArgumentParser, default_text: str) -> None:
    """`--checkpoint`: the learned policy's."""
    sub.add_argument("--checkpoint", default=None,
                     help=f"the learned policy, a shipped name, a .pt file or a .onnx of export-policy (default: "
                          f"{default_text})")


def add_crossing_side(sub: argparse.ArgumentParser) -> None:
    """`--crossing-side`: where a side-conditioned clone is told its side (`LearnedPolicyConfig`)."""
    sub.add_argument("--crossing-side", default=None, choices=CROSSING_SIDE_SOURCES,
                     help="with the learned policy of a side-conditioned checkpoint (the generalist): perceived "
                          "(found in the lidar's rays) or oracle (read from the analytic ditch: privileged, for the "
                          f"ablation) (default: {ConfigDefault(LEARNED, 'crossing_side')})")


def learned_with_crossing_side(controller, checkpoint: str, crossing_side: str | None):
    """`controller` (a name or a config) with `--crossing-side` applied (`with_crossing_side`),
    or itself when none is given.

    Raises:
        ConfigError: --crossing-side with a controller other than the learned policy.
    """
    if crossing_side is None:
        return controller
    from ditch_drake.diagrams.controllers import controller_config
    from ditch_drake.diagrams.rollout import with_crossing_side

    config = controller_config(controller, checkpoint) if isinstance(controller, str) else controller
    return with_crossing_side(config, crossing_side)


def add_time_limit(sub: argparse.ArgumentParser, default=None) -> None:
    """`--time-limit`: `default`, or else the scenario's (None)."""
    if default is not None:
        sub.add_argument("--time-limit", type=float, default=default, help="episode timeout in s")
        return
    _built_in(sub.add_argument("--time-limit", type=float, default=None,
                               help="episode timeout in s (default: the scenario's; built in: %(built_in)s)"),
              "time_limit_s", EPISODE)


def add_scenario(sub: argparse.ArgumentParser, controller_default: str) -> None:
    """The single-episode options of a Scenario: each one given overrides the scenario's."""
    from ditch_drake.world.environments import environment_names

    add_scenario_file(sub, "the options below override it")
    _built_in(sub.add_argument("--env", default=None, metavar="NAME",
                               help="environment (default: the scenario's; built in: %(built_in)s; packaged: "
                                    f"{environment_names(variants=True)})"), "environment")
    _built_in(sub.add_argument("--task", type=int, default=None,
                               help="task index, the list below (default: the scenario's; built in: %(built_in)s)"),
              "task")
    _built_in(sub.add_argument("--seed", type=int, default=None,
                               help="the episode's seed (start jitter, sensor noise, expert style; default: the "
                                    "scenario's; built in: %(built_in)s)"), "seed")
    add_controller(sub, default_text=f"the scenario's; built in: {controller_default}")
    add_checkpoint(sub, "the scenario's, else the environment's shipped model")
    add_time_limit(sub)


def add_workers(sub: argparse.ArgumentParser, what: str, default=None) -> None:
    """`--workers`: processes for `what` (None: one per core; 0: in this process)."""
    sub.add_argument("--workers", type=int, default=default,
                     help=f"worker processes for the {what} (default %(default)s: one per core; 0: in this process)")


def add_backend(sub: argparse.ArgumentParser, owner: str) -> None:
    """`--backend` and `--address`, their defaults `owner`'s ("module:Name" with fields or
    parameters `backend` and `address`)."""
    sub.add_argument("--backend", default=ConfigDefault(owner, "backend"), choices=["local", "ray"],
                     help="local process pool, or a Ray cluster (pip install -e '.[ray]')")
    sub.add_argument("--address", default=ConfigDefault(owner, "address"),
                     help="Ray cluster address (default %(default)s: start Ray here)")


def add_out(sub: argparse.ArgumentParser, help: str, default=None) -> None:
    """`--out`: where the command writes; required when it has no default."""
    if default is None:
        sub.add_argument("--out", required=True, help=help)
    else:
        sub.add_argument("--out", default=default, help=help)


def add_json(sub: argparse.ArgumentParser) -> None:
    """`--json`: one JSON object on stdout instead of a table."""
    sub.add_argument("--json", action="store_true", help="one JSON object on stdout")


def print_table(rows: list[dict], columns: list[str], file=None) -> None:
    widths = [max(len(column), *(len(str(row[column])) for row in rows)) for column in columns]
    print("  ".join(column.ljust(width) for column, width in zip(columns, widths)), file=file)
    for row in rows:
        print("  ".join(str(row[column]).ljust(width) for column, width in zip(columns, widths)), file=file)


def check_task(environment: str, task: int, environments_file: str = "") -> None:
    from ditch_drake.world.environments import get_environment

    tasks = get_environment(environment, environments_file or None).tasks
    if not 0 <= task < len(tasks):
        raise ConfigError(f"--task {task}: {environment!r} has tasks 0..{len(tasks) - 1} "
                          f"({', '.join(f'{i} {t.name}' for i, t in enumerate(tasks))})")


def checkpoint_for(args, environment: str) -> str:
    """The learned policy's checkpoint: --checkpoint, else the environment's shipped model."""
    from ditch_drake.learning.checkpoint import environment_model

    return args.checkpoint or environment_model(environment, getattr(args, "environments", None) or "")


def scenario_from_options(args, default_controller: str = "learned", name_checkpoint: bool = True):
    """The Scenario of a single-episode command: the defaults, then --scenario FILE (and
    --scenario-name), then the options given on the command line, then --override. With
    `name_checkpoint`, a learned controller's empty checkpoint becomes its environment's model
    (a command of several environments names each one's: `named_checkpoint`)."""
    from dataclasses import replace

    from ditch_drake.diagrams.controllers import controller_config, with_checkpoint
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
    if getattr(args, "checkpoint", None):
        if not hasattr(scenario.controller, "checkpoint"):
            raise ConfigError(f"--checkpoint {args.checkpoint}: the controller {type(scenario.controller).__name__} "
                              "takes no checkpoint; expected --checkpoint only with the learned policy")
        scenario = replace(scenario, controller=with_checkpoint(scenario.controller, args.checkpoint))
    if getattr(args, "time_limit", None) is not None:
        scenario = replace(scenario, episode=replace(scenario.episode, time_limit_s=args.time_limit))
    if args.override:
        scenario = load_scenario(override=args.override, defaults=scenario)
    check_scenario(scenario)
    if name_checkpoint:
        scenario = replace(scenario, controller=named_checkpoint(scenario.controller, scenario.environment,
                                                                 scenario.environments_file))
    return scenario


def named_checkpoint(controller, environment: str, environments_file: str = ""):
    """`controller` (a config) with an empty checkpoint replaced by `environment`'s model, so that
    records and pages say which; any other controller as it is."""
    if getattr(controller, "checkpoint", None) != "":
        return controller
    from ditch_drake.diagrams.controllers import with_checkpoint
    from ditch_drake.learning.checkpoint import environment_model

    return with_checkpoint(controller, environment_model(environment, environments_file))
