"""The exported IK refinement (dacr_learn.ik.exported) and the Rerun recording of a solve."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import ROOT, TDCR3, first_pass_export, random_features, spec_by_name
from rerun_testkit import rrd_data, rrd_verify, rrd_views

from dacr_learn import load_exported
from dacr_learn.cli.ik import main
from dacr_learn.ik import ConstantCurvature
from dacr_learn.ik.exported import IKRefinement, export_refinement
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder

F64 = torch.float64


def warm_started(spec, n: int, noise: float, seed: int):
    """Targets (n, 4, 4) of random features and warm starts q0: those features moved by ``noise`` of the ranges."""
    model = ConstantCurvature(spec)
    feats = random_features(spec, (n,), seed)
    x = model.variables(ClarkeDecoder(spec).to(F64)(feats))
    g = torch.Generator().manual_seed(seed)
    q0 = model.joints(model.limits.project(x + noise * model.limits.scale * torch.randn(x.shape, generator=g,
                                                                                        dtype=F64)))
    return forward_kinematics(spec, feats), q0, model


@pytest.mark.parametrize("robot", ["tdcr_3seg_coupled", "twisting"])
def test_refinement_from_a_warm_start_reaches_micrometres_inside_the_limits(robot):
    spec = spec_by_name(robot)
    target, q0, model = warm_started(spec, 50, 0.005, 1)
    q, pos_err, rot_err = IKRefinement(spec, iterations=4)(target, q0)
    assert (pos_err <= 1e-6).all() and (rot_err <= 1e-5).all()
    check = model.check(q)                                     # from the joints alone
    assert check.inside.all() and (check.constraint <= 1e-9).all()
    assert ((check.position - target[:, :3, 3]).norm(dim=-1) <= 1e-6).all()


def test_refinement_position_only_and_bad_arguments():
    target, q0, _ = warm_started(TDCR3, 20, 0.005, 2)
    q, pos_err, rot_err = IKRefinement(TDCR3, 3, position_only=True)(target[:, :3, 3], q0)
    assert (pos_err <= 1e-6).all() and (rot_err == 0).all()
    with pytest.raises(ValueError, match="iterations"):
        IKRefinement(TDCR3, 0)


@pytest.mark.slow                                              # torch.export of the graph: ~10 s
def test_exported_refinement_equals_the_eager_one(tmp_path_factory):
    """The exported one-iteration refinement equals the eager one to 1e-12 (conftest.first_pass_export: under make
    test the second pass runs the first pass's export)."""
    robot = ROOT / "configs" / "robots" / "type1.yaml"
    root, meta = first_pass_export("ik_refinement", lambda out: export_refinement(robot, out / "export", iterations=1,
                                                                                  aoti=False), tmp_path_factory)
    assert meta["task"] == "ik_refinement" and meta["max_abs_deviation"]["refine.pt2"] <= 1e-12
    refine = load_exported(root / "export", "refine")
    spec = spec_by_name("type1")
    target, q0, _ = warm_started(spec, 5, 0.01, 3)
    got = refine(target, q0)
    expected = IKRefinement(spec, 1)(target, q0)
    for a, b in zip(got, expected, strict=True):
        assert (a - b).abs().max() <= 1e-12
    with pytest.raises(ValueError, match="refine input q0"):
        refine(target, q0[:, :2])


def test_cli_rerun_recording_shows_targets_and_solutions(tmp_path):
    poses = forward_kinematics(TDCR3, random_features(TDCR3, (3,), 4))
    np.save(tmp_path / "T.npy", poses.numpy())
    rrd = tmp_path / "ik.rrd"
    main(["--robot", str(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"), "--targets",
          str(tmp_path / "T.npy"), "--out", str(tmp_path / "S.npz"), "--solutions", "3", "--rerun", str(rrd),
          "--show", "2"])
    rrd_verify(rrd)
    data = rrd_data(rrd)
    assert {f"/ik/target_{b}/solution_{k}" for b in range(2) for k in range(3)} <= set(data)
    assert "/ik/target_2/frame" not in data and "/ik/target_1/frame" in data
    strip = data["/ik/target_0/solution_0"]["LineStrips3D:strips"][0][0]
    assert len(strip) == 1 + TDCR3.num_segments * 16                   # base + 16 points per segment
    views = rrd_views(rrd)
    assert [v["origin"] for v in views.values()] == ["ik"]
