"""Cosserat model, check (b): SoRoSim's static shapes of a 0.6 m steel rod and a 0.4 m TPU rod.

tests/data/sorosim/ (MIT, LICENSE and README there) holds 500 shapes per rod computed with SoRoSim, an
independent Cosserat-rod solver: gravity (9.81 m/s² in a random direction) plus one random wrench at
the middle and one at the tip. Decoded as follows (the only reading under which the shapes match, see
docs/cosserat.md §5): per shape six rows (EulX, EulY, EulZ, Px, Py, Pz) over 7 + 7 stations (the two
halves of the rod; normalised arc 0, .0469, .2308, .5, .7692, .9531, 1); the column ``gravity`` holds g
[m/s²] on the P rows, ``mid_wrench``/``tip_wrench`` hold (M [N·m], F [N]) on the six rows, in the
fixed (file) frame, whose x is the straight rod. Our base frame has z along the rod, so file (x, y, z)
is our (z, x, y). Euler angles are pytorch-kinematics' "XYZ" of the SoRoSim body frame (x tangent).
The lab validated its MuJoCo model against these shapes to < 1 % of the length; we require
≤ 1 % at every station and report the measured figure in docs/cosserat.md.

Orientation: the tangent must match for both rods. The whole frame matches for the steel rod; the TPU
frames carry no torsion (a fitted twist ratio of 0.005 of ours: SoRoSim's TPU model apparently had the
torsional strain off). For a rod of equal bending stiffnesses the centreline does not depend on GJ, so
positions and tangents stay a valid check there.
"""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import pytorch_kinematics.transforms as tf
import torch
from conftest import ROOT

from dacr_learn.cosserat import solve_statics
from dacr_learn.robot import RobotSpec

DATA = ROOT / "tests" / "data" / "sorosim"
FRACTIONS = (0.0, 0.0469, 0.2308, 0.5, 0.7692, 0.9531, 1.0)
FILE_TO_OURS = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)  # a_ours = P·a
CASES = [("SpringSteelRodMuJoCo_dataStatics.csv", "spring_steel_statics.json"),
         ("TPURodMuJoCo_dataStatics.csv", "tpu_statics.json")]


def load(csv_name: str, json_name: str):
    """(spec of the rod, shapes (N, 6, 17) as in the file, station arcs [m])."""
    cfg = json.loads((DATA / json_name).read_text())["generator_config"]
    mat, length = cfg["material_properties"], cfg["total_length"]
    spec = RobotSpec.from_dict({"name": "sorosim-rod", "segments": [
        {"type": "0", "length": length, "radius": mat["outer_radius"], "joints": 3}], "mechanics": {
        "youngs_modulus": mat["youngs_modulus"], "poisson_ratio": mat["poisson_ratio"],
        "outer_radius": mat["outer_radius"], "inner_radius": mat["inner_radius"], "density": mat["density"]}})
    with (DATA / csv_name).open() as fh:
        rows = list(csv.reader(fh))
    shapes = np.array([[float(x) for x in r[1:]] for r in rows[2:]]).reshape(-1, 6, 17)
    stations = [f * length / 2 for f in FRACTIONS] + [length / 2 + f * length / 2 for f in FRACTIONS[1:]]
    return spec, torch.tensor(shapes), stations


def to_ours(v: torch.Tensor) -> torch.Tensor:
    return v @ FILE_TO_OURS.T


@pytest.mark.slow
@pytest.mark.parametrize("csv_name,json_name", CASES)
def test_sorosim_shapes_within_one_percent_of_length(csv_name, json_name):
    spec, shapes, stations = load(csv_name, json_name)
    length = spec.total_length
    gravity = to_ours(shapes[:, 3:6, 0])
    mid = torch.cat([to_ours(shapes[:, 3:6, 1]), to_ours(shapes[:, 0:3, 1])], -1)    # (F, M), ours
    tip = torch.cat([to_ours(shapes[:, 3:6, 2]), to_ours(shapes[:, 0:3, 2])], -1)
    sol = solve_statics(spec, torch.zeros(shapes.shape[0], 3, dtype=torch.float64), gravity=gravity, tip_wrench=tip,
                        point_wrenches=[(length / 2, mid)], stations=stations, steps_per_segment=32)
    assert bool(sol.converged.all()) and float(sol.residual.max()) <= 1e-10
    columns = list(range(3, 10)) + list(range(11, 17))                  # seg1 s01..s07, seg2 s02..s07
    ref_pos = to_ours(shapes[:, 3:6, columns].transpose(1, 2))
    frames = sol.at(stations)
    err = (frames[..., :3, 3] - ref_pos).norm(dim=-1)
    deflection = (ref_pos[:, -1, :2]).norm(dim=-1)                      # tip off the straight line
    assert deflection.median() > 0.2 * length                            # large deflections, not a linear test
    assert err.max() <= 0.01 * length
    assert err.max() <= 0.002 * length          # measured 0.07 %, CSV rounding 0.1 mm (0.02-0.03 %) included
    # orientation: SoRoSim body frame (x tangent) = ours with (z, x, y) axes, Euler "XYZ", rounding 1e-4 rad
    rot_file = FILE_TO_OURS.T @ frames[..., :3, :3] @ FILE_TO_OURS
    ref_rot = tf.euler_angles_to_matrix(shapes[:, 0:3, columns].transpose(1, 2), "XYZ")
    tangent_cos = (rot_file[..., :, 0] * ref_rot[..., :, 0]).sum(-1)
    assert torch.acos(tangent_cos.clamp(max=1.0)).max() <= math.radians(0.5)      # measured 0.24° / 0.07°
    if csv_name.startswith("SpringSteel"):
        angle = 2 * torch.atan2((rot_file - ref_rot).flatten(-2).norm(dim=-1),
                                (rot_file + ref_rot).flatten(-2).norm(dim=-1))
        assert angle.max() <= math.radians(0.5)
