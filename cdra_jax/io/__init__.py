"""File contracts: model TOML, measurement CSV, result JSON (see ``shared/design.md``)."""

from .model import ModelFileError as ModelFileError
from .model import arm_from_dict as arm_from_dict
from .model import arm_to_dict as arm_to_dict
from .model import default_arm as default_arm
from .model import default_model_text as default_model_text
from .model import dumps_model as dumps_model
from .model import load_model as load_model
from .model import loads_model as loads_model
from .model import save_model as save_model
