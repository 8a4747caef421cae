"""The files of a whole-body solve: an arm URDF, its tip link and a mount (.npy), around a continuum model.

Used by ``python -m dacr_learn.ik --arm ARM.urdf --arm-tip LINK --mount M.npy`` (:mod:`dacr_learn.ik.cli`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .chain import load_arm
from .composite import Composite, check_mount


def load_mount(path: str | Path) -> torch.Tensor:
    """A mount file: float64 (4, 4) .npy, the tip link → robot base transform [m]. ValueError / FileNotFoundError
    naming --mount and what was wrong."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"--mount {path}: no such file; expected a float64 (4, 4) .npy transform")
    try:
        array = np.load(p, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise ValueError(f"--mount {path}: expected a .npy array (numpy.save), found a file numpy cannot read "
                         f"({err})") from err
    if array.dtype != np.float64:
        raise ValueError(f"--mount {path}: expected float64, got {array.dtype}")
    try:
        return check_mount(torch.from_numpy(array))
    except ValueError as err:
        raise ValueError(f"--mount {path}: {err}") from err


def composite_from_files(arm: str | Path, tip: str | None, mount: str | Path | None, robot) -> Composite:
    """The whole-body model of an arm URDF, its tip link and a mount file around ``robot`` (any continuum
    model :func:`~dacr_learn.ik.as_solver_model` accepts)."""
    missing = [flag for flag, v in (("--arm-tip", tip), ("--mount", mount)) if v is None]
    if missing:
        raise ValueError(f"--arm needs {' and '.join(missing)}: the arm's tip link and the mount (tip link → robot "
                         f"base, float64 (4, 4) .npy)")
    return Composite(load_arm(arm, tip), load_mount(mount), robot)


def describe(model: Composite) -> str:
    """One line naming the joint vector's layout, e.g. for the CLI's summary."""
    names = model.arm.joint_names
    return (f"q = ({names[0]} … {names[-1]}: {len(names)} arm joints [rad, m], then the robot's "
            f"{model.robot.num_joints} joints)")
