"""``python -m dacr_learn.hardware``: the model-selection study's command line (:mod:`dacr_learn.cli.hardware`)."""
import sys

from ..cli.hardware import main
from ..console import run_cli

if __name__ == "__main__":
    sys.exit(run_cli(main))
