"""Why does a calibrated model still disagree with the recordings? Detect, locate, attribute.

``diagnose(arm, measurements, noise)`` tests whether the geometric calibration is consistent
with the measuring device, tries every candidate effect of :mod:`cdra_jax.physics`, and
reports the one the data support (or ``none``, or ``unattributed`` with a location), with its
physical parameters and the held-out improvement. See :mod:`.core` for the method.
"""

from .core import diagnose as diagnose
from .core import diagnose_files as diagnose_files
from .result import CandidateRow as CandidateRow
from .result import Diagnosis as Diagnosis
from .result import HeldOutErrors as HeldOutErrors
from .result import ParameterEstimate as ParameterEstimate
