"""python -m dacr_learn.ik: see :mod:`dacr_learn.ik.cli`."""
import sys

from ..console import run_cli
from .cli import package_main

sys.exit(run_cli(package_main))
