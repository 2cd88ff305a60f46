"""The ``cdra-jax`` command line: a thin argparse layer over :mod:`cdra_jax.workflows`, one
module per subcommand (:mod:`.commands` wires them)."""

from .commands import SUBCOMMANDS as SUBCOMMANDS
from .commands import build_parser as build_parser
from .commands import main as main
from .common import EXIT_ERROR as EXIT_ERROR
from .common import EXIT_INTERRUPTED as EXIT_INTERRUPTED
from .common import EXIT_NOT_CONVERGED as EXIT_NOT_CONVERGED
from .common import EXIT_OK as EXIT_OK
from .common import EXIT_TERMINATED as EXIT_TERMINATED
from .common import EXIT_UNTRUSTED as EXIT_UNTRUSTED
from .common import EXIT_USAGE as EXIT_USAGE
