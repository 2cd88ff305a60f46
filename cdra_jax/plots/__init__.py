"""Figures: the paper's Figs. 5 and 7, sweeps, calibration and validation residuals, diagnosis.

Every function returns a bare :class:`matplotlib.figure.Figure` on the Agg canvas
(:mod:`.canvas`): nothing here touches pyplot or matplotlib's global state.
"""

from .calibration import calibration_residuals_figure as calibration_residuals_figure
from .canvas import new_figure as new_figure
from .diagnosis import regressors as regressors
from .diagnosis import residual_per_pose_figure as residual_per_pose_figure
from .diagnosis import residual_vs_regressors_figure as residual_vs_regressors_figure
from .diagnosis import save_diagnosis_plots as save_diagnosis_plots
from .reproduction import convergence_figure as convergence_figure
from .reproduction import noise_figure as noise_figure
from .reproduction import parameter_error_figure as parameter_error_figure
from .sweeps import plot_sweep as plot_sweep
from .sweeps import plot_sweep_figure as plot_sweep_figure
from .validation import validation_figure as validation_figure
