"""cdra_jax: differentiable kinematic calibration of modular robot arms in JAX.

Implements Mustafa, Yang, Yeo and Lin, "Kinematic calibration of a 7-DOF self-calibrated
modular cable-driven robotic arm" (ICRA 2008): the SE(3) maps of its appendix (:mod:`.lie`), the
modular arm (:mod:`.arm`), the local-POE calibration model and its solvers
(:mod:`.calibration`), identifiability analysis, simulation and file I/O. What a user runs
(calibrate, validate, diagnose, simulate, sweep, plan poses) is in :mod:`.workflows`, which the
command line (:mod:`.cli`) and the notebooks share.
"""

import importlib.metadata
from typing import TYPE_CHECKING

from . import arm as arm
from . import calibration as calibration
from . import compilation as compilation
from . import identifiability as identifiability
from . import io as io
from . import lie as lie
from . import modules as modules
from . import pose_selection as pose_selection
from . import simulation as simulation
from . import sweeps as sweeps
from . import uncertainty as uncertainty
from ._lazy import lazy_names
from .arm import Arm as Arm
from .arm import Module as Module
from .arm import apply_frame_errors as apply_frame_errors
from .arm import error_twists as error_twists
from .arm import forward_kinematics as forward_kinematics
from .arm import frame_errors as frame_errors
from .arm import tool_pose as tool_pose
from .calibration import RESULTS as RESULTS
from .calibration import CalibrationSolution as CalibrationSolution
from .calibration import NoiseModel as NoiseModel
from .calibration import calibrate_lm as calibrate_lm
from .calibration import calibrate_paper as calibrate_paper
from .calibration import calibrate_robust as calibrate_robust
from .calibration import deviation_metrics as deviation_metrics
from .compilation import compiler_options as compiler_options
from .compilation import jit as jit
from .io import check_plausibility as check_plausibility
from .io import default_arm as default_arm
from .io import load_measurements as load_measurements
from .io import load_model as load_model
from .io import load_result as load_result
from .io import save_measurements as save_measurements
from .io import save_model as save_model
from .io import save_result as save_result
from .pose_selection import prediction_bound as prediction_bound
from .pose_selection import select_poses as select_poses
from .sweeps import run_sweep as run_sweep
from .uncertainty import analyze_uncertainty as analyze_uncertainty

if TYPE_CHECKING:  # imported on first use: the figures, the paper's reproduction, workflows,
    # the optimistix reference solver (optimistix takes a tenth of a second to import)
    from . import plots as plots
    from . import reproduction as reproduction
    from . import workflows as workflows
    from .calibration import calibrate_lm_optimistix as calibrate_lm_optimistix

__getattr__, __dir__ = lazy_names(
    __name__,
    {
        "plots": "",
        "reproduction": "",
        "workflows": "",
        "calibrate_lm_optimistix": "calibration",
    },
)

__version__ = importlib.metadata.version("cdra_jax")
