"""Execute the notebooks at reduced size (nbclient), and check that they are committed clean.

Each notebook has a code cell tagged ``parameters`` that sets its sizes; the test inserts a cell
after it that overrides them (as papermill does). Add a notebook by adding an entry to
``NOTEBOOKS``.
"""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"

NOTEBOOKS: dict[str, dict[str, object]] = {
    "01_paper_reproduction.ipynb": {
        "TABLE_M_VERIFY": 20,
        "CONVERGENCE_TRIALS": 16,
        "NOISE_TRIALS": 16,
        "NOISE_M_VALUES": (4, 8, 40),
        "NOISE_M_VERIFY": 10,
        "NOISE_PAD_TO": 40,
        "FAST_COMPILE": True,
    },
    # Notebooks 02-04 read CDRA_NOTEBOOK_FAST=1 (always set) in their parameters cell.
    "02_noise_sensitivity.ipynb": {},
    "03_missing_physics.ipynb": {},
    "04_cdpm_modules.ipynb": {},
}
"""Notebook file name -> the parameter overrides that make it run in well under a minute."""

_TRIALS_01 = NOTEBOOKS["01_paper_reproduction.ipynb"]["CONVERGENCE_TRIALS"]

EXPECTED_TEXT: dict[str, tuple[str, ...]] = {
    "01_paper_reproduction.ipynb": (
        # Table I: base and tool recovered, the middle rows differ by a null-space move only
        "-> recovered exactly (< 1e-8): base, tool",
        "unidentifiable directions at the actual arm (rank 22 of 24)",
        "only the elbow-axis screw differs: True",
        "within its 4-decimal rounding (<= 2.4e-04): True",
        # Fig. 5: every noise-free draw converges, within the paper's few iterations
        f"solver converged in {_TRIALS_01}/{_TRIALS_01} trials",
        "(the paper: 'within three to four iterations')",
        # Fig. 7: the weighted solver reaches the noise floor (where the curves flatten) and
        # beats the paper's unweighted form
        "weighted solver within 25 % of the noise floor at m = 40: True",
        "weighted solver more accurate than the paper's at m = 40: True",
        "the weighted solver's curves against measured poses flatten at m = ",
    ),
    "02_noise_sensitivity.ipynb": (
        "predicted",
        "selected",
        "not identifiable on its own",
        "mm per mm",  # the influence of each measured pose, by jax.jacrev through the solver
    ),
    "03_missing_physics.ipynb": (
        "Most likely missing physics: the shoulder module's cables stretch",
        "held-out position error",
    ),
    "04_cdpm_modules.ipynb": (
        "100% successful",  # forward kinematics from exact lengths
        "lengths.csv: row 3, column shoulder.l3: no pose of module 'shoulder'",
        "sampled states with tension closure in every module: True",
        "simulate_trial's states with tension closure: True",
        "100% solved",  # holding tensions
        "calibrated from the file (states from lengths)",
        "self-calibration from exact lengths: successful",
        "self-calibration from noisy lengths: successful",
        "self-calibration of shoulder: rank 36 of 42 parameters",
        "rotation of all shoulder base points about the module centre",
        "self-calibration of elbow: rank 7 of 14 parameters",
    ),
}
"""Text each notebook's printed output must contain when run at reduced size."""

MIN_IMAGES: dict[str, int] = {
    "01_paper_reproduction.ipynb": 3,
    "02_noise_sensitivity.ipynb": 0,  # draws with the Agg backend and saves; checked by its text
    "03_missing_physics.ipynb": 2,
    "04_cdpm_modules.ipynb": 3,
}
"""Minimum number of PNG outputs each notebook shows inline."""


def _read(name: str) -> nbformat.NotebookNode:
    return nbformat.read(NOTEBOOK_DIR / name, as_version=4)


def _parameters_index(nb: nbformat.NotebookNode, name: str) -> int:
    tagged = [
        i
        for i, c in enumerate(nb.cells)
        if c.cell_type == "code" and "parameters" in c.get("metadata", {}).get("tags", [])
    ]
    assert len(tagged) == 1, f"{name}: expected one code cell tagged 'parameters', got {tagged}"
    return tagged[0]


def test_every_notebook_is_listed():
    assert sorted(p.name for p in NOTEBOOK_DIR.glob("*.ipynb")) == sorted(NOTEBOOKS)


@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_notebook_committed_without_outputs(name):
    nb = _read(name)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.get("outputs", []) == [], f"{name}: cell {i} has outputs"
            assert cell.get("execution_count") is None, f"{name}: cell {i} has a count"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_notebook_runs(name, monkeypatch):
    nb = _read(name)
    overrides = NOTEBOOKS[name]
    i = _parameters_index(nb, name)
    known = nb.cells[i].source
    for key in overrides:
        assert f"{key} =" in known, f"{name}: parameter {key} is not set in the parameters cell"
    source = "\n".join(f"{k} = {v!r}" for k, v in overrides.items())
    nb.cells.insert(i + 1, nbformat.v4.new_code_cell(source, metadata={"tags": ["injected"]}))
    # The kernel imports this checkout's cdra_jax, whatever is installed.
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", str(ROOT) + (os.pathsep + path if path else ""))
    monkeypatch.setenv("CDRA_NOTEBOOK_FAST", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    client = NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    )
    client.execute()
    images = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if "image/png" in o.get("data", {})
    ]
    need = MIN_IMAGES.get(name, 1)
    assert len(images) >= need, f"{name}: expected {need} figures as PNG outputs, got {len(images)}"
    text = "\n".join(
        o.get("text", "")
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "stream"
    )
    for part in EXPECTED_TEXT.get(name, ()):
        assert part in text, f"{name}: expected {part!r} in the printed output"
