"""python -m dacr_learn.arm.exported: see :mod:`dacr_learn.cli.arm_exported`."""
import sys

from ...cli.arm_exported import main
from ...console import run_cli

sys.exit(run_cli(main))
