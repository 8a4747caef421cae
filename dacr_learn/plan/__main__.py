"""python -m dacr_learn.plan: see :mod:`dacr_learn.cli.plan`."""
import sys

from ..cli.plan import package_main
from ..console import run_cli

sys.exit(run_cli(package_main))
