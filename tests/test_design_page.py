"""docs/design.md agrees with the code, and every pointer to it names one of its sections.

A table row of the page whose last cell links a module of the package and names an
expression (`[robot.py](../ditch_drake/spec/robot.py) `TRACK_M``) shows, in its second
cell, the numbers that expression gives in that module, to the precision printed.
"""

import importlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "design.md"
_CODE_CELL = re.compile(r"\]\(\.\./(ditch_drake/[\w/]+)\.py\)\s*`([^`]+)`\s*$")
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?")
_POINTER = re.compile(r'docs/design\.md, "([^"]+)"')
PAPER_ENVIRONMENTS = ("crater", "wide", "narrow", "sine")


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def _code_rows() -> list[tuple[str, str, str, str]]:
    rows = []
    for line in PAGE.read_text().splitlines():
        if not line.startswith("|"):
            continue
        cells = _cells(line)
        match = _CODE_CELL.search(cells[-1])
        if match:
            rows.append((cells[0], cells[1], match.group(1).replace("/", "."), match.group(2)))
    return rows


def _shown_matches(shown: str, values: np.ndarray) -> bool:
    numbers = _NUMBER.findall(shown)
    if len(numbers) != values.size:
        return False
    for text, value in zip(numbers, values):
        decimals = len(text.partition(".")[2])
        if not abs(float(text) - float(value)) <= 0.5 * 10.0**-decimals + 1e-9:
            return False
    return True


def test_the_page_is_a_manual_page_of_reasonable_size():
    assert PAGE.stat().st_size < 40_000
    assert len(_code_rows()) >= 60


@pytest.mark.parametrize("quantity, shown, module, expression", _code_rows(), ids=lambda value: str(value)[:40])
def test_every_table_number_is_the_code_s(quantity, shown, module, expression):
    namespace = vars(importlib.import_module(module))
    value = eval(expression, dict(namespace))
    values = np.ravel(np.asarray(value, dtype=float))
    assert _shown_matches(shown, values), f"{quantity!r}: the page shows {shown!r}, {module}.{expression} is {value!r}"


def test_the_environment_table_is_the_packaged_environments():
    rows = {cells[0]: cells for line in PAGE.read_text().splitlines()
            if line.startswith("|") and (cells := _cells(line))[0] in PAPER_ENVIRONMENTS}
    assert sorted(rows) == sorted(PAPER_ENVIRONMENTS)
    for name, (_, course, bottom, depth, slope, hinge, tasks) in rows.items():
        environment = get_environment(name)
        terrain = environment.terrain
        assert course == terrain.course
        values = [terrain.bottom_width_m, terrain.depth_m, terrain.slope_deg,
                  DitchTerrain(terrain).hinge_distance_m, len(environment.tasks)]
        assert _shown_matches(" ".join([bottom, depth, slope, hinge, tasks]), np.array(values, dtype=float)), name


def _headings() -> set[str]:
    return {line[3:].strip() for line in PAGE.read_text().splitlines() if line.startswith("## ")}


def _pointer_sources() -> list[Path]:
    sources = []
    for folder, patterns in (("ditch_drake", ("*.py", "*.yaml")), ("tests", ("*.py",)),
                             ("experiments", ("*.yaml",)), ("examples", ("*.py", "*.yaml")),
                             ("notebooks", ("*.ipynb",))):
        for pattern in patterns:
            sources += sorted((ROOT / folder).rglob(pattern))
    return sources


def test_every_pointer_to_the_page_names_one_of_its_sections():
    headings = _headings()
    pointers = 0
    for path in _pointer_sources():
        text = path.read_text()
        if path.suffix == ".ipynb":
            text = "\n".join("".join(cell["source"]) for cell in json.loads(text)["cells"])
        for section in _POINTER.findall(text):
            pointers += 1
            assert section in headings, f"{path.relative_to(ROOT)} points at docs/design.md, {section!r}: no such section"
    assert pointers > 0


def test_the_sections_other_pages_link_to_are_stable():
    assert {"The robot", "The action table", "The observation", "The control schedule", "The ditches",
            "Outcomes and regions", "Reading the paper"} <= _headings()


def test_no_citation_of_a_spec_document():
    for path in _pointer_sources():
        if path == Path(__file__).resolve():
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            assert not re.search(r"\bSPEC\b", line), f"{path.relative_to(ROOT)}:{number} cites SPEC: {line.strip()}"



def test_every_relative_link_of_the_page_resolves():
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", PAGE.read_text())
    missing = [link for link in links if "://" not in link and not (PAGE.parent / link).exists()]
    assert not missing, f"docs/design.md links to missing files: {missing}"
