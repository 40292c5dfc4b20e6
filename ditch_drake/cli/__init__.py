"""The `ditch-drake` command line: `main` (the entry point), its parser, and one module per
group of commands (`episode_commands`, `training_commands`, `evaluation_commands`,
`tool_commands`) over the shared options of `options`."""

from ditch_drake.cli.main import build_parser, import_extensions, main

__all__ = ["build_parser", "import_extensions", "main"]
