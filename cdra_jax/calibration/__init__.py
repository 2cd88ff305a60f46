"""Calibration model (Eqs. 7-9), solvers (Eqs. 10-19) and deviation metrics (Eqs. 20-21)."""

from typing import TYPE_CHECKING

from .._lazy import lazy_names
from .auto import AutoSolution as AutoSolution
from .auto import calibrate_auto as calibrate_auto
from .gauge import GaugeFix as GaugeFix
from .gauge import to_nominal_gauge as to_nominal_gauge
from .gauss_newton import calibrate_paper as calibrate_paper
from .levenberg_marquardt import calibrate_lm as calibrate_lm
from .linear import default_rcond as default_rcond
from .linear import min_norm_lstsq as min_norm_lstsq
from .model import NoiseModel as NoiseModel
from .model import calibration_jacobian as calibration_jacobian
from .model import deviation_metrics as deviation_metrics
from .model import point_residual as point_residual
from .model import pose_errors as pose_errors
from .model import residual_twist as residual_twist
from .model import stacked_system as stacked_system
from .model import tool_points as tool_points
from .model import whitening as whitening
from .observations import Observations as Observations
from .observations import make_observations as make_observations
from .registration import rigid_registration as rigid_registration
from .robust import CAUCHY_C as CAUCHY_C
from .robust import HUBER_C as HUBER_C
from .robust import OUTLIER_THRESHOLD as OUTLIER_THRESHOLD
from .robust import Cauchy as Cauchy
from .robust import Huber as Huber
from .robust import RobustLoss as RobustLoss
from .robust import RobustSolution as RobustSolution
from .robust import calibrate_robust as calibrate_robust
from .robust import robust_loss as robust_loss
from .robust import standardized_residuals as standardized_residuals
from .solution import RESULTS as RESULTS
from .solution import CalibrationSolution as CalibrationSolution
from .solution import result_messages as result_messages
from .solution import result_names as result_names
from .validation import MIN_POSES as MIN_POSES
from .validation import check_problem as check_problem

if TYPE_CHECKING:  # imported on first use (optimistix takes a tenth of a second to import)
    from .optimistix_lm import calibrate_lm_optimistix as calibrate_lm_optimistix

__getattr__, __dir__ = lazy_names(__name__, {"calibrate_lm_optimistix": "optimistix_lm"})
