"""Every notebook runs top to bottom (short mode: small loops, no waiting for a person)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parent.parent / "notebooks").glob("*.ipynb"))


def test_there_are_the_five_notebooks():
    assert [path.name for path in NOTEBOOKS] == [
        "01_environments.ipynb", "02_perception.ipynb", "03_demonstrations.ipynb", "04_train_and_evaluate.ipynb",
        "05_benchmark.ipynb"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebooks_are_committed_without_outputs(path):
    notebook = nbformat.read(path, as_version=4)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert code and all(not cell.outputs and cell.execution_count is None for cell in code)


# The training notebook takes about 40 s on 2 cores: it runs with `-m slow`, the others by default.
@pytest.mark.parametrize("path", [pytest.param(path, marks=pytest.mark.slow) if path.stem == "04_train_and_evaluate"
                                  else path for path in NOTEBOOKS], ids=lambda path: path.stem)
def test_notebook_runs_top_to_bottom(path, tmp_path, monkeypatch):
    # The kernel inherits this environment: short mode; Drake deprecations are errors in its first cell.
    monkeypatch.setenv("DITCH_DRAKE_NOTEBOOK_SHORT", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    notebook = nbformat.read(path, as_version=4)
    assert "DrakeDeprecationWarning" in notebook.cells[1].source
    NotebookClient(notebook, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(path.parent.parent)}}).execute()
    errors = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.outputs
              if output.output_type == "error"]
    assert not errors
