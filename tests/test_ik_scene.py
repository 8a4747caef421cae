"""Collision-free IK (solve_ik(..., scene=, clearance=)), the arm's link geometry and the CLI's --scene: every
flagged solution is re-checked with NumPy geometry (the classic arcs of the joints' features, densely sampled,
and the obstacles' distances by projection)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from arm_reference import UrdfArm
from conftest import ROOT, reference_backbone, reference_joint_vector, spec_by_name

from dacr_learn.arm import Composite, load_arm
from dacr_learn.ik import ConstantCurvature, IKOptions, solve_ik
from dacr_learn.ik.collision import Avoidance
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.scene import load_scene

F64 = torch.float64
SPEC = spec_by_name("tdcr_3seg_equal")
SCENE_FILE = ROOT / "configs" / "scenes" / "spheres_tdcr3.yaml"
D = 0.004


def numpy_clearance(spec, q: np.ndarray, centers: np.ndarray, radii: np.ndarray, points: int = 600) -> float:
    """Clearance of one joint vector's body to spheres: features by the encoder, accepted only when the
    independent joint geometry reproduces q; then the classic arcs, densely sampled, minus the body radius."""
    f = ClarkeEncoder(spec).to(F64)(torch.from_numpy(q)).numpy()
    assert np.abs(reference_joint_vector(spec, f) - q).max() < 1e-9
    arc = reference_backbone(spec, f, points)
    d = np.linalg.norm(arc[:, None] - centers[None], axis=-1) - radii
    return float(d.min() - spec.segments[0].body_radius)


def clear_targets(model, scene, n: int, seed: int) -> torch.Tensor:
    x = model.limits.sample(40 * n, torch.Generator().manual_seed(seed))
    x = x[Avoidance(model, scene, D).clearance_of(x) >= D][:n]
    return forward_kinematics(SPEC, model.features(x))


def test_collision_free_solutions_pass_the_dense_numpy_check():
    model, scene = ConstantCurvature(SPEC), load_scene(SCENE_FILE)
    targets = clear_targets(model, scene, 5, seed=0)
    res = solve_ik(model, targets, 4, scene=SCENE_FILE, clearance=D)
    assert res.clearance.shape == (5, 4) and torch.isfinite(res.clearance).all()
    assert res.success.any(1).all()
    centers, radii = scene.sphere_center.numpy(), scene.sphere_radius.numpy()
    for b, k in res.success.nonzero().tolist():
        true = numpy_clearance(SPEC, res.q[b, k].numpy(), centers, radii)
        assert true >= D and true - 5e-4 <= res.clearance[b, k].item() <= true
    plain = solve_ik(model, targets, 4)
    assert plain.clearance is None and "clearance" not in plain.numpy()


@pytest.mark.parametrize("pool", [8192, 0])
def test_target_without_collision_free_solution_fails_cleanly(pool):
    """A tip inside an obstacle: no solution is collision-free, success is False, nothing is NaN (the working
    batch and the grouped restarts)."""
    model = ConstantCurvature(SPEC)
    x = model.rest.unsqueeze(0).clone()
    target = forward_kinematics(SPEC, model.features(x))
    scene = {"obstacles": [{"type": "sphere", "center": target[0, :3, 3].tolist(), "radius": 0.02}]}
    res = solve_ik(model, target, 2, scene=scene, clearance=0.0,
                   options=IKOptions(restarts=1, max_iterations=10, pool=pool))
    assert not res.success.any()
    assert torch.isfinite(res.q).all() and torch.isfinite(res.clearance).all() and (res.clearance < 0).all()


def test_working_batch_and_grouped_restarts_keep_the_same_contract():
    """The scene solve in the working batch (default) and with grouped restarts (pool=0): every flagged solution
    clears D by the dense NumPy check, its reported clearance is the independent check of the returned joints
    recomputed now, and both solve every target; with two shards the same holds."""
    model, scene = ConstantCurvature(SPEC), load_scene(SCENE_FILE)
    targets = clear_targets(model, scene, 4, seed=8)
    avoid = Avoidance(model, scene, D)
    centers, radii = scene.sphere_center.numpy(), scene.sphere_radius.numpy()
    checked = {}                                    # joints → dense check: a solution found again is checked once
    for options in (IKOptions(), IKOptions(pool=0), IKOptions(shards=2)):
        res = solve_ik(model, targets, 3, scene=scene, clearance=D, options=options)
        assert res.success.any(1).all() and res.clearance.shape == (4, 3)
        again = avoid.clearance_of_joints(res.q.reshape(-1, res.q.shape[-1])).view(4, 3)
        assert torch.allclose(again, res.clearance, rtol=0, atol=1e-15)
        assert torch.equal(res.success, res.success & (res.clearance >= D))
        for b, k in res.success.nonzero().tolist():
            q = res.q[b, k].numpy()
            if q.tobytes() not in checked:
                checked[q.tobytes()] = numpy_clearance(SPEC, q, centers, radii)
            true = checked[q.tobytes()]
            assert true >= D and true - 5e-4 <= res.clearance[b, k].item() <= true + 1e-12


def test_tangent_cuts_bound_convex_obstacles_along_a_chord():
    """cut_bound never exceeds the smallest distance of 4,001 points along each chord (spheres, capsules, boxes),
    is never looser than the two end tangents' bound, and with two cuts is within 0.2 mm of the minimum on chords
    of 12 mm."""
    from dacr_learn.scene import convex_bound, cut_bound, scene_from_dict
    scene = scene_from_dict({"obstacles": [
        {"type": "sphere", "center": [0.0, 0.0, 0.1], "radius": 0.02},
        {"type": "capsule", "a": [0.05, -0.03, 0.0], "b": [0.05, 0.03, 0.2], "radius": 0.01},
        {"type": "box", "center": [-0.05, 0.02, 0.12], "half_extents": [0.02, 0.01, 0.03], "rpy": [0.3, -0.2, 0.9]}]})
    gen = np.random.default_rng(6)
    n = 300
    o = torch.from_numpy(np.repeat(np.arange(3), n // 3))
    a = torch.from_numpy(gen.uniform([-0.1, -0.06, 0.04], [0.1, 0.06, 0.18], (n, 3)))
    direction = torch.from_numpy(gen.normal(size=(n, 3)))
    b = a + 0.012 * direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True)
    t = torch.linspace(0, 1, 4001, dtype=F64).view(1, -1, 1)
    with torch.no_grad():
        d = scene.distances(a.unsqueeze(1) + t * (b - a).unsqueeze(1))[0]                  # (n, 4001, 3)
    dense = d.gather(2, o.view(-1, 1, 1).expand(-1, t.shape[1], 1)).amin((1, 2))
    pair = lambda rows, p, f: scene.pair_distances(p, f)                              # noqa: E731
    fa, ga = scene.pair_distances(a, o)
    fb, gb = scene.pair_distances(b, o)
    plain = convex_bound(fa, fb, (ga * (b - a)).sum(-1), (gb * (b - a)).sum(-1))
    rows = torch.arange(n)
    for cuts in (0, 1, 2, 3):
        bound = cut_bound(pair, rows, a, b, o, cuts)
        assert (bound <= dense + 1e-15).all() and (bound >= plain - 1e-15).all()
    assert torch.equal(cut_bound(pair, rows, a, b, o, 0), plain)
    assert (dense - cut_bound(pair, rows, a, b, o, 2)).max() < 2e-4


def test_negative_clearance_is_refused():
    with pytest.raises(ValueError, match="clearance"):
        solve_ik(SPEC, torch.eye(4, dtype=F64).unsqueeze(0), 1, scene=SCENE_FILE, clearance=-1.0)


URDF = """<robot name="two">
  <link name="base"><collision><origin xyz="0 0 0.05"/><geometry><cylinder radius="0.04" length="0.1"/></geometry>
  </collision></link>
  <link name="upper"><collision><origin xyz="0 0 0.15" rpy="0 0 0.3"/><geometry><box size="0.05 0.06 0.3"/>
  </geometry></collision></link>
  <link name="hand"><collision><geometry><sphere radius="0.03"/></geometry></collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="upper"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="upper"/><child link="hand"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
</robot>"""


def test_link_capsules_contain_the_urdf_collision_geometry():
    arm = load_arm(URDF, "hand")
    g = arm.geometry
    assert g.source == "urdf" and g.frame.tolist() == [0, 1, 2] and g.near_mount.tolist() == [False, False, True]
    a, b, r = g.a.numpy(), g.b.numpy(), g.radius.numpy()
    assert np.allclose([a[0], b[0]], [[0, 0, 0], [0, 0, 0.1]]) and r[0] == 0.04           # cylinder
    assert np.allclose(np.sort([a[1][2], b[1][2]]), [0.0, 0.3]) and np.isclose(r[1], np.hypot(0.025, 0.03))
    assert np.allclose(a[2], b[2]) and r[2] == 0.03                                       # sphere
    rng = np.random.default_rng(0)                          # every corner region of the box lies in its capsule
    corners = rng.uniform(-1, 1, (500, 3)) * [0.025, 0.03, 0.15]
    c, s = np.cos(0.3), np.sin(0.3)
    pts = corners @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [0, 0, 0.15]
    t = np.clip((pts - a[1]) @ (b[1] - a[1]) / np.dot(b[1] - a[1], b[1] - a[1]), 0, 1)
    assert (np.linalg.norm(pts - (a[1] + t[:, None] * (b[1] - a[1])), axis=-1) <= r[1] + 1e-12).all()


def test_panda_fallback_capsules_and_composite_body():
    arm = load_arm(ROOT / "configs" / "arms" / "panda.urdf", "panda_link8")
    g = arm.geometry
    assert g.source == "fallback" and (g.radius == 0.06).all()
    assert [arm.frame_names[i] for i in g.frame[g.near_mount].tolist()] == ["panda_link7"]
    mount = torch.from_numpy(np.load(ROOT / "configs" / "arms" / "panda_mount.npy"))
    whole = Composite(arm, mount, SPEC)
    x = whole.limits.sample(3, torch.Generator().manual_seed(1))
    body = whole.body(x, 4)
    ref = UrdfArm(ROOT / "configs" / "arms" / "panda.urdf", "panda_link8")
    robot = ConstantCurvature(SPEC).body(x[:, 7:], 4).points.numpy()
    for i in range(3):
        base = ref.tip_pose(x[i, :7].numpy()) @ mount.numpy()
        assert np.abs(body.points[i].numpy() - (robot[i] @ base[:3, :3].T + base[:3, 3])).max() < 1e-12
    a, b, radius, near = whole.links(x)
    assert a.shape == (3, g.radius.numel(), 3) and near.tolist() == g.near_mount.tolist()


def test_cli_scene_and_clearance(tmp_path):
    from dacr_learn.cli.ik import main
    model, scene = ConstantCurvature(SPEC), load_scene(SCENE_FILE)
    np.save(tmp_path / "t.npy", clear_targets(model, scene, 2, seed=4).numpy())
    args = ["--robot", str(ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml"), "--targets", str(tmp_path / "t.npy"),
            "--out", str(tmp_path / "s.npz"), "--solutions", "2"]
    with pytest.raises(ValueError, match="--clearance goes with --scene"):
        main(args + ["--clearance", "0.01"])
    main(args + ["--scene", str(SCENE_FILE), "--clearance", str(D)])
    out = np.load(tmp_path / "s.npz")
    assert out["clearance"].shape == (2, 2) and (out["clearance"][out["success"]] >= D).all()


def test_rerun_draws_obstacles_and_the_body_coloured_by_clearance(tmp_path):
    from rerun_testkit import rrd_data, rrd_verify

    from dacr_learn.cli.ik import main
    from dacr_learn.viz.obstacles import clearance_colors
    model, scene = ConstantCurvature(SPEC), load_scene(SCENE_FILE)
    np.save(tmp_path / "t.npy", clear_targets(model, scene, 2, seed=5).numpy())
    main(["--robot", str(ROOT / "configs" / "robots" / "tdcr_3seg_equal.yaml"), "--targets", str(tmp_path / "t.npy"),
          "--out", str(tmp_path / "s.npz"), "--solutions", "2", "--scene", str(SCENE_FILE), "--clearance", str(D),
          "--rerun", str(tmp_path / "s.rrd"), "--show", "2"])
    rrd_verify(tmp_path / "s.rrd")
    data = rrd_data(tmp_path / "s.rrd")
    for b in range(2):
        centers = data[f"/ik/target_{b}/obstacles/spheres"]["Ellipsoids3D:centers"][-1]
        assert np.allclose(np.array(centers), scene.sphere_center.numpy(), atol=1e-6)
        balls = data[f"/ik/target_{b}/body/balls"]
        assert len(balls["Points3D:positions"][-1]) == 1 + 3 * 16
    assert clearance_colors(np.array([-0.001, 0.002, 0.02]), 0.004)[:, :3].tolist() == [
        [220, 30, 30], [255, 150, 0], [40, 190, 60]]


def test_restarts_lie_near_a_solution_of_the_same_target_inside_the_limits():
    from dacr_learn.ik.collision import RESTART_SPREAD
    model = ConstantCurvature(SPEC)
    gen = torch.Generator().manual_seed(3)
    x = model.limits.sample(6, gen)
    uniform = model.limits.sample(400, gen)
    solved = torch.full((400, 3), -1, dtype=torch.long)
    solved[:200, 1] = 4                                              # the first 200 starts' target has row 4 solved
    solved[100:200, 2] = 5
    out = Avoidance(model, load_scene(SCENE_FILE), D).restarts(uniform, x, solved, gen)
    assert out.shape == uniform.shape and model.limits.inside(out).all()
    assert torch.equal(out[200:], uniform[200:])                    # no solution of their target: uniform
    moved = ~(out[:200] == uniform[:200]).all(-1)
    assert 0.6 < moved.double().mean() < 0.9                        # about RESTART_NEAR of them
    reach = RESTART_SPREAD * torch.linalg.vector_norm(model.limits.scale)
    near4 = torch.linalg.vector_norm(out[:200] - x[4], dim=-1) <= reach + 1e-12
    near5 = torch.linalg.vector_norm(out[:200] - x[5], dim=-1) <= reach + 1e-12
    assert (near4[:100] | ~moved[:100]).all()
    assert (near4[100:] | near5[100:] | ~moved[100:]).all() and (near5[100:] & moved[100:]).any()
    every = Avoidance(model, load_scene(SCENE_FILE), D).restarts(uniform, x, solved, gen, share=1.0)
    assert torch.equal(every[200:], uniform[200:]) and not (every[:200] == uniform[:200]).all(-1).any()
    assert (torch.linalg.vector_norm(every[:100] - x[4], dim=-1) <= reach + 1e-12).all()


def test_hinge_residuals_and_their_jacobian():
    """With ``hinge`` the residual's forward-difference Jacobian matches forward-mode autodiff of the same pair
    distances, and a start short of the clearance gets positive hinge rows."""
    model, scene = ConstantCurvature(SPEC), load_scene(SCENE_FILE)
    avoid = Avoidance(model, scene, 0.01, hinge=True)
    assert avoid.rows == 4 and Avoidance(model, scene, D).rows == 0
    x = model.limits.sample(300, torch.Generator().manual_seed(2))
    x = x[(avoid.clearance_of(x, 8) < 0.01) & (avoid.clearance_of(x, 8) > 0.0)][:5]
    r, jac, ok = avoid.residual(x)
    assert r.shape == (5, 4) and jac.shape == (5, 4, x.shape[1]) and (r[:, 0] > 0).all() and not ok.any()
    _, d, longest = avoid._evaluate(x, 8)
    pick = (0.01 + 0.1 * longest.unsqueeze(-1) - d).topk(4, dim=-1).indices
    auto = torch.func.jacfwd(lambda v: avoid._pair_distances(v, pick))(x)          # (5, 4, 5, D)
    auto = auto[torch.arange(5), :, torch.arange(5)]                                # (5, 4, D)
    active = (r > 0).unsqueeze(-1)
    scale = model.limits.scale
    assert ((jac * model.length + auto).abs() * scale <= 1e-5 * active.to(F64) + 1e-12 + ~active * 1e9).all()


def test_capsule_chain_samples_each_axis_and_bounds_the_capsules():
    """capsule_chain: per capsule ceil(length / spacing) chords (from the first row) of equal length along its axis,
    both ends included (NumPy linspace reference), the chords between capsules invalid; its chain_clearance to a
    sphere is a lower bound of the capsules' distance to it (closed form: the sphere centre projected on each
    axis), and within the chord sag (0) plus 1 mm of it."""
    from dacr_learn.scene import capsule_chain, chain_clearance, scene_from_dict
    gen = np.random.default_rng(3)
    b, c, spacing = 5, 4, 0.05
    a = gen.uniform(-0.2, 0.2, (b, c, 3))
    axis = gen.normal(size=(c, 3))
    length = np.array([0.01, 0.07, 0.13, 0.31])
    tip = a + (axis / np.linalg.norm(axis, axis=-1, keepdims=True) * length[:, None])[None]
    radius = np.array([0.01, 0.02, 0.03, 0.04])
    swept, point_radius = capsule_chain(torch.from_numpy(a), torch.from_numpy(tip), torch.from_numpy(radius), spacing)
    counts = [max(1, int(np.ceil(x / spacing))) for x in length]
    expected = np.concatenate([a[:, j, None] + np.linspace(0, 1, n + 1)[None, :, None] * (tip - a)[:, j, None]
                               for j, n in enumerate(counts)], 1)
    assert np.abs(swept.points.numpy() - expected).max() < 1e-15
    assert point_radius.tolist() == [r for r, n in zip(radius, counts, strict=True) for _ in range(n + 1)]
    valid = [v for n in counts for v in [True] * n + [False]][:-1]
    assert swept.valid.tolist() == valid and (swept.sag == 0).all()
    assert swept.radius[swept.valid].tolist() == [r for r, n in zip(radius, counts, strict=True) for _ in range(n)]
    centre = np.array([0.05, -0.02, 0.1])
    scene = scene_from_dict({"obstacles": [{"type": "sphere", "center": centre.tolist(), "radius": 0.02}]})
    u = np.clip(np.einsum("bck,ck->bc", centre - a, tip[0] - a[0]) / (length ** 2), 0, 1)
    exact = (np.linalg.norm(centre - (a + u[..., None] * (tip - a)), axis=-1) - 0.02 - radius).min(-1)
    bound = chain_clearance(scene, swept).numpy()
    assert (bound <= exact + 1e-12).all() and (exact - bound).max() < 1e-3


def test_skipped_body_to_link_pairs_leave_the_clearance_unchanged():
    """The robot on the Panda at the port: the independent check skips the body-to-link distances of (row, link)
    pairs whose link is farther from the body's base than the body's reach plus an upper bound of the result; its
    value equals the unfiltered one (every body point to every far link, one swept_clearance over obstacles and
    links) to 1e-12, on configurations near the arm's home and uniform ones, with pairs both kept and skipped."""
    from dacr_learn.ik.collision import LINK_SPACING
    from dacr_learn.scene import capsule_chain, join, swept_body, swept_clearance
    from dacr_learn.scene.shapes import capsule_distance
    arm = load_arm(ROOT / "configs" / "arms" / "panda.urdf", "panda_link8")
    whole = Composite(arm, torch.from_numpy(np.load(ROOT / "configs" / "arms" / "panda_mount.npy")), SPEC)
    scene = load_scene(ROOT / "configs" / "scenes" / "port_panda.yaml")
    gen = torch.Generator().manual_seed(5)
    x = whole.limits.sample(300, gen)
    x[:200, :7] = whole.home + 0.15 * (2 * torch.rand(200, 7, generator=gen, dtype=F64) - 1)
    got = Avoidance(whole, scene, 0.005).clearance_of(x)
    body, (a, b, r, near) = whole.body(x, 8), whole.links(x)
    chain, _ = capsule_chain(a, b, r, LINK_SPACING)
    a, b, r = a[:, ~near], b[:, ~near], r[~near]
    swept = join(swept_body(body), chain)
    o, p = scene.num_obstacles, body.points.shape[1]
    d_self = torch.full((x.shape[0], swept.points.shape[1], r.numel()), float("inf"), dtype=F64)
    d_self[:, :p] = capsule_distance(body.points.unsqueeze(2), a.unsqueeze(1), b.unsqueeze(1), r, grad=False)[0]

    def pair(rows, points, field):
        d0, g0 = scene.pair_distances(points, field.clamp_max(o - 1))
        link = (field - o).clamp_min(0)
        d1, g1 = capsule_distance(points, a[rows, link], b[rows, link], r[link])
        return torch.where(field < o, d0, d1), torch.where((field < o).unsqueeze(-1), g0, g1)

    convex = torch.cat([scene.convex, torch.ones(r.numel(), dtype=torch.bool)])
    ref = swept_clearance(swept, torch.cat([scene.distances(swept.points)[0], d_self], -1), pair, convex)
    assert got.shape == ref.shape and (got - ref).abs().max() <= 1e-12
    to_links = (d_self[:, :p] - body.radius.unsqueeze(-1)).amin(1)                # (B, C) body to each far link
    to_scene = (scene.distances(body.points)[0] - body.radius.unsqueeze(-1)).amin((1, 2))
    assert (to_links.amin(-1) < to_scene).sum() >= 10                             # links hold the minimum in rows
    assert ((to_links - to_scene.unsqueeze(-1)) > 0.3).float().mean() > 0.3       # and many pairs are far apart
