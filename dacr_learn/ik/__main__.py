"""python -m dacr_learn.ik: see :mod:`dacr_learn.cli.ik`."""
import sys

from ..cli.ik import main
from ..console import run_cli

sys.exit(run_cli(main))
