"""Figures and Rerun recordings of predicted vs measured tip paths on a validation recording."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .benchmark import Setup
from .metrics import offset_removed_errors

COLORS = {"measured": (20, 20, 20), "cc": (31, 119, 180)}
PALETTE = [(214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def _color(name: str, k: int) -> tuple[int, int, int]:
    return COLORS.get(name, PALETTE[k % len(PALETTE)])


def label_runs(labels: tuple[str, ...]) -> list[slice]:
    """Consecutive rows with the same label (ignoring a trailing '_hold'), as slices."""
    base = [lab.removesuffix("_hold") for lab in labels]
    runs, start = [], 0
    for i in range(1, len(base) + 1):
        if i == len(base) or base[i] != base[start]:
            runs.append(slice(start, i))
            start = i
    return runs


def centered_errors_mm(pred: torch.Tensor, meas: torch.Tensor) -> np.ndarray:
    """‖e_k − ē‖ per row [mm] (the terms of the offset-removed RMSE)."""
    return (offset_removed_errors(pred.double(), meas.double()) * 1e3).numpy()


def plot_paths(setup: Setup, preds: dict[str, torch.Tensor], path: Path) -> None:
    """PNG: top (x–y) and side (x–z) views of the val tip paths, and the error per sample."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meas = setup.val.tip.numpy() * 1e3
    runs = label_runs(setup.val_rec.labels)
    fig, axes = plt.subplots(1, 3, figsize=(18, 6), gridspec_kw={"width_ratios": [1, 1, 1.3]})
    series = {"measured": meas} | {k: v.numpy() * 1e3 for k, v in preds.items()}
    for k, (name, pts) in enumerate(series.items()):
        color = np.array(_color(name, k)) / 255
        for r_i, r in enumerate(runs):
            kw = dict(color=color, lw=1.6 if name == "measured" else 1.0, alpha=0.9,
                      label=name if r_i == 0 else None, ls="-" if name == "measured" else "--")
            axes[0].plot(pts[r, 0], pts[r, 1], **kw)
            axes[1].plot(pts[r, 0], pts[r, 2], **kw)
    for ax, (a, b) in zip(axes[:2], [("x", "y"), ("x", "z")], strict=True):
        ax.set_xlabel(f"{a} [mm]"), ax.set_ylabel(f"{b} [mm]"), ax.set_aspect("equal"), ax.grid(alpha=0.3)
    axes[0].set_title("top view"), axes[1].set_title("side view"), axes[0].legend(loc="best", fontsize=8)
    for k, (name, pred) in enumerate(preds.items(), start=1):
        err = centered_errors_mm(pred, setup.val.tip)
        rmse = float(np.sqrt((err**2).mean()))
        axes[2].plot(err, color=np.array(_color(name, k)) / 255, lw=1, label=f"{name} (RMSE {rmse:.2f} mm)")
    for r in runs:
        axes[2].axvline(r.start, color="0.85", lw=0.5)
    axes[2].set_xlabel("val sample (grey lines: pattern starts)"), axes[2].set_ylabel("offset-removed error [mm]")
    axes[2].legend(fontsize=8), axes[2].grid(alpha=0.3)
    fig.suptitle(f"{setup.spec.name}: predicted vs measured tip paths on {Path(setup.val_rec.source).name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _log_static_paths(rr, setup: Setup, preds: dict[str, torch.Tensor]) -> None:
    runs = label_runs(setup.val_rec.labels)
    series = {"measured": setup.val.tip} | preds
    for k, (name, pts) in enumerate(series.items()):
        strips = [pts[r].numpy() for r in runs]
        rr.log(f"world/paths/{name}", rr.LineStrips3D(strips, colors=[_color(name, k)], radii=0.0004), static=True)


def log_rerun(setup: Setup, preds: dict[str, torch.Tensor], path: Path) -> None:
    """Rerun .rrd: static val paths; per sample (timeline "sample") the measured and predicted
    tips, the CC model's backbone, and each model's offset-removed error [mm]."""
    import rerun as rr

    rr.init("dacr_learn_hardware", spawn=False)
    rr.save(str(path))
    rr.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_static_paths(rr, setup, preds)
    with torch.no_grad():
        backbone = setup.cc.backbone(setup.val.x).numpy()
    errors = {name: centered_errors_mm(p, setup.val.tip) for name, p in preds.items()}
    meas = setup.val.tip.numpy()
    for i in range(len(meas)):
        rr.set_time("sample", sequence=i)
        rr.log("world/tip/measured", rr.Points3D(meas[i:i + 1], colors=[COLORS["measured"]], radii=0.002,
                                                 labels=[setup.val_rec.labels[i]]))
        for k, (name, pred) in enumerate(preds.items(), start=1):
            rr.log(f"world/tip/{name}", rr.Points3D(pred[i:i + 1].numpy(), colors=[_color(name, k)], radii=0.0015))
            rr.log(f"errors/{name}", rr.Scalars(float(errors[name][i])))
        rr.log("world/robot/cc_backbone", rr.LineStrips3D([backbone[i]], colors=[COLORS["cc"]], radii=0.001))
    rr.disconnect()
