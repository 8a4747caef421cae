"""``python -m dacr_learn.hardware``: the model-selection study's command line (:mod:`.study.cli`)."""
import sys

from ..console import run_cli
from .study.cli import main

if __name__ == "__main__":
    sys.exit(run_cli(main))
