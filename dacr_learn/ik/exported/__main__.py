"""python -m dacr_learn.ik.exported: see :mod:`dacr_learn.cli.ik_exported`."""
import sys

from ...cli.ik_exported import main
from ...console import run_cli

sys.exit(run_cli(main))
