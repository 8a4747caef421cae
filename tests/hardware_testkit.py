"""Shared pieces of the hardware tests (not collected: no ``test_`` prefix).

FTDCR v4 / v6: the recordings and robot files (V4_*, V6_*) and the tip magnitude of the motion-capture frame
(V4_TIP_SCALE); slices of v4 for the CC model and the compositional hardware model (fixtures ``v4_train_head``,
``v4_slice`` and ``compositional_models`` in tests/conftest.py).

A small synthetic 2-segment robot: a CalibratedCC with non-trivial physical parameters and an ensemble of untrained
residual networks (with enlarged output weights, so that the correction matters), for the deploy tests
(checkpoint, inference, export, uncertainty) and the control example.

:func:`write_labelled_robot`: a labelled synthetic recording folder (single-segment and pair patterns,
no val.csv, like data/ftdcr_v6) for the selection-proxy and CLI tests (fixture ``labelled_robot_dir``
in tests/conftest.py); the same robot's servo map and a synthetic split of it for the compositional model
(fixture ``compositional_split``).
"""
from __future__ import annotations

import csv
import math
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from conftest import ROOT, roundoff_tol

from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.compositional_model import CCCompositionalResidual
from dacr_learn.hardware.deploy.checkpoint import HardwareModel, load_hardware_model, save_hardware_model
from dacr_learn.hardware.deploy.uncertainty import SigmaCalibration, SigmaModel, SupportModel
from dacr_learn.hardware.learned import CCClarkeResidual, CCClarkeResidualHistory, Split, make_split, synthetic_split
from dacr_learn.hardware.recording import Recording, load_recording
from dacr_learn.hardware.servo_map import ServoAssignment, ServoMap
from dacr_learn.hardware.study.benchmark import Setup, load_setup, resolve_robot
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec

V4_DATA = ROOT / "data" / "ftdcr_v4"
V4_ROBOT = ROOT / "configs" / "robots" / "ftdcr_v4.yaml"
V4_CALIBRATED = ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml"
V6_DATA = ROOT / "data" / "ftdcr_v6"
V6_ROBOT = ROOT / "configs" / "robots" / "ftdcr_v6.yaml"
V6_CALIBRATED = ROOT / "configs" / "robots" / "ftdcr_v6_calibrated.yaml"
V4_TIP_SCALE = 0.2                                  # [m] magnitude of FTDCR v4's tip coordinates (motion-capture frame)

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
        member = cls(cc)
        member.fit_normalization(train)
        with torch.no_grad():
            member.net[-1].weight.mul_(20.0)
        nets.append(member.eval())
    support = SupportModel(spec.num_segments).fit(train.features[..., :2], ["p"] * 100 + ["q"] * 100)
    return HardwareModel("cc_clarke_residual_history" if history else "cc_clarke_residual", spec, smap, IDS, cc,
                         nets, sigma=SigmaCalibration(1.5, 2e-4), support=support,
                         examples=1e3 * command_recording(64, 3).servo)


SUPPORT_SCALE = 10.0     # magnitude of the standardised Clarke coordinates the support distance is computed from


def saved_history_model(folder: Path, members: int = 3) -> tuple[HardwareModel, Path, torch.Tensor]:
    """The history test model (:func:`synthetic_model`) as --save writes it (its recorded servo range: 200
    training-like commands), saved to ``folder``/model.pt and loaded back: (model, checkpoint, those commands [mm])."""
    model = synthetic_model(history=True, members=members)
    commands = 1e3 * command_recording(200, 0).servo
    model.info["servo_range_mm"] = {"lower": commands.amin(0).tolist(), "upper": commands.amax(0).tolist()}
    path = save_hardware_model(model, folder / "model.pt")
    return load_hardware_model(path), path, commands


def export_recording_warnings(ckpt: Path, out: Path) -> tuple[dict, list[str]]:
    """``python -m dacr_learn.export`` of a hardware checkpoint into ``out`` without AOTI: (its metadata, the messages
    of every warning the export raised)."""
    from dacr_learn import export as dexport

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        meta = dexport.export_checkpoint(ckpt, out, aoti=False)
    return meta, [str(w.message) for w in caught]


def sigma_roundoff_tol(model: HardwareModel, dtype: torch.dtype, tip_scale: float, ulps: float = 64.0,
                       support_dtype: torch.dtype = torch.float64) -> float:
    """Tolerance [m] for two computations of ``model``'s σ (its :meth:`~HardwareModel.sigma_of`) that differ only by
    rounding, tied to the scale σ is computed from rather than to σ's own (sub-millimetre) scale.

    σ_a = √(σ₀² + Σ_t (c_t·f_t,a)²) has ∂σ_a/∂f_t,a = c_t²·f_t,a/σ_a ≤ c_t, so feature errors δ_t move σ by at most
    Σ_t c_t·δ_t. The ensemble std and the disagreement |mean − CC tip| are differences of tips: each off by at most
    two roundings at ``tip_scale`` [m] in ``dtype``; the bend ‖ρ‖ comes from tendon displacements no larger than the
    tip's scale either; the support distance (dimensionless, computed in ``support_dtype``) rounds at the scale of
    the standardised coordinates (SUPPORT_SCALE). The sqrt adds a relative rounding of σ, far below these."""
    sigma = model.sigma_of()
    tip = roundoff_tol(dtype, tip_scale, ulps)
    per_term = {"ensemble": 2 * tip, "disagreement": 2 * tip, "bend": tip,
                "support": roundoff_tol(support_dtype, SUPPORT_SCALE, ulps)}
    return sum(c * per_term[t] for c, t in zip(sigma.coefficients.tolist(), sigma.terms, strict=True))


def ensemble_predict(members: Sequence[Callable], x) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean (n, 3), std (n, 3)) over ensemble members ``member(x)`` → (n, 3) [m], in their dtype; std with K − 1
    (zeros for K = 1)."""
    if len(members) == 0:
        raise ValueError("members: expected at least one model, got an empty sequence")
    with torch.no_grad():
        preds = torch.stack([m(x) for m in members])
    std = preds.std(0, correction=1) if len(members) > 1 else torch.zeros_like(preds[0])
    return preds.mean(0), std


def batch_prediction(model: HardwareModel, rec: Recording) -> torch.Tensor:
    split = make_split(rec, model.spec, model.smap, model.cc)
    return ensemble_predict(model.members, split)[0]


LABELLED_ROBOT = {"name": "synthetic-2seg", "routing": "coupled", "segments": [
    {"type": "0", "length": 0.08, "radius": 0.005, "joints": 3, "offset": 0.3, "limits": {"bend": 0.8}},
    {"type": "0", "length": 0.07, "radius": 0.005, "joints": 3, "offset": -0.5, "limits": {"bend": 0.8}}]}
LABELLED_IDS = ("s4", "s1", "s6", "s2", "s5", "s3")


def labelled_servo_map(spec: RobotSpec) -> ServoMap:
    """The servo map of LABELLED_ROBOT: servo LABELLED_IDS[j] drives segment j // 3, joint j % 3."""
    return ServoMap(spec.name, tuple(ServoAssignment(s, j // 3, j % 3) for j, s in enumerate(LABELLED_IDS)), -8e-3)


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
    labelled_servo_map(spec).to_yaml(root / "servo_maps" / "robot.yaml")
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


# --------------------------------------------------------------------------------------------------
# FTDCR v4 slices, the compositional hardware model, CSV files
# --------------------------------------------------------------------------------------------------


def synthetic_compositional_split() -> tuple[CalibratedCC, Split]:
    """The calibrated CC model of LABELLED_ROBOT at its nominal parameters (frozen) and a synthetic split of 64
    rows of it (fixture ``compositional_split``)."""
    spec = RobotSpec.from_dict(LABELLED_ROBOT)
    smap = labelled_servo_map(spec)
    cc = CalibratedCC(spec, compliance=1e-7)
    for p in cc.parameters():
        p.requires_grad_(False)
    return cc, synthetic_split(cc, smap, LABELLED_IDS, 64, seed=0)


def load_v4_train_head(root: Path) -> tuple[RobotSpec, ServoMap, Recording]:
    """(spec, servo map, the first 240 rows of FTDCR v4's train.csv) of the calibrated robot (fixture
    ``v4_train_head``); ``root``: an empty folder for resolve_robot."""
    spec, smap, _ = resolve_robot(V4_CALIBRATED, None, None, root, "mm")
    rec = load_recording(V4_DATA / "train.csv", spec)
    return spec, smap, rec.select(torch.arange(len(rec)) < 240)


def load_v4_slice(root: Path) -> Setup:
    """The benchmark setup (calibrated robot, servo map, CC model fitted) of every 8th row of FTDCR v4's train.csv,
    written to ``root``/train.csv."""
    rows = (V4_DATA / "train.csv").read_text().splitlines()
    (root / "train.csv").write_text("\n".join(rows[:1] + rows[1::8]) + "\n")
    return load_setup(V4_CALIBRATED, root / "train.csv", None, root)


COMPOSITIONAL_CONFIGS = {"none": {}, "distal": {"context": "distal", "torsion": True},
                         "segment": {"context": "segment"}}


def compositional_ensemble(setup, config: str = "none", members: int = 2, steps: int = 20) -> HardwareModel:
    """An ensemble of CCCompositionalResidual members (context and torsion of COMPOSITIONAL_CONFIGS[config]) trained
    for ``steps`` steps on the setup's rows, with a support model, a σ calibration and a σ model."""
    nets = []
    for seed in range(members):
        torch.manual_seed(seed)
        member = CCCompositionalResidual(setup.cc, steps=max(steps, 1), **COMPOSITIONAL_CONFIGS[config])
        if steps:
            member.fit(setup.train)
        else:
            member.fit_normalization(setup.train)
        nets.append(member.eval())
    support = SupportModel(setup.spec.num_segments).fit(setup.train.features[..., :2], list(setup.train_rec.labels))
    return HardwareModel("cc_compositional_residual", setup.spec, setup.smap, setup.train_rec.servo_ids, setup.cc,
                         nets, sigma=SigmaCalibration(1.5, 2e-4), support=support,
                         examples=1e3 * setup.train_rec.servo[:64],
                         sigma_model=SigmaModel(("ensemble", "bend"), (1.3, 0.05), 3e-4))


def v4_commands(setup, n: int = 24) -> torch.Tensor:
    """Commands [mm]: training rows spread over the recording (all three segments' patterns)."""
    servo = 1e3 * setup.train_rec.servo
    return servo[torch.linspace(0, servo.shape[0] - 1, n).long()]


def strained_cc(spec, strain: bool, p: float = 3e-4, s: float = 5e-4) -> CalibratedCC:
    """A CalibratedCC with non-trivial parameters, a common pretension ``p`` and, with ``strain``, the pretension
    strain ``s`` (tendon i stretched by p + s·(L_i/L̄ − 1))."""
    cc = CalibratedCC(spec, compliance=1e-6, pretension_strain=strain)
    with torch.no_grad():
        cc.encoder.log_radius_scale.copy_(torch.tensor([0.05, -0.03, 0.02]))
        cc.encoder.rotation.copy_(torch.tensor([0.02, -0.04, 0.03]))
        cc.encoder.pretension.fill_(p)
        cc.base_translation.copy_(torch.tensor([0.01, -0.02, 0.005]))
        cc.tip_offset.fill_(8e-3)
        if strain:
            cc.encoder.pretension_strain.fill_(s)
    return cc


def write_csv(path: Path, header: list[str], rows: list[list]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path
