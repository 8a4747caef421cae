"""Shared pieces of the hardware deploy tests (not collected: no ``test_`` prefix).

A small synthetic 2-segment robot (the same kind as tests/test_hardware.py's second robot): a
CalibratedCC with non-trivial physical parameters and an ensemble of untrained residual networks
(with enlarged output weights, so that the correction matters). Used by test_hardware_deploy,
test_hardware_control, test_hardware_marker and test_hardware_uncertainty.

:func:`write_labelled_robot`: a labelled synthetic recording folder (single-segment and pair patterns,
no val.csv, like data/ftdcr_v6) for the selection-proxy and CLI tests (fixture ``labelled_robot_dir``
in tests/conftest.py).
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import torch

from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.deploy.checkpoint import HardwareModel
from dacr_learn.hardware.deploy.uncertainty import SigmaCalibration, SupportModel, ensemble_predict
from dacr_learn.hardware.learned import CCClarkeResidual, CCClarkeResidualHistory, make_split
from dacr_learn.hardware.recording import Recording
from dacr_learn.hardware.servo_map import ServoAssignment, ServoMap
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec

IDS = ("B7", "A2", "C1", "A9", "B3", "C5", "A4", "B1")
COLS = (3, 6, 0, 5, 1, 7, 2, 4)                     # joint driven by each column
TIP_SCALE = 0.15                                    # [m] magnitude of tip coordinates


def synthetic_spec() -> RobotSpec:
    return RobotSpec.from_dict({"name": "synthetic-2seg", "routing": "coupled", "segments": [
        {"type": "0", "length": 0.08, "radius": 0.005, "joints": 4, "offset": 0.4, "limits": {"bend": 0.8}},
        {"type": "0", "length": 0.07, "radius": 0.005, "joints": 4, "offset": -1.1, "limits": {"bend": 0.8}}]})


def command_recording(n: int, seed: int, amplitude: float = 3e-3) -> Recording:
    """A smooth random command sequence (servo values in column order) [m]; tips are not used."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, n, dtype=torch.float64)[:, None]
    phase = 6.3 * torch.rand(1, 8, generator=g, dtype=torch.float64)
    servo = amplitude * torch.sin(2 * torch.pi * (1 + torch.arange(8)) * t / 3 + phase)
    return Recording(IDS, servo, torch.zeros(n, 3, dtype=torch.float64), ("p",) * n,
                     torch.arange(n, dtype=torch.float64), "synthetic")


def synthetic_model(history: bool, members: int = 3) -> HardwareModel:
    spec = synthetic_spec()
    smap = ServoMap(spec.name, tuple(ServoAssignment(i, c // 4, c % 4, (-1) ** c, 1e-4 * c)
                                     for i, c in zip(IDS, COLS, strict=True)), -8e-3)
    cc = CalibratedCC(spec, compliance=1e-6)
    with torch.no_grad():
        cc.encoder.log_radius_scale.copy_(torch.tensor([0.05, -0.03]))
        cc.encoder.rotation.copy_(torch.tensor([0.02, -0.04]))
        cc.encoder.pretension.fill_(2e-4)
        cc.base_tilt.copy_(torch.tensor([0.03, -0.02]))
        cc.base_translation.copy_(torch.tensor([0.01, -0.02, 0.005]))
        cc.tip_offset.fill_(0.012)
    cc.requires_grad_(False)
    train = make_split(command_recording(200, 0), spec, smap, cc)
    cls = CCClarkeResidualHistory if history else CCClarkeResidual
    nets = []
    for seed in range(members):
        torch.manual_seed(seed)
        member = cls(train, cc)
        with torch.no_grad():
            member.net[-1].weight.mul_(20.0)
        nets.append(member.eval())
    support = SupportModel(train.features[..., :2], ["p"] * 100 + ["q"] * 100)
    return HardwareModel("cc_clarke_residual_history" if history else "cc_clarke_residual", spec, smap, IDS, cc,
                         nets, sigma=SigmaCalibration(1.5, 2e-4), support=support,
                         examples=1e3 * command_recording(64, 3).servo)


def batch_prediction(model: HardwareModel, rec: Recording) -> torch.Tensor:
    split = make_split(rec, model.spec, model.smap, model.cc)
    return ensemble_predict(model.members, split)[0]


LABELLED_ROBOT = {"name": "synthetic-2seg", "routing": "coupled", "segments": [
    {"type": "0", "length": 0.08, "radius": 0.005, "joints": 3, "offset": 0.3, "limits": {"bend": 0.8}},
    {"type": "0", "length": 0.07, "radius": 0.005, "joints": 3, "offset": -0.5, "limits": {"bend": 0.8}}]}
LABELLED_IDS = ("s4", "s1", "s6", "s2", "s5", "s3")


def _bent_features(g: torch.Generator, n: int, moving: tuple[int, ...], reach: float) -> torch.Tensor:
    """(n, 2, 4) features with only the segments in ``moving`` bent (|ρ| ≤ reach [m])."""
    feat = torch.zeros(n, 2, 4, dtype=torch.float64)
    for k in moving:
        r = reach * torch.rand(n, generator=g, dtype=torch.float64).sqrt()
        a = 2 * math.pi * torch.rand(n, generator=g, dtype=torch.float64)
        feat[:, k, 0], feat[:, k, 1] = r * a.cos(), r * a.sin()
    feat[..., 2] = torch.tensor([0.08, 0.07], dtype=torch.float64)
    return feat


def write_labelled_robot(root: Path) -> tuple[Path, Path]:
    """Write a synthetic labelled recording under ``root``; returns (data folder with train.csv only,
    robot YAML with its servo map next to it). Tips: the CalibratedCC model of LABELLED_ROBOT + 0.1 mm noise;
    40 rows each of patterns seg1, seg2 and pair12."""
    spec = RobotSpec.from_dict(LABELLED_ROBOT)
    robot = root / "robot.yaml"
    spec.to_yaml(robot)
    (root / "servo_maps").mkdir()
    assignments = tuple(ServoAssignment(s, j // 3, j % 3) for j, s in enumerate(LABELLED_IDS))
    ServoMap(spec.name, assignments, -8e-3).to_yaml(root / "servo_maps" / "robot.yaml")
    g = torch.Generator().manual_seed(3)
    parts = [("rep1_seg1_dir0", (0,)), ("rep1_seg2_dir0", (1,)), ("rep1_pair12_same_dir0", (0, 1))]
    feat = torch.cat([_bent_features(g, 40, moving, 0.004) for _, moving in parts])
    labels = [label for label, _ in parts for _ in range(40)]
    dec = ClarkeDecoder(spec)
    x = dec(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - dec(feat)
    with torch.no_grad():
        tip = CalibratedCC(spec, compliance=1e-7)(x) + 1e-4 * torch.randn(len(x), 3, generator=g, dtype=torch.float64)
    data = root / "data"
    data.mkdir()
    with open(data / "train.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["timestamp", "pattern_label", *(f"servo_{i}_mm" for i in LABELLED_IDS), "tip_x", "tip_y", "tip_z"])
        w.writerows([[1000.0 + 0.5 * k, labels[k]] + [f"{v * 1e3:.5f}" for v in x[k].tolist() + tip[k].tolist()]
                     for k in range(len(x))])
    return data, robot
