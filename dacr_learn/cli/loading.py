"""What the command lines read and write: .npy arrays, a model (--robot / --ckpt, recognised by the file's contents),
the files of a whole-body solve (an arm URDF, its tip link and a mount .npy around a continuum model) and the .npz
results (written atomically).

Every error is a ValueError / FileNotFoundError naming the flag and what was expected. The arm, hardware and
checkpoint modules are imported where they are needed: ``--robot`` alone starts without them.
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ..checks import F64, prefix_errors
from ..robot import RobotSpec

Seeder = Callable[[torch.Tensor, int], "torch.Tensor | None"]


def load_array(path: str | Path, flag: str, expected: str = "a .npy array") -> np.ndarray:
    """The .npy array a flag names (no pickles). FileNotFoundError / ValueError naming the flag."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{flag} {path}: no such file; expected {expected}")
    try:
        return np.load(p, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise ValueError(f"{flag} {path}: expected a .npy array (numpy.save), found a file numpy cannot read "
                         f"({err})") from err


def out_path(path: str) -> Path:
    """``--out PATH`` as a Path, checked before any work is done: ValueError if it is a folder or its parent a file."""
    out = Path(path)
    if out.is_dir():
        raise ValueError(f"--out {path}: is a folder; expected the path of the .npz file to write")
    if out.parent.exists() and not out.parent.is_dir():
        raise ValueError(f"--out {path}: its parent {out.parent} is a file, not a folder")
    return out


def save_npz(out: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write atomically: a temporary file beside ``out``, then renamed (an interrupted run leaves no half file)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)                 # mkstemp makes it private; a result file is a normal one
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_solver_model(robot: str | None, ckpt: str | None) -> tuple[object, Seeder | None, str]:
    """(model_or_spec, seed function or None, description) for --robot / --ckpt. A --ckpt file is recognised by
    its contents (:func:`~dacr_learn.hardware.deploy.checkpoint.read_model_file`), whatever it is called: a saved
    hardware model, else a ``train.py`` run or checkpoint (FK: the network is inverted; IK or learned sampler:
    the analytic CC model of its robot, seeded by the network)."""
    if robot is not None:
        spec = RobotSpec.from_yaml(robot)
        return spec, None, f"analytic constant-curvature model of {robot}"
    from ..hardware.deploy.checkpoint import hardware_model_from_blob, read_model_file
    from ..runs import load_model
    file = read_model_file(ckpt)
    if file.hardware:
        return hardware_model_from_blob(file.blob, file.path), None, f"hardware model {ckpt} (servo commands [mm])"
    net = load_model(file.path, dtype=F64, blob=file.blob)
    if net.task == "fk":
        return net, None, f"learned FK {ckpt} (accuracy with respect to the network)"
    if net.task == "sampler":     # seeds need no float64 (the solver refines them in float64): float32 samples faster
        seeds = network_seeds(net.float())
        return net.spec, seeds, f"analytic CC model of {ckpt}'s robot, seeded by its learned sampler"
    return net.spec, network_seeds(net), f"analytic CC model of {ckpt}'s robot, seeded by its IK network"


def network_seeds(net) -> Seeder:
    """Seeds (B, S, D) from a trained IK network (its prediction for each pose target) or a learned sampler."""
    from ..clarke_space import ClarkeSpace
    space = ClarkeSpace(net.spec)

    def seeds(target: torch.Tensor, count: int) -> torch.Tensor | None:
        if hasattr(net, "sample_features"):                       # a learned multi-solution sampler
            return net.sample_features(target, count)
        if target.dim() != 3:
            return None                                           # an IK network needs whole poses
        with torch.no_grad():
            return space.features(net(target).to(F64)).unsqueeze(1)
    return seeds


def load_mount(path: str | Path) -> torch.Tensor:
    """A mount file: float64 (4, 4) .npy, the tip link → robot base transform [m]. ValueError / FileNotFoundError
    naming --mount and what was wrong."""
    array = load_array(path, "--mount", "a float64 (4, 4) .npy transform")
    if array.dtype != np.float64:
        raise ValueError(f"--mount {path}: expected float64, got {array.dtype}")
    from ..arm import check_mount
    return prefix_errors(f"--mount {path}", check_mount, torch.from_numpy(array))


def composite_from_files(arm: str | Path, tip: str | None, mount: str | Path | None, robot):
    """The whole-body model of an arm URDF, its tip link and a mount file around ``robot`` (any continuum
    model :func:`~dacr_learn.ik.as_solver_model` accepts): a :class:`~dacr_learn.arm.Composite`."""
    from ..arm import Composite, load_arm
    missing = [flag for flag, v in (("--arm-tip", tip), ("--mount", mount)) if v is None]
    if missing:
        raise ValueError(f"--arm needs {' and '.join(missing)}: the arm's tip link and the mount (tip link → robot "
                         f"base, float64 (4, 4) .npy)")
    return Composite(load_arm(arm, tip), load_mount(mount), robot)


def describe(model) -> str:
    """One line naming the joint vector's layout of a :class:`~dacr_learn.arm.Composite`, for the CLI's summary."""
    names = model.arm.joint_names
    return (f"q = ({names[0]} … {names[-1]}: {len(names)} arm joints [rad, m], then the robot's "
            f"{model.robot.num_joints} joints)")
