"""The package layout is the architecture: layers import only downwards, no import cycles, no
two files of the same name, no loose modules at the top level."""

import ast
from collections import defaultdict
from pathlib import Path

import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

PACKAGE = Path(__file__).resolve().parent.parent / "ditch_drake"

# Lowest first; a module may import its own layer and the layers below it.
LAYERS = [
    {"common"},
    {"spec"},
    {"world"},
    {"perception", "planning", "learning"},
    {"systems"},
    {"diagrams"},
    {"demos"},
    {"evaluation"},
    {"gym", "benchmark"},
    {"pipelines"},
    {"perf", "validation"},
    {"docs_tools"},
    {"cli"},
]
RANK = {part: rank for rank, parts in enumerate(LAYERS) for part in parts}
TOP_LEVEL_MODULES = {"__init__.py"}


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(("ditch_drake", *parts))] = path
    return modules


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """The ditch_drake modules `path` imports, at the top or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        for name in names:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name and name != "ditch_drake":
                found.add(name)
    return found


def _part(module: str) -> str:
    return module.split(".")[1] if module.count(".") >= 1 else module


def test_layers_import_only_downwards():
    modules = _modules()
    upward = [f"{module} -> {imported}" for module, path in modules.items() if _part(module) in RANK
              for imported in _imports(path, modules)
              if _part(imported) in RANK and RANK[_part(imported)] > RANK[_part(module)]]
    assert upward == []


def test_every_part_has_a_layer():
    parts = {_part(module) for module in _modules() if module != "ditch_drake"}
    assert parts - set(RANK) <= {"models", "models_sdf"}


def test_no_import_cycles():
    modules = _modules()
    names = sorted(modules)
    index = {name: i for i, name in enumerate(names)}
    edges = [(index[module], index[imported]) for module in names for imported in _imports(modules[module], modules)
             if imported != module and modules[module].name != "__init__.py"]
    rows, cols = zip(*edges)
    _, labels = connected_components(csr_matrix(([1] * len(edges), (rows, cols)), shape=(len(names),) * 2),
                                     directed=True, connection="strong")
    groups = defaultdict(list)
    for name, label in zip(names, labels):
        groups[label].append(name)
    assert [group for group in groups.values() if len(group) > 1] == []


def test_no_two_files_share_a_name():
    by_name = defaultdict(list)
    for path in PACKAGE.rglob("*.py"):
        if path.name != "__init__.py":
            by_name[path.name].append(str(path.relative_to(PACKAGE)))
    assert {name: paths for name, paths in by_name.items() if len(paths) > 1} == {}


def test_no_loose_modules_at_the_top_level():
    assert {path.name for path in PACKAGE.glob("*.py")} == TOP_LEVEL_MODULES


@pytest.mark.parametrize("module", sorted(_modules()))
def test_every_module_imports(module):
    __import__(module)
