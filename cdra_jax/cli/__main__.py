"""``python -m cdra_jax.cli ...``: the same as ``cdra-jax ...``."""

import sys

from .commands import main

sys.exit(main())
