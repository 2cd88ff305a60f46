"""The notebooks: stored with their outputs, and executed again at reduced size (nbclient).

The stored notebooks carry the outputs of a top-to-bottom run (with ``CDRA_NOTEBOOK_FAST=1``):
every code cell executed in order, figures as PNG, no errors. The slow test re-executes each one
at reduced size in one shared kernel (its namespace reset before each notebook; imported modules
and their compiled functions are kept, which saves the start-up and part of the compilation).
Each notebook has a code cell tagged ``parameters`` that sets its sizes; the test inserts a cell
after it that overrides them (as papermill does). Add a notebook by adding an entry to
``NOTEBOOKS``.
"""

from collections.abc import Iterator

import nbformat
import pytest
from _subprocess import ROOT, checkout_env
from jupyter_client.manager import KernelManager
from nbclient import NotebookClient

from cdra_jax.compilation import GC_THRESHOLDS

NOTEBOOK_DIR = ROOT / "notebooks"
CELL_TIMEOUT_S = 300
"""Per-cell execution limit of the re-execution (nbclient ``timeout``)."""

NOTEBOOKS: dict[str, dict[str, object]] = {
    "01_paper_reproduction.ipynb": {
        "TABLE_M_VERIFY": 20,
        "CONVERGENCE_TRIALS": 8,
        "NOISE_TRIALS": 8,
        "NOISE_M_VALUES": (4, 8, 40),
        "NOISE_M_VERIFY": 10,
        "NOISE_PAD_TO": 40,
        "FAST_COMPILE": True,
    },
    # Notebooks 02-04 read CDRA_NOTEBOOK_FAST=1 (always set) in their parameters cell; their fast
    # sizes (those of the stored outputs) are reduced further here. Compilation dominates, so the
    # pose counts are chosen to repeat shapes the kernel has already compiled: 02 calibrates 15
    # simulated poses (workflows.calibrate), and 03 (M) and 04 (N_CSV) calibrate 15 as well, which
    # reuses that program; 04 samples 15 states everywhere (one compiled sampler).
    "02_noise_sensitivity.ipynb": {
        "NOISE_POS": [0.08],
        "NOISE_ROT": [1e-3],
        "POSE_COUNTS": [8],
        "SOLVERS": ["weighted"],
        "TRIALS": 4,
        "SELECT_M": [8],
        "SELECT_TRIALS": 4,
        "POOL": 100,
    },
    "03_missing_physics.ipynb": {"M": 15, "HELD_OUT": 15},
    "04_cdpm_modules.ipynb": {
        "N_POSES": 15,
        "GRID": 21,
        "N_UNIFORM": 1000,
        "N_CSV": 15,
        "SELF_CAL_POSES": 15,
    },
    # 05 calibrates the shipped example data (examples/ur5) in full; only the truth check shrinks.
    "05_calibrate_your_arm.ipynb": {"TRUTH_STATES": 20},
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
        "median held-out dp (mm) / dR (rad), converged fraction:",  # workflows.sweep report
        "predicted",
        "selected",
        "not identifiable on its own",  # the uncertainty report of workflows.calibrate
        "mm per mm",  # the influence of each measured pose, by jax.jacrev through the solver
    ),
    "03_missing_physics.ipynb": (
        "nominal position [mm]",  # workflows.validate of the calibration on held-out poses
        "Most likely missing physics: the shoulder module's cables stretch",
        "held-out position error",
        "predicted with the model's effects: cable_elasticity@shoulder",  # the refit model
        "with the effect",
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
    "05_calibrate_your_arm.ipynb": (
        "ur5_markers.toml has the imported frames: True",
        "fit.csv reproduced by workflows.simulate: True",  # the shipped data are current
        "solver: auto (Huber loss",  # the default solver on points in the tracker's frame
        "start: base frame registered to the measuring device's frame",
        "held-out position error on test.csv",
        "calibrated model within 0.1 mm of the true arm: True",
        "read back: the file's chain equals the model's frames",
    ),
}
"""Text each notebook's printed output must contain when run at reduced size."""

MIN_IMAGES: dict[str, int] = {
    "01_paper_reproduction.ipynb": 3,  # Fig. 5, Fig. 7, the parameter error
    "02_noise_sensitivity.ipynb": 4,  # sweep, Cramer-Rao overlay, calibration, pose selection
    "03_missing_physics.ipynb": 3,  # validation, residuals vs regressors, residuals per pose
    "04_cdpm_modules.ipynb": 3,  # closure margin, tensions, self-calibration
    "05_calibrate_your_arm.ipynb": 3,  # the imported chain, held-out errors, error vs the truth
}
"""Minimum number of PNG outputs each notebook shows inline (stored and re-executed)."""


def _read(name: str) -> nbformat.NotebookNode:
    return nbformat.read(NOTEBOOK_DIR / name, as_version=4)


def _outputs(nb: nbformat.NotebookNode) -> list[dict]:
    return [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]


def _images(nb: nbformat.NotebookNode) -> int:
    return sum("image/png" in o.get("data", {}) for o in _outputs(nb))


def _errors(nb: nbformat.NotebookNode) -> list[str]:
    """Error outputs and stderr text with a traceback, as short descriptions."""
    out = []
    for o in _outputs(nb):
        if o.get("output_type") == "error":
            out.append(f"error output {o.get('ename')}: {o.get('evalue')}")
        elif o.get("output_type") == "stream" and o.get("name") == "stderr":
            if "Traceback" in o.get("text", ""):
                out.append(f"traceback on stderr: {o['text'][:300]}")
    return out


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
def test_notebook_stored_with_outputs(name):
    """Stored from one top-to-bottom run: every code cell executed in order, the figures
    present as PNG, no error outputs or tracebacks."""
    nb = _read(name)
    code = [c for c in nb.cells if c.cell_type == "code"]
    counts = [c.get("execution_count") for c in code]
    assert counts == list(range(1, len(code) + 1)), (
        f"{name}: not stored from one run in order (execution counts {counts})"
    )
    assert _outputs(nb), f"{name}: stored without outputs"
    need = MIN_IMAGES[name]
    assert _images(nb) >= need, f"{name}: expected {need} stored PNG figures, got {_images(nb)}"
    assert not _errors(nb), f"{name}: {_errors(nb)}"


@pytest.fixture(scope="module")
def kernel() -> Iterator[KernelManager]:
    """One Python kernel for all notebooks, importing this checkout's cdra_jax."""
    env = checkout_env(CDRA_NOTEBOOK_FAST="1", MPLBACKEND="Agg")
    km = KernelManager(kernel_name="python3")
    km.start_kernel(env=env, cwd=str(ROOT))
    try:
        yield km
    finally:
        km.shutdown_kernel(now=True)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(NOTEBOOKS))
def test_notebook_runs(name, kernel):
    nb = _read(name)
    for cell in nb.cells:
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None
    overrides = NOTEBOOKS[name]
    i = _parameters_index(nb, name)
    known = nb.cells[i].source
    for key in overrides:
        assert f"{key} =" in known, f"{name}: parameter {key} is not set in the parameters cell"
    source = "\n".join(f"{k} = {v!r}" for k, v in overrides.items())
    nb.cells.insert(i + 1, nbformat.v4.new_code_cell(source, metadata={"tags": ["injected"]}))
    # A clean namespace, as in a fresh kernel (the imported modules stay), and the cycle
    # collector's thresholds of the test processes (tests/conftest.py) in the kernel too.
    preamble = f"%reset -f\nimport gc\ngc.set_threshold{GC_THRESHOLDS}"
    nb.cells.insert(0, nbformat.v4.new_code_cell(preamble, metadata={"tags": ["injected"]}))
    client = NotebookClient(
        nb, km=kernel, timeout=CELL_TIMEOUT_S, interrupt_on_timeout=True, kernel_name="python3"
    )
    try:
        client.execute()
    finally:
        if client.kc is not None:
            client.kc.stop_channels()
    need = MIN_IMAGES[name]
    assert _images(nb) >= need, f"{name}: expected {need} figures as PNG outputs, got {_images(nb)}"
    assert not _errors(nb), f"{name}: {_errors(nb)}"
    text = "\n".join(o.get("text", "") for o in _outputs(nb) if o.get("output_type") == "stream")
    for part in EXPECTED_TEXT.get(name, ()):
        assert part in text, f"{name}: expected {part!r} in the printed output"
