import sys

from ..console import run_cli
from .cli import main

if __name__ == "__main__":
    sys.exit(run_cli(main))
