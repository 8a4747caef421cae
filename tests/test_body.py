"""The body (dacr_learn.body), scenes and their distances (dacr_learn.scene) against independent references:
the classic arc formula in NumPy, dense NumPy distances of finely sampled arcs, gradcheck in float64."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import random_features, reference_backbone, spec_by_name

from dacr_learn.body import BodyPoints, cc_body, chord_sag
from dacr_learn.ik import ConstantCurvature, SolverModel
from dacr_learn.robot import RobotSpec
from dacr_learn.scene import Swept, chain_clearance, convex_bound, load_scene, scene_from_dict, swept_body

F64 = torch.float64
TDCR3 = spec_by_name("tdcr_3seg_equal")


@pytest.mark.parametrize("name", ["tdcr_3seg_equal", "twisting", "hetero_4seg_types"])
def test_cc_body_is_the_arcs_with_arc_length_and_radius(name):
    spec = spec_by_name(name)
    f = random_features(spec, (5,), seed=3)
    model = ConstantCurvature(spec)
    body = model.body(model.variables(_joints(spec, f)), 6)
    assert isinstance(body, BodyPoints) and body.points.shape == (5, 1 + 6 * spec.num_segments, 3)
    for i in range(5):
        ref = reference_backbone(spec, f[i].numpy(), 6)
        assert np.abs(body.points[i].numpy() - ref).max() < 1e-12 * spec.total_length * 10
    lengths = np.concatenate([[0.0], np.cumsum(np.repeat([s.length for s in spec.segments], 6) / 6)])
    assert np.allclose(body.arc_length.numpy(), lengths, rtol=0, atol=1e-15)
    radii = [spec.segments[0].body_radius] + [s.body_radius for s in spec.segments for _ in range(6)]
    assert body.radius.tolist() == radii


def _joints(spec: RobotSpec, f: torch.Tensor) -> torch.Tensor:
    from dacr_learn.layers import ClarkeDecoder
    return ClarkeDecoder(spec).to(F64)(f)


def test_body_radius_default_explicit_and_validated():
    d = TDCR3.to_dict()
    assert TDCR3.segments[0].body_radius == max(TDCR3.segments[0].joint_radii) == 0.008
    d["segments"][1]["body_radius"] = 0.012
    spec = RobotSpec.from_dict(d)
    assert spec.segments[1].body_radius == 0.012 and spec.segments[0].body_radius == 0.008
    assert RobotSpec.from_dict(spec.to_dict()) == spec
    for bad in (-0.01, 0, "thick", float("nan")):
        d["segments"][1]["body_radius"] = bad
        with pytest.raises(ValueError, match=r"segments\[1\]\.body_radius"):
            RobotSpec.from_dict(d)


def test_cc_body_gradcheck_float64():
    f = random_features(TDCR3, (2,), seed=1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: cc_body(TDCR3, x, 3).points, (f,))


def test_model_without_body_says_so():
    with pytest.raises(ValueError, match="has no body"):
        SolverModel().body(torch.zeros(1, 3, dtype=F64))


# -- distances -----------------------------------------------------------------------------------------------

SCENE = {"obstacles": [
    {"type": "sphere", "center": [0.05, 0.02, 0.12], "radius": 0.03},
    {"type": "capsule", "a": [-0.08, 0.0, 0.05], "b": [-0.06, 0.05, 0.2], "radius": 0.015},
    {"type": "box", "center": [0.0, -0.09, 0.15], "half_extents": [0.04, 0.01, 0.06], "rpy": [0.3, -0.2, 0.7]},
]}


def rpy_numpy(r, p, y):
    cx, sx, cy, sy, cz, sz = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def numpy_distances(points: np.ndarray) -> np.ndarray:
    """Signed distances (N, 3 obstacles) of SCENE by projection onto each obstacle, NumPy."""
    s, c, b = SCENE["obstacles"]
    d_s = np.linalg.norm(points - s["center"], axis=-1) - s["radius"]
    a, e = np.array(c["a"]), np.array(c["b"])
    t = np.clip((points - a) @ (e - a) / ((e - a) @ (e - a)), 0, 1)
    d_c = np.linalg.norm(points - (a + t[:, None] * (e - a)), axis=-1) - c["radius"]
    rot, half = rpy_numpy(*b["rpy"]), np.array(b["half_extents"])
    local = (points - b["center"]) @ rot
    nearest = np.clip(local, -half, half)
    outside = np.linalg.norm(local - nearest, axis=-1)
    inside = np.min(half - np.abs(local), axis=-1)
    d_b = np.where(outside > 0, outside, -inside)
    return np.stack([d_s, d_c, d_b], -1)


def test_primitive_distances_match_numpy_and_gradients_are_unit_normals():
    scene = scene_from_dict(SCENE)
    pts = torch.from_numpy(np.random.default_rng(0).uniform([-0.12, -0.12, 0.0], [0.12, 0.12, 0.25], (4000, 3)))
    d, g = scene.distances(pts, grad=True)
    order = [scene.labels.index(f"obstacles[{i}] ({o['type']})") for i, o in enumerate(SCENE["obstacles"])]
    assert np.abs(d[:, order].numpy() - numpy_distances(pts.numpy())).max() < 1e-14
    assert (d < 0).any() and (d > 0).any()
    auto = torch.func.vmap(torch.func.jacrev(lambda p: scene.distances(p)[0]))(pts)            # (N, O, 3)
    assert (auto - g).abs().max() < 1e-9
    i, o = torch.randint(0, 4000, (50,)), torch.randint(0, 3, (50,))
    dp, gp = scene.pair_distances(pts[i], o)
    assert torch.equal(dp, d[i, o]) and torch.allclose(gp, g[i, o], rtol=0, atol=1e-15)


def test_distance_gradcheck_float64():
    scene = scene_from_dict(SCENE)
    pts = torch.tensor([[0.01, 0.02, 0.1], [-0.05, 0.03, 0.12], [0.02, -0.07, 0.16]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: scene.distances(p)[0], (pts,))


def test_chain_clearance_is_a_tight_lower_bound_of_dense_arcs():
    """The swept-chord bound never exceeds the clearance of the exact arcs (1,500 points per segment, NumPy) and
    is within 2 mm of it at 8 points per segment without tangent cuts, within 0.5 mm with them (the default) and
    within 0.15 mm at 16 (the sag bound is loose at segment joints)."""
    spec = spec_by_name("tdcr_3seg_equal")
    scene = scene_from_dict(SCENE)
    f = random_features(spec, (20,), seed=7)
    true = np.array([(numpy_distances(reference_backbone(spec, f[i].numpy(), 1500))
                      - spec.segments[0].body_radius).min() for i in range(20)])        # computed once per sample
    for k, cuts, gap in ((8, 0, 2e-3), (8, 2, 5e-4), (16, 2, 1.5e-4)):
        bound = chain_clearance(scene, swept_body(cc_body(spec, f, k)), cuts=cuts).numpy()
        assert (bound <= true + 1e-12).all(), (k, cuts, bound - true)
        assert (true - bound < gap).all(), (k, cuts, true - bound)


def test_sphere_distances_without_autograd_match_numpy():
    """Without autograd the spheres take torch.cdist (no (..., O, 3) differences): the same distances."""
    scene = scene_from_dict(SCENE)
    pts = torch.from_numpy(np.random.default_rng(4).uniform([-0.12, -0.12, 0.0], [0.12, 0.12, 0.25], (3, 700, 3)))
    with torch.no_grad():
        d = scene.distances(pts)[0]
    ref = numpy_distances(pts.numpy().reshape(-1, 3)).reshape(3, 700, 3)
    order = [scene.labels.index(f"obstacles[{i}] ({o['type']})") for i, o in enumerate(SCENE["obstacles"])]
    assert d.shape == (3, 700, 3) and np.abs(d[..., order].numpy() - ref).max() < 1e-14


def _every_pair_bound(scene, swept: Swept) -> torch.Tensor:
    """The chain bound with the convex bound taken for every (chord, obstacle) pair (no selection)."""
    p = swept.points
    d, g = scene.distances(p, grad=True)
    chord = (p[:, 1:] - p[:, :-1]).unsqueeze(-2)
    length = torch.linalg.vector_norm(chord, dim=-1)
    shrink = (swept.radius + swept.sag).unsqueeze(-1)
    lip = (d[:, :-1] + d[:, 1:] - length) / 2 - shrink
    convex = convex_bound(d[:, :-1], d[:, 1:], (g[:, :-1] * chord).sum(-1), (g[:, 1:] * chord).sum(-1)) - shrink
    return torch.maximum(lip, convex).flatten(1).amin(-1)


def test_chain_clearance_selects_every_pair_that_can_decide():
    """Refining only the pairs whose Lipschitz bound lies below the row's upper bound gives exactly the bound of
    refining every pair (without cuts; the cuts only tighten it); with ``decide`` the (looser) bound lies on the
    same side of the threshold."""
    scene = scene_from_dict(SCENE)
    f = random_features(TDCR3, (300,), seed=11)
    for k in (4, 16):
        swept = swept_body(cc_body(TDCR3, f, k))
        plain = chain_clearance(scene, swept, cuts=0)
        assert torch.allclose(plain, _every_pair_bound(scene, swept), rtol=0, atol=1e-15)
        full = chain_clearance(scene, swept)
        assert (full >= plain - 1e-15).all()                               # the tangent cuts only tighten
        for threshold in (-0.01, 0.0, 0.004, float(full.median())):
            decided = chain_clearance(scene, swept, decide=threshold)
            assert (decided <= full + 1e-15).all()
            assert torch.equal(decided >= threshold, full >= threshold)


def test_chord_sag_bounds_the_arc():
    spec = spec_by_name("tdcr_3seg_equal")
    f = random_features(spec, (10,), seed=2)
    coarse, dense = cc_body(spec, f, 4).points.numpy(), cc_body(spec, f, 400).points.numpy()
    sag = chord_sag(torch.from_numpy(coarse)).numpy()
    for i in range(10):
        for c in range(coarse.shape[1] - 1):
            a, b = coarse[i, c], coarse[i, c + 1]
            arc = dense[i, c * 100:(c + 1) * 100 + 1]
            t = np.clip((arc - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
            off = np.linalg.norm(arc - (a + t[:, None] * (b - a)), axis=-1).max()
            assert off <= sag[i, c] + 1e-15 and sag[i, c] < 6 * off + 1e-9


def test_mesh_obstacle_matches_the_box_it_is(tmp_path):
    import trimesh
    trimesh.creation.box(extents=[80.0, 20.0, 120.0]).export(tmp_path / "part.stl")
    (tmp_path / "s.yaml").write_text("obstacles:\n  - {type: mesh, file: part.stl, scale: 0.001, xyz: [0.0, -0.09, "
                                     "0.15], rpy: [0.3, -0.2, 0.7]}\n")
    mesh_scene = load_scene(tmp_path / "s.yaml")
    box = numpy_distances
    pts = torch.from_numpy(np.random.default_rng(1).uniform([-0.1, -0.2, 0.05], [0.1, 0.0, 0.25], (300, 3)))
    pts.requires_grad_(True)
    d = mesh_scene.distances(pts)[0]
    assert np.abs(d[:, 0].detach().numpy() - box(pts.detach().numpy())[:, 2]).max() < 1e-9
    (grad,) = torch.autograd.grad(d.sum(), pts)
    ref = scene_from_dict({"obstacles": [SCENE["obstacles"][2]]}).distances(pts.detach(), grad=True)[1][:, 0]
    assert (grad - ref).abs().max() < 1e-6
    swept = Swept(pts.detach()[:4].unsqueeze(0), torch.full((3,), 0.001, dtype=F64), torch.zeros(1, 3, dtype=F64),
                  torch.ones(3, dtype=torch.bool))
    assert chain_clearance(mesh_scene, swept) <= d[:4, 0].min() - 0.001


@pytest.mark.parametrize("entry, field", [
    ({"type": "cone", "center": [0, 0, 0]}, "obstacles[1].type"),
    ({"type": "sphere", "center": [0, 0, 0]}, "obstacles[1].radius"),
    ({"type": "sphere", "center": [0, 0], "radius": 0.1}, "obstacles[1].center"),
    ({"type": "sphere", "center": [0, 0, 0], "radius": -1}, "obstacles[1].radius"),
    ({"type": "capsule", "a": [0, 0, 0], "b": [0, 0, "x"], "radius": 0.1}, "obstacles[1].b"),
    ({"type": "box", "center": [0, 0, 0], "half_extents": [0.1, 0, 0.1]}, "obstacles[1].half_extents[1]"),
    ({"type": "box", "center": [0, 0, 0], "half_extents": [0.1, 0.1, 0.1], "rpy": [0, 0]}, "obstacles[1].rpy"),
    ({"type": "box", "center": [0, 0, 0], "half_extents": [0.1, 0.1, 0.1], "colour": 1}, "obstacles[1].colour"),
    ({"type": "mesh", "file": "nowhere.stl"}, "obstacles[1].file"),
])
def test_bad_scene_file_is_one_line_naming_entry_and_field(tmp_path, entry, field):
    import yaml
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"obstacles": [SCENE["obstacles"][0], entry]}))
    with pytest.raises(ValueError) as err:
        load_scene(path)
    assert str(err.value).startswith(f"{path}: {field}:") and "\n" not in str(err.value)


def test_scene_file_top_level_errors(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("spheres: []\n")
    with pytest.raises(ValueError, match="obstacles"):
        load_scene(path)
    empty = scene_from_dict({"obstacles": []})
    swept = swept_body(cc_body(TDCR3, random_features(TDCR3, (2,), 0), 4))
    assert torch.isinf(chain_clearance(empty, swept)).all()
