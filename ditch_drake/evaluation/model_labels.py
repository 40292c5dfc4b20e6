"""How the results pages name the controllers of records: a checkpoint by its file stem (its
folder too where stems clash), and the experiment's `<environments>_<N>` models parsed back."""

from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

from ditch_drake.evaluation.results import RolloutRecord


def model_label(record: RolloutRecord) -> str:
    """A short name of the controller: the checkpoint's file stem, or the controller."""
    return Path(record.checkpoint).stem if record.checkpoint else record.controller


def controller_labels(records: list[RolloutRecord]) -> Callable[[RolloutRecord], str]:
    """Each record's controller as the page names it: `model_label` (the checkpoint's file
    stem), preceded by its folder where checkpoints of one stem lie in several."""
    paths = defaultdict(set)
    for record in records:
        if record.checkpoint:
            paths[model_label(record)].add(record.checkpoint)
    shared = {stem for stem, found in paths.items() if len(found) > 1}

    def label(record: RolloutRecord) -> str:
        stem = model_label(record)
        folder = Path(record.checkpoint).parent.name if stem in shared else ""
        return f"{folder}/{stem}" if folder else stem

    return label


def model_demos(label: str) -> int | None:
    """N of a model named `<envs>_<N>` (as the experiment names them), else None."""
    tail = label.rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else None


def model_environments(label: str) -> list[str]:
    """The environments a model named `<env>+<env>_<N>` was trained in; any other name: itself."""
    return label.rsplit("_", 1)[0].split("+") if model_demos(label) is not None else [label]
