"""Where a page made from results goes: by default beside the results, never over a file git
tracks unless named (`tracked_by_git`), and never over the results it is made from
(`refuse_outputs_over_inputs`)."""

import fnmatch
import os
import subprocess
from collections.abc import Iterable
from pathlib import Path

from ditch_drake.common.errors import ConfigError


def default_outputs(results: list[str | os.PathLike]) -> tuple[Path, Path]:
    """Where `ditch-drake report` writes by default: beside the first results entry.

    A folder `results/paper` gives `results/paper/report.md`; a file `results/x.jsonl` gives
    `results/x_report.md`. The figures go to the page's name with `_img` beside it
    (`results/paper/report_img/`, `results/x_report_img/`).
    """
    first = Path(results[0])
    out = first / "report.md" if first.is_dir() else first.with_name(f"{first.stem}_report.md")
    return out, figures_beside(out)


def figures_beside(out: str | os.PathLike) -> Path:
    """The default figures folder of a page: `<page name>_img` beside it."""
    out = Path(out)
    return out.with_name(f"{out.stem}_img")


def tracked_by_git(path: str | os.PathLike) -> bool:
    """Whether git tracks `path` (for a folder: any file under it). Not a git checkout, or no
    git on this machine: False."""
    path = Path(os.path.abspath(path))
    existing = next(folder for folder in [path, *path.parents] if folder.is_dir())
    try:
        result = subprocess.run(["git", "-C", str(existing), "ls-files", "--error-unmatch", "--",
                                 os.path.relpath(path, existing)], capture_output=True, timeout=30, check=False)
    except (OSError, subprocess.SubprocessError):
        return False
    return result.returncode == 0


def refuse_outputs_over_inputs(outputs: dict[str, str | os.PathLike], inputs: Iterable[str | os.PathLike],
                               read_in_folders: tuple[str, ...] = ("*.jsonl",), recursive: bool = False) -> None:
    """Refuses outputs that would replace what they are made from, before anything is written.

    Args:
        outputs: each output's path by what it is ("--out page", "--figures folder").
        inputs: the results files and folders read; also any file read beside them.
        read_in_folders: name patterns of the files read in an input folder: an output of such
            a name in one is refused even where no such file is there yet, as the next run
            would read it as results.
        recursive: the files matching `read_in_folders` are read in the folders' subfolders too.

    Raises:
        ConfigError: an output that is an input, or would be read as one, or two outputs at one
            path, naming the path and what was expected.
    """
    inputs = [Path(os.path.abspath(entry)) for entry in inputs]
    folders = [entry for entry in inputs if entry.is_dir()]
    seen: dict[Path, str] = {}
    for what, path in outputs.items():
        target = Path(os.path.abspath(path))
        if target in seen:
            raise ConfigError(f"{what} {path} is also the {seen[target]}: expected separate paths")
        seen[target] = what
        resolved = target.resolve()
        for entry in inputs:
            if resolved == entry.resolve():
                raise ConfigError(f"{what} {path} is the input {entry} the page is made from: expected a path "
                                  "apart from the results (writing there would replace them)")
        for folder in folders:
            inside = resolved.parent == folder.resolve() or (recursive and folder.resolve() in resolved.parents)
            if inside and any(fnmatch.fnmatch(resolved.name, pattern) for pattern in read_in_folders):
                raise ConfigError(f"{what} {path} is a results file of the folder {folder} the page is made from: "
                                  "expected a path apart from the results (writing there would replace them, or "
                                  "be read as results next time)")
