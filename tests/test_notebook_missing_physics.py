"""Notebook 03 runs at reduced size (CDRA_NOTEBOOK_FAST=1) and is committed without outputs.

(When tests/test_notebooks.py lists it, that shared test covers the same ground.)
"""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "03_missing_physics.ipynb"


def test_committed_without_outputs_and_with_a_parameters_cell():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    tagged = [c for c in nb.cells if "parameters" in c.get("metadata", {}).get("tags", [])]
    assert len(tagged) == 1 and "CDRA_NOTEBOOK_FAST" in tagged[0].source
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.get("outputs", []) == [] and cell.get("execution_count") is None


@pytest.mark.slow
def test_runs_at_reduced_size(monkeypatch):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    root = str(NOTEBOOK.parents[1])
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", root + (os.pathsep + path if path else ""))
    monkeypatch.setenv("CDRA_NOTEBOOK_FAST", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": root}}
    ).execute()
    text = "\n".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "Most likely missing physics: the shoulder module's cables stretch" in text
    assert "held-out position error" in text
