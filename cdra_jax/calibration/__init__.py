"""Calibration model (Eqs. 7-9), solvers (Eqs. 10-19) and deviation metrics (Eqs. 20-21)."""

from .gauss_newton import calibrate_paper as calibrate_paper
from .levenberg_marquardt import calibrate_lm as calibrate_lm
from .linear import default_rcond as default_rcond
from .linear import min_norm_lstsq as min_norm_lstsq
from .model import NoiseModel as NoiseModel
from .model import calibration_jacobian as calibration_jacobian
from .model import deviation_metrics as deviation_metrics
from .model import pose_errors as pose_errors
from .model import residual_twist as residual_twist
from .model import stacked_system as stacked_system
from .model import whitening as whitening
from .solution import RESULTS as RESULTS
from .solution import CalibrationSolution as CalibrationSolution
from .solution import result_messages as result_messages
from .solution import result_names as result_names
from .validation import MIN_POSES as MIN_POSES
from .validation import check_problem as check_problem
