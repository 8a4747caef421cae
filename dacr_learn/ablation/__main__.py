"""``python -m dacr_learn.ablation``: the ablation runner's command line (:mod:`dacr_learn.cli.ablation`)."""
import sys

from ..cli.ablation import main
from ..console import run_cli

if __name__ == "__main__":
    sys.exit(run_cli(main))
