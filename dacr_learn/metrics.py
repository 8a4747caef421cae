"""Pose error metrics (pure torch, no Lightning): per-sample errors and their summaries."""
from __future__ import annotations

import torch
from torch import Tensor


def rotation_geodesic(r1: Tensor, r2: Tensor) -> Tensor:
    """Geodesic angle between rotations (..., 3, 3) → (...) [rad].

    θ = 2·atan2(‖R₁ − R₂‖_F, ‖R₁ + R₂‖_F): exact for rotation matrices and, unlike acos of the
    trace, accurate for tiny angles (no floor near 0, which matters for 0.01° errors in float32).
    """
    return 2 * torch.atan2(torch.linalg.matrix_norm(r1 - r2), torch.linalg.matrix_norm(r1 + r2))


def pose_errors(pred: Tensor, target: Tensor) -> dict[str, Tensor]:
    """Per-sample tip errors of poses (..., 4, 4): {"pos_err": [m], "rot_err": [rad]}."""
    return {"pos_err": torch.linalg.vector_norm(pred[..., :3, 3] - target[..., :3, 3], dim=-1),
            "rot_err": rotation_geodesic(pred[..., :3, :3], target[..., :3, :3])}


def summarize(errors: dict[str, Tensor], total_length: float) -> dict[str, float]:
    """Summary numbers of per-sample errors (1-D tensors) in display units.

    pos_err [m] → pos_err_{mean,p95,max}_mm and pos_err_mean_pct (% of total robot length);
    rot_err [rad] → rot_err_{mean,p95,max}_deg; body_err [m] (per sample the largest error of a body point) →
    body_err_{mean,p95,max}_mm and body_err_mean_pct; joint_err [m] → joint_err_{mean,max}_mm;
    constraint_residual [m] → constraint_residual_{mean,max}_m; out_of_limits (1 where a prediction
    leaves the joint limits, else 0) → out_of_limits_pct; nll (a sampler's negative log-likelihood) → nll_mean.
    """
    out: dict[str, float] = {}
    e = {k: v.detach().double().flatten() for k, v in errors.items()}
    for key, unit, scaled in (("pos_err", "mm", 1e3), ("rot_err", "deg", None), ("body_err", "mm", 1e3)):
        if key in e:
            x = e[key] * scaled if scaled else torch.rad2deg(e[key])
            out.update({f"{key}_mean_{unit}": x.mean().item(), f"{key}_p95_{unit}": torch.quantile(x, 0.95).item(),
                        f"{key}_max_{unit}": x.max().item()})
            if unit == "mm":
                out[f"{key}_mean_pct"] = (e[key].mean() / total_length * 100).item()
    if "joint_err" in e:
        out.update(joint_err_mean_mm=e["joint_err"].mean().item() * 1e3,
                   joint_err_max_mm=e["joint_err"].max().item() * 1e3)
    if "constraint_residual" in e:
        out.update(constraint_residual_mean_m=e["constraint_residual"].mean().item(),
                   constraint_residual_max_m=e["constraint_residual"].max().item())
    if "out_of_limits" in e:
        out.update(out_of_limits_pct=e["out_of_limits"].mean().item() * 100)
    if "nll" in e:
        out.update(nll_mean=e["nll"].mean().item())
    return out


def format_table(summary: dict[str, float], title: str = "") -> str:
    """A small two-column text table of a summary dict."""
    width = max(len(k) for k in summary) if summary else 0
    lines = [title] if title else []
    lines += [f"  {k:<{width}}  {v:>12.6g}" for k, v in summary.items()]
    return "\n".join(lines)
