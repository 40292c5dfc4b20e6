"""The reference pages (docs/reference) are what the parser and the dataclasses make now, and
the command line's defaults are the dataclasses'."""

import argparse
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ditch_drake.cli import build_parser
from ditch_drake.cli.options import ConfigDefault

REFERENCE = Path(__file__).resolve().parent.parent / "docs" / "reference"
REGENERATE = "ditch-drake reference --out docs/reference"


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    # A process of its own: a controller that another test registered would join the pages here.
    out = tmp_path_factory.mktemp("reference")
    # A narrow terminal: the pages must not depend on its width.
    subprocess.run([sys.executable, "-m", "ditch_drake.cli", "reference", "--out", str(out)], check=True,
                   capture_output=True, text=True, env={**os.environ, "COLUMNS": "37"})
    return out


def test_the_committed_pages_are_the_generated_ones(generated):
    committed = {path.name: path.read_text() for path in REFERENCE.glob("*.md")}
    fresh = {path.name: path.read_text() for path in generated.glob("*.md")}
    assert sorted(committed) == sorted(fresh), f"run `{REGENERATE}`"
    stale = [name for name in fresh if committed[name] != fresh[name]]
    assert stale == [], f"{stale} differ from what the parser and the dataclasses make now: run `{REGENERATE}`"


def test_every_page_is_under_40_kb(generated):
    assert {path.name: path.stat().st_size for path in generated.glob("*.md")
            if path.stat().st_size >= 40_000} == {}


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction))
    return dict(action.choices)


def test_every_command_and_option_is_in_the_command_line_page(generated):
    page = "\n".join(path.read_text() for path in sorted(generated.glob("cli*.md")))
    for name, command in _commands(build_parser()).items():
        assert f"\n## ditch-drake {name}\n" in page
        for action in command._actions:
            if not isinstance(action, argparse._HelpAction):
                assert all(f"`{option}" in page for option in action.option_strings), (name, action.option_strings)


def test_every_scenario_field_is_in_the_scenario_page(generated):
    from ditch_drake.diagrams.controllers import controller_names
    from ditch_drake.diagrams.scenario import Scenario

    page = (generated / "scenario.md").read_text()
    section = page.split("\n## Scenario\n", 1)[1].split("\n## ", 1)[0]
    assert [field.name for field in dataclasses.fields(Scenario)] == [
        line.split("`")[1] for line in section.splitlines() if line.startswith("| `")]
    controllers = (generated / "controllers.md").read_text()
    assert all(f"| `{name}` |" in controllers for name in controller_names())


def _config_defaults() -> list[tuple[str, ConfigDefault]]:
    found = []
    for name, command in _commands(build_parser()).items():
        for action in command._actions:
            for value in (action.default, getattr(action, "built_in", None)):
                if isinstance(value, ConfigDefault):
                    found.append((f"{name} {action.dest}", value))
    return found


@pytest.mark.parametrize("option, default", _config_defaults(), ids=lambda item: item if isinstance(item, str) else "")
def test_a_default_read_from_the_source_is_the_imported_ones(option, default):
    """Help reads a literal default from the source, so as not to import Drake and torch."""
    assert default.value == default.imported_value(), option
