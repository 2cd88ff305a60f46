"""File contracts: model TOML, measurement CSV, result JSON (see ``shared/design.md``)."""

from .files import OutputExistsError as OutputExistsError
from .files import write_text_atomic as write_text_atomic
from .measurements import MeasurementFileError as MeasurementFileError
from .measurements import Measurements as Measurements
from .measurements import check_pose_count as check_pose_count
from .measurements import dumps_measurements as dumps_measurements
from .measurements import load_measurements as load_measurements
from .measurements import loads_measurements as loads_measurements
from .measurements import save_measurements as save_measurements
from .model import ModelFileError as ModelFileError
from .model import arm_from_dict as arm_from_dict
from .model import arm_to_dict as arm_to_dict
from .model import default_arm as default_arm
from .model import default_model_text as default_model_text
from .model import dumps_model as dumps_model
from .model import load_model as load_model
from .model import loads_model as loads_model
from .model import save_model as save_model
