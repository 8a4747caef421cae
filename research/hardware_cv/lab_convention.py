"""A saved hardware model's tip error on whole recordings, computed the way the lab computes its published figure.

The lab (ContinuumRoboticsLab/opencr-mujoco, ``paper_results/visualize_sysid.py`` and
``opencr_mujoco/sysid/README.md``, "Metric convention") reports one number per recording: the Euclidean tip RMSE
after removing the mean offset between the simulated and the recorded tip over the whole recording, in mm — for
its paper, its calibrated MuJoCo model (``configs/generation/ftdcr_v4_sysid_0326.json``, identified on an earlier
session) simulated over FTDCR v4's ``train.csv``. That is :func:`dacr_learn.hardware.metrics.offset_removed_rmse`
over every row of one file. The lab's ``evaluate_sysid_model.py`` also aligns by the first point instead (both
paths shifted to start at 0); that number is printed too (``first_point_mm``), as a second convention.

Prints one JSON line per recording (rows, ``rmse_mm``, ``first_point_mm``, the plain mean error). The model runs
over each file in its own time order (a history model's play state starts at the file's first row).
Numbers: docs/hardware.md, "Like for like with the lab". FTDCR v6's validation recording is a hidden hold-out:
this script refuses it.

Run from the repository root: python -m research.hardware_cv.lab_convention CKPT CSV [CSV ...]
e.g.   python -m research.hardware_cv.lab_convention runs/ftdcr_v4_model/model.pt \\
           data/ftdcr_v4/train.csv data/ftdcr_v4/tendon_pull.csv data/ftdcr_v4/val.csv
"""
import json
import sys
from pathlib import Path

import torch

from dacr_learn.hardware.deploy.checkpoint import load_hardware_model
from dacr_learn.hardware.metrics import offset_removed_rmse
from dacr_learn.hardware.recording import load_recording


def refuse_hidden(path: Path) -> None:
    """FTDCR v6's val / keypoints recordings are the project's hidden hold-out: never read here."""
    name = path.name.lower()
    if "v6" in str(path).lower() and ("val" in name or "keypoints" in name):
        raise ValueError(f"{path}: FTDCR v6's validation recording is a hidden hold-out; this script does not read it")


def evaluate(ckpt: str, csv: str) -> dict:
    path = Path(csv)
    refuse_hidden(path)
    model = load_hardware_model(ckpt)
    rec = load_recording(path, model.spec)
    index = [rec.servo_ids.index(s) for s in model.servo_ids]
    tip, _ = model.predict(1e3 * rec.servo[:, index])
    first = (tip - tip[0]) - (rec.tip - rec.tip[0])
    return {"file": str(path), "model": model.name, "rows": len(rec),
            "rmse_mm": round(float(offset_removed_rmse(tip, rec.tip)) * 1e3, 3),
            "first_point_mm": round(float(first.norm(dim=-1).pow(2).mean().sqrt()) * 1e3, 3),
            "mean_mm": round(float((tip - rec.tip).norm(dim=-1).mean()) * 1e3, 3)}


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2:
        sys.exit("usage: python -m research.hardware_cv.lab_convention CKPT CSV [CSV ...]")
    torch.set_num_threads(1)
    for csv in args[1:]:
        print(json.dumps(evaluate(args[0], csv)))


if __name__ == "__main__":
    main()
