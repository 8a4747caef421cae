"""``python -m dacr_learn.hardware.calibrate --pulls CSV --robot NOMINAL.yaml --out CALIBRATED.yaml``

Calibrates a robot from single-tendon pulls (method: :mod:`dacr_learn.hardware.calibration`)
and writes the calibrated robot YAML plus its servo map (``servo_maps/<out file name>``). The
servo map's ``calibration`` block records the fit quality, including the tip error of the
calibrated CC model fitted to the pull rows.
"""
from __future__ import annotations

import argparse
import sys

import torch

from ..console import run_cli
from ..robot import RobotSpec
from .calibration import calibrate, default_map_path, write_calibration
from .ccmodel import CalibratedCC, fit_cc
from .metrics import tip_metrics
from .recording import Recording, load_recording
from .servo_map import ServoMap


def pull_fit_quality(spec: RobotSpec, smap: ServoMap, rec: Recording) -> dict:
    """Fit the calibrated CC model (:mod:`.ccmodel`) to all pull rows; tip errors in mm."""
    cc = CalibratedCC(spec)
    x = smap.displacements(spec, rec)
    fit_cc(cc, x, rec.tip, max_iter=60)
    with torch.no_grad():
        m = tip_metrics(cc(x), rec.tip)
    return {"rows": len(rec), **{k: round(v, 3) for k, v in m.items()}, "parameters": cc.report()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m dacr_learn.hardware.calibrate", description=__doc__.split("\n")[0])
    ap.add_argument("--pulls", required=True, help="single-tendon pull recording (CSV)")
    ap.add_argument("--robot", required=True, help="nominal robot YAML")
    ap.add_argument("--out", required=True, help="calibrated robot YAML to write")
    ap.add_argument("--servo-map", help="servo map YAML to write (default: servo_maps/<out name> next to --out)")
    ap.add_argument("--units", default="mm")
    args = ap.parse_args(argv)
    spec = RobotSpec.from_yaml(args.robot)
    rec = load_recording(args.pulls, spec, args.units)
    cal_spec, smap, report = calibrate(rec, spec)
    report["cc_fit_on_pulls"] = pull_fit_quality(cal_spec, smap, rec)
    map_path = args.servo_map or default_map_path(args.out)
    write_calibration(cal_spec, smap, args.out, map_path)
    for j, seg in enumerate(report["segments"]):
        ids = [f"{a.servo}(j{a.joint})" for a in smap.servos if a.segment == j]
        print(f"segment {j}: servos {' '.join(ids)}  offset {seg['offset_deg']:.1f} deg  "
              f"angle rms {seg['angle_rms_deg']:.1f} deg  gain {seg['mean_gain_mm_per_mm']:.1f}")
    q = report["cc_fit_on_pulls"]
    print(f"CC model fitted to the {q['rows']} pull rows: tip RMSE {q['rmse_mm']:.2f} mm (offset removed), "
          f"mean {q['mean_mm']:.2f} mm")
    print(f"wrote {args.out} and {map_path}")


if __name__ == "__main__":
    sys.exit(run_cli(main))
