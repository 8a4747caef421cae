"""Lines of Python in dacr_learn/ that carry the functionality of a base commit, against that commit.

Counted today: every file that existed at the base and still exists, plus the files its code moved into since
(``--moved``: the CLIs in dacr_learn/cli/ except plan.py, dacr_learn/export/, dacr_learn/ik/adapters.py,
dacr_learn/ik/exported/, dacr_learn/ik/seeds.py, dacr_learn/limits.py (was ik/limits.py)). Files of capabilities
added since (body, scenes, planner, QP control, …) are not counted.

    python tools/line_accounting.py            # base 3a013fc, target -5 %
    python tools/line_accounting.py --base REV --target 0.05
"""
from __future__ import annotations

import argparse
import os
import subprocess
from pathlib import Path

MOVED = ("dacr_learn/cli/", "dacr_learn/export/", "dacr_learn/ik/adapters.py", "dacr_learn/ik/exported/",
         "dacr_learn/ik/seeds.py", "dacr_learn/limits.py")
NOT_MOVED = ("dacr_learn/cli/plan.py",)


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], check=True, capture_output=True, text=True).stdout


def _lines(text: str) -> int:
    return text.count("\n") + (1 if text and not text.endswith("\n") else 0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="3a013fc")
    parser.add_argument("--target", type=float, default=0.05, help="the reduction asked for (0.05 = 5 %%)")
    args = parser.parse_args()
    os.chdir(Path(__file__).resolve().parents[1])                 # the checkout this script is in
    base_files = [f for f in _git("ls-tree", "-r", "--name-only", args.base, "dacr_learn").split() if f.endswith(".py")]
    base = sum(_lines(_git("show", f"{args.base}:{f}")) for f in base_files)
    now_files = sorted(str(p) for p in Path("dacr_learn").rglob("*.py"))
    kept = [f for f in now_files if f in set(base_files)]
    moved = [f for f in now_files if f.startswith(MOVED) and f not in NOT_MOVED and f not in set(base_files)]
    n_kept = sum(_lines(Path(f).read_text()) for f in kept)
    n_moved = sum(_lines(Path(f).read_text()) for f in moved)
    total = sum(_lines(Path(f).read_text()) for f in now_files)
    now = n_kept + n_moved
    print(f"base {args.base}: {base} lines in {len(base_files)} files")
    print(f"today, files of the base still there: {n_kept} ({len(kept)} files)")
    print(f"today, files its code moved into:     {n_moved} ({len(moved)} files)")
    print(f"today, that functionality:            {now} ({(now - base) / base:+.2%} against the base)")
    limit = int(base * (1 - args.target))
    print(f"target -{args.target:.0%}: <= {limit} lines ({now - limit} to go)")
    print(f"all of dacr_learn/ today:             {total}")


if __name__ == "__main__":
    main()
