"""Workflows: what a user runs, from Python, a notebook or the command line alike.

Each function takes a model (an :class:`~cdra_jax.arm.Arm`, a model TOML path, or ``None`` for
the embedded default arm) and data, and returns a result object with ``to_dict()`` /
``to_json()`` (what the command writes), ``report()`` (the text the command prints), ``plot()``
(a matplotlib figure) and ``save(...)``. ``cdra-jax <command>`` is a thin argparse layer over
these functions (:mod:`cdra_jax.cli`).
"""

from .calibrate import LOSSES as LOSSES
from .calibrate import SOLVERS as SOLVERS
from .calibrate import CalibrationRun as CalibrationRun
from .calibrate import calibrate as calibrate
from .demo import DemoRun as DemoRun
from .demo import demo as demo
from .diagnose import DiagnosisRun as DiagnosisRun
from .diagnose import diagnose as diagnose
from .export_model import ExportedURDF as ExportedURDF
from .export_model import export_urdf as export_urdf
from .import_model import ImportedModel as ImportedModel
from .import_model import import_dh as import_dh
from .import_model import import_urdf as import_urdf
from .inputs import noise_model as noise_model
from .plan_poses import PosePlan as PosePlan
from .plan_poses import plan_poses as plan_poses
from .simulate import SimulationRun as SimulationRun
from .simulate import simulate as simulate
from .sweep import SweepRun as SweepRun
from .sweep import sweep as sweep
from .validate import ValidationRun as ValidationRun
from .validate import validate as validate
