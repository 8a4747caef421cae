"""Displacement-actuated datasets from the Cosserat-rod model (docs/cosserat.md §6, "Datasets": the sampling and the
tensors, stored under the names of the CC datasets of :mod:`.cc`, so the datamodule serves both).

Per segment ``tendons_pulled`` neighbouring tendons get tensions uniform in [0, ``tension_max``] N (the others
slack), optionally a random tip force; :func:`~dacr_learn.cosserat.solve_statics` gives the shape. The joint vector
is the unstretched tendon lengths (``tendon_rest_lengths``), what a displacement actuator sets. Deterministic for a
seed (tensions drawn up front by a private generator, then solved in chunks).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..cosserat.statics import ConvergenceError, solve_statics
from ..cosserat.tendon import tendon_routing
from ..kinematics import forward_kinematics
from ..layers import ClarkeEncoder
from ..metrics import pose_errors, summarize
from ..robot import RobotSpec
from .store import generate_or_load as _generate_or_load_any

PROGRESS_CHUNK = 1024   # samples per solve call, i.e. per progress-bar update


class DatasetConvergenceError(ConvergenceError, ValueError):
    """Samples of a dataset failed to solve: a ConvergenceError caused by the options, so also a ValueError
    (train.py shows it as one ``error:`` line naming the options to change, not as a traceback)."""


@dataclass(frozen=True)
class CosseratOptions:
    """Sampling and solver options of a Cosserat dataset (``data.cosserat``; docs/cosserat.md §6): tension_max [N];
    tendons_pulled (per segment); gravity (3,) [m/s²], base frame; tip_force_max [N] (0: none); steps_per_segment
    (RK4); tol, max_iter: Newton's (solve_statics)."""

    source: ClassVar[str] = "cosserat"
    tension_max: float = 2.0
    tendons_pulled: int = 2
    gravity: tuple[float, float, float] = field(default=(-9.81, 0.0, 0.0))
    tip_force_max: float = 0.0
    steps_per_segment: int = 8
    tol: float = 1e-10
    max_iter: int = 40

    def __post_init__(self):
        g = self.gravity
        if not (isinstance(g, (list, tuple)) and len(g) == 3
                and all(isinstance(x, (int, float)) and math.isfinite(x) for x in g)):
            raise ValueError(f"gravity: expected 3 finite numbers [m/s²] in the base frame, got {g!r}")
        object.__setattr__(self, "gravity", tuple(float(x) for x in g))
        for name in ("tension_max", "tip_force_max", "tol"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        for name in ("tendons_pulled", "steps_per_segment", "max_iter"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"{name}: expected an integer >= 1, got {v!r}")

    @classmethod
    def from_dict(cls, d: dict | None) -> CosseratOptions:
        """Options from a config mapping; unknown keys are a ValueError naming them and the known ones."""
        d = dict(d or {})
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"data.cosserat: unknown option(s) {unknown}, expected some of {sorted(known)}")
        return cls(**d)


def sample_tensions(spec: RobotSpec, n: int, options: CosseratOptions, generator: torch.Generator) -> Tensor:
    """(n, T) [N] float64: per segment ``tendons_pulled`` neighbouring tendons uniform in [0, tension_max]."""
    out = []
    for j, seg in enumerate(spec.segments):
        k = seg.num_joints
        if options.tendons_pulled > k:
            raise ValueError(f"tendons_pulled: got {options.tendons_pulled}, expected at most {k} (the tendons "
                             f"of segment {j})")
        first = torch.randint(k, (n, 1), generator=generator)
        cols = (first + torch.arange(options.tendons_pulled)) % k
        tau = torch.zeros(n, k, dtype=torch.float64)
        values = options.tension_max * torch.rand(n, options.tendons_pulled, generator=generator, dtype=torch.float64)
        out.append(tau.scatter(1, cols, values))
    return torch.cat(out, dim=-1)


def _tip_forces(n: int, force_max: float, generator: torch.Generator) -> Tensor:
    """(n, 3) [N]: uniform random directions, magnitudes uniform in [0, force_max]."""
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, dtype=torch.float64), dim=-1)
    return direction * force_max * torch.rand(n, 1, generator=generator, dtype=torch.float64)


def generate(spec: RobotSpec, n: int, seed: int, options: CosseratOptions = CosseratOptions(),
             dtype=torch.float32, *, progress: bool = True, chunk: int = PROGRESS_CHUNK) -> dict[str, Tensor]:
    """n samples (tensors of the module docstring), solved ``chunk`` at a time with a progress bar. Raises
    DatasetConvergenceError (after trying every sample) naming the failures, the worst residual and the options to
    change; ValueError without a ``mechanics:`` block."""
    if spec.mechanics is None:
        raise ValueError(f"robot {spec.name!r}: data source 'cosserat' needs a mechanics: block in the robot "
                         "description (docs/cosserat.md §1)")
    if n < 1:
        raise ValueError(f"n: expected a positive number of samples, got {n}")
    g = torch.Generator().manual_seed(int(seed))
    tension = sample_tensions(spec, n, options, g)
    force = _tip_forces(n, options.tip_force_max, g) if options.tip_force_max > 0 else None
    gravity = torch.tensor(options.gravity, dtype=torch.float64)
    ends = tendon_routing(spec).ends[1:].tolist()             # the segments' distal ends [m]
    parts = []
    with tqdm(total=n, desc=f"Cosserat dataset ({spec.name})", unit="sample", disable=not progress,
              dynamic_ncols=True) as bar:
        for i in range(0, n, chunk):
            wrench = None if force is None else torch.nn.functional.pad(force[i:i + chunk], (0, 3))   # (F, M = 0)
            sol = solve_statics(spec, tension[i:i + chunk], gravity=gravity, tip_wrench=wrench,
                                steps_per_segment=options.steps_per_segment, tol=options.tol,
                                max_iter=options.max_iter, on_failure="flag")
            parts.append({"q": sol.tendon_rest_lengths, "pose": sol.tip, "segment_frames": sol.at(ends),
                          "backbone": sol.frames[..., :3, 3], "residual": sol.residual, "ok": sol.converged})
            bar.update(min(chunk, n - i))
    data = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    finite = [v.flatten(1).isfinite().all(-1) for k, v in data.items() if k not in ("ok", "residual")]
    ok = data.pop("ok") & torch.stack(finite).all(0)
    if not bool(ok.all()):
        worst = torch.nan_to_num(data["residual"][~ok], nan=math.inf).max()
        raise DatasetConvergenceError(
            f"Cosserat dataset: {int((~ok).sum())} of {n} samples failed (worst shooting residual {float(worst):.3g}, "
            f"tol {options.tol:g}; inf = NaN; a converged but inadmissible shape also counts); nothing was written. "
            "Lower data.cosserat.tension_max or tip_force_max, or raise data.cosserat.max_iter or steps_per_segment")
    out = {k: v.to(dtype) for k, v in data.items()}
    out["q_clean"], out["pose_clean"], out["tension"] = out["q"].clone(), out["pose"].clone(), tension.to(dtype)
    out["features"] = ClarkeEncoder(spec)(data["q"]).to(dtype)
    if force is not None:
        out["tip_force"] = force.to(dtype)
    return out


def generate_or_load(directory: str | Path, spec: RobotSpec, n: int, seed: int,
                     options: CosseratOptions = CosseratOptions(), *, progress: bool = True) -> dict[str, Tensor]:
    """Load ``directory`` if it holds exactly this Cosserat dataset (spec, n, seed, source, options), else
    generate and save it (as :func:`.store.generate_or_load`; a failed generation writes nothing)."""
    return _generate_or_load_any(directory, spec, n, seed, options,
                                 make=lambda s, k, sd, o: generate(s, k, sd, o, progress=progress))


def cc_baseline(spec: RobotSpec, q: Tensor, pose: Tensor) -> dict[str, float]:
    """Summary of the analytic CC model's errors on samples (q (N, T), pose (N, 4, 4)), prefixed "cc_":
    CC evaluated on the Clarke features of the same joint lengths (float64), e.g. cc_pos_err_mean_pct."""
    q64 = q.detach().to(torch.float64)
    predicted = forward_kinematics(spec, ClarkeEncoder(spec)(q64))
    summary = summarize(pose_errors(predicted, pose.detach().to(torch.float64)), spec.total_length)
    return {f"cc_{k}": v for k, v in summary.items()}
