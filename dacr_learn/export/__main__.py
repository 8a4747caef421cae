"""python -m dacr_learn.export: see :mod:`dacr_learn.cli.export`."""
import sys

from ..cli.export import main
from ..console import run_cli

sys.exit(run_cli(main))       # a bad --ckpt or --out: its one-line message, not a traceback
