"""CDPM modules: cable kinematics, tension closure, statics and self-calibration.

Each module of the arm (:class:`cdra_jax.arm.Module`) may carry cables. This package models
them as cable-driven parallel mechanisms: straight cables between attachment points on the
module base and the moving platform (:mod:`.cables`), the tension-closure condition that makes
a pose holdable (:mod:`.tension`), the cable tensions holding the arm against gravity
(:mod:`.statics`), cable lengths as measurement data (:mod:`.cable_data`) and the
self-calibration of a module from redundant cable lengths (:mod:`.self_calibration`).

Called on concrete arrays, the array functions (lengths and forward kinematics, structure
matrices and closure tests, the feasible sampler, loads and tensions, self-calibration) each run
as one compiled program per shape and per value of their static arguments (iteration caps,
counts, flags), not operation by operation; inside ``jit``, ``vmap`` or ``grad`` they are traced
inline.
"""

from ._results import result_messages as result_messages
from ._results import result_names as result_names
from .cable_data import CableDataProblem as CableDataProblem
from .cable_data import arm_cable_lengths as arm_cable_lengths
from .cable_data import arm_states_from_cable_lengths as arm_states_from_cable_lengths
from .cable_data import cable_length_columns as cable_length_columns
from .cable_data import cable_length_table as cable_length_table
from .cable_data import check_cable_lengths as check_cable_lengths
from .cable_data import module_states_from_cable_lengths as module_states_from_cable_lengths
from .cable_data import simulate_cable_lengths as simulate_cable_lengths
from .cables import DEFAULT_RESIDUAL_TOL as DEFAULT_RESIDUAL_TOL
from .cables import CableFKResult as CableFKResult
from .cables import CableFKSolution as CableFKSolution
from .cables import cable_forward_kinematics as cable_forward_kinematics
from .cables import cable_length_names as cable_length_names
from .cables import cable_lengths as cable_lengths
from .cables import cable_vectors as cable_vectors
from .cables import length_jacobian as length_jacobian
from .cables import platform_points as platform_points
from .self_calibration import SelfCalibrationReport as SelfCalibrationReport
from .self_calibration import SelfCalibrationResult as SelfCalibrationResult
from .self_calibration import SelfCalibrationSolution as SelfCalibrationSolution
from .self_calibration import analyze_self_calibration as analyze_self_calibration
from .self_calibration import gauge_invariants as gauge_invariants
from .self_calibration import module_parameters as module_parameters
from .self_calibration import parameter_names as parameter_names
from .self_calibration import reduced_jacobian as reduced_jacobian
from .self_calibration import self_calibrate as self_calibrate
from .self_calibration import with_module as with_module
from .self_calibration import with_parameters as with_parameters
from .statics import TensionResult as TensionResult
from .statics import TensionSolution as TensionSolution
from .statics import distribute_tensions as distribute_tensions
from .statics import gravity_loads as gravity_loads
from .statics import gravity_torques as gravity_torques
from .statics import holding_tensions as holding_tensions
from .statics import total_mass as total_mass
from .tension import DEFAULT_MIN_MARGIN as DEFAULT_MIN_MARGIN
from .tension import arm_closure_margins as arm_closure_margins
from .tension import arm_tension_closure as arm_tension_closure
from .tension import closure_margin as closure_margin
from .tension import feasible_fraction as feasible_fraction
from .tension import has_tension_closure as has_tension_closure
from .tension import hull_margin as hull_margin
from .tension import lever_scale as lever_scale
from .tension import sample_feasible_states as sample_feasible_states
from .tension import structure_matrix as structure_matrix
from .tension import tension_closure as tension_closure
