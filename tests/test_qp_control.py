"""Constrained QP control (dacr_learn.deploy.qp_control, dacr_learn.arm.qp_control): the step is the damped
least-squares step when no constraint is active (against ResolvedRateController / WholeBodyController and a NumPy
formula), meets every constraint on random seeded states (limits, bend disks, joint speeds, dampers, the port,
URDF velocities; checked with independent Jacobians), relaxes an unmeetable damper instead of failing; the body's
closed-form Jacobian (robot alone and on the arm) and the scene's clearance rows against central differences and
NumPy distances; DAQP directly and through qpsolvers agree; the example's QP runs have no collision and no limit
violation by an independent check (classic arcs, NumPy URDF chain, NumPy distances from the scene file), and bad
configuration is a clear ValueError."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from arm_reference import UrdfArm, robot_check
from conftest import ROOT, TDCR3, load_example, reference_backbone, reference_joint_vector, spec_by_name
from scipy.spatial.transform import Rotation

from dacr_learn.arm import Composite, load_arm
from dacr_learn.arm.control import Port, WholeBodyConfig, WholeBodyController
from dacr_learn.arm.qp_control import WholeBodyQPController
from dacr_learn.deploy.control import ControllerConfig, ResolvedRateController, analytic_jacobian
from dacr_learn.deploy.export import SMALL_MATMULS
from dacr_learn.deploy.qp_clearance import cc_body_and_jacobian
from dacr_learn.deploy.qp_control import QPConfig, QPController, Sensing, disk_rows, solve_program
from dacr_learn.deploy.qp_export import ExportedStep, step_program
from dacr_learn.ik import ConstantCurvature
from dacr_learn.ik.adapters import SolverModel
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec
from dacr_learn.scene import load_scene

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
TYPE3 = RobotSpec.coerce(ROOT / "configs" / "robots" / "type3.yaml")
PANDA = ROOT / "configs" / "arms" / "panda.urdf"
READY = torch.tensor([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.785], dtype=F64)
TOL = 1e-9                                   # the solver's primal tolerance is ~1e-12 on these scaled steps


def interior(model, n: int, seed: int, frac: float = 0.4) -> torch.Tensor:
    """States (n, D) a fraction ``frac`` of the way from rest towards uniform admissible samples."""
    x = model.limits.sample(n, torch.Generator().manual_seed(seed))
    return model.rest + frac * (x - model.rest)


class LinearClearance:
    """A distance provider with fixed d (M,) [m] and ∂d/∂x (M, D) (the program sees only these numbers)."""

    def __init__(self, d: np.ndarray, jac: np.ndarray):
        self.d, self.jac = torch.from_numpy(d), torch.from_numpy(jac)

    def __call__(self, x: torch.Tensor):
        return self.d.expand(len(x), -1), self.jac.expand(len(x), -1, -1)


def test_disk_polygon_is_inscribed_with_a_vertex_on_the_current_direction():
    rng = np.random.default_rng(0)
    for sides in (3, 8, 13):
        for _ in range(20):
            r = rng.uniform(0.001, 0.02)
            y = r * rng.uniform(0, 1) * np.array([math.cos(a := rng.uniform(-4, 4)), math.sin(a)])
            normals, room = (v[0].numpy() for v in disk_rows(torch.from_numpy(y[None]), torch.tensor([r], dtype=F64),
                                                              sides))
            assert (room >= 0).all()                                                 # the current point is inside
            vertices = r * np.stack([np.cos(a + 2 * np.pi * np.arange(sides) / sides),
                                     np.sin(a + 2 * np.pi * np.arange(sides) / sides)], -1)
            slack = r * math.cos(math.pi / sides) - vertices @ normals.T                # (vertex, edge)
            assert slack.min() >= -1e-12 * r and (np.abs(slack) <= 1e-12 * r).sum(-1).tolist() == [2] * sides


@pytest.mark.parametrize("pose", [False, True])
def test_without_an_active_constraint_the_step_is_the_damped_least_squares_step(pose):
    model = ConstantCurvature(TDCR3)
    x = interior(model, 4, seed=1)
    goal = model.limits.project(x + 0.05 * model.limits.scale * torch.randn(x.shape, generator=torch.Generator()
                                                                              .manual_seed(2), dtype=F64))
    position, rotation, _ = model.tip_and_jacobian(goal)
    target = torch.eye(4, dtype=F64).repeat(4, 1, 1)
    target[:, :3, :3], target[:, :3, 3] = rotation, position
    cfg = QPConfig(gain=0.7, damping=2e-3, max_step=10.0)
    qp = QPController(model, cfg)
    got = qp.step_variables(x, target if pose else position)
    assert qp.status == ["ok"] * 4 and qp.active == [0] * 4
    if not pose:                                                     # today's controller, with its own Jacobian
        rrc = ResolvedRateController(TDCR3, analytic_jacobian(TDCR3), ControllerConfig(0.7, 2e-3, max_step=10.0))
        assert torch.allclose(model.variables(rrc.step(model.joints(x), position)), got, atol=1e-12, rtol=0)
        return
    p, r, jac = (t.numpy() for t in model.tip_and_jacobian(x))                      # the formula, in NumPy
    w = TDCR3.total_length
    for b in range(4):
        rotvec = Rotation.from_matrix(target[b, :3, :3].numpy() @ r[b].T).as_rotvec()
        e = 0.7 * np.concatenate([position[b].numpy() - p[b], w * rotvec])
        js = np.concatenate([jac[b, :3], w * jac[b, 3:]]) * qp.scale
        dz = js.T @ np.linalg.solve(js @ js.T + 2e-3**2 * np.eye(6), e)
        assert np.allclose(got[b].numpy(), x[b].numpy() + qp.scale * dz, atol=1e-12, rtol=0)


def assert_program_solution_meets_every_row(qp: QPController, x: torch.Tensor, target: torch.Tensor,
                                            joints_of) -> dict[str, int]:
    """Solve each sample's program and check the raw step x + s·z (before the final projection) against the
    limits, the bend disks, the step bound, the joint speeds (Jacobian by autograd of ``joints_of``) and the
    damper rows (from the provider's own numbers). Returns how many joint-speed and damper rows were tight."""
    cfg, lim = qp.config, qp.limits
    tight = {"joint_step": 0, "damper": 0}
    sensed = qp.sense(x)
    jac, err = qp.task(sensed, target, None)
    for b, program in enumerate(qp.programs(qp.program_rows(x, sensed, jac, err))):
        xb = x[b].numpy()
        z, status = solve_program(program, cfg.solver)
        assert status == "ok"
        step = qp.scale * z
        new = torch.from_numpy(xb + step)
        assert float(lim.violation(new)) <= TOL
        assert np.abs(z).max() <= cfg.max_step * (1 + TOL)
        if cfg.joint_step is not None:
            rate = torch.func.jacrev(joints_of)(x[b]).numpy()                       # ∂q/∂x, not DecoderJacobian
            assert np.abs(rate @ step).max() <= cfg.joint_step * (1 + 1e-7)
            tight["joint_step"] += int((np.abs(rate @ step) >= cfg.joint_step * (1 - 1e-6)).sum())
        if sensed.distance is not None:
            d, jd = sensed.distance[b].numpy(), sensed.distance_jacobian[b].numpy()
            near = d < cfg.influence
            bound = -cfg.damper_gain * (d - cfg.safety) / (cfg.influence - cfg.safety)
            assert (jd[near] @ step >= bound[near] - TOL * cfg.influence).all()
            tight["damper"] += int((jd[near] @ step <= bound[near] + 1e-6 * cfg.damper_gain).sum())
    moved = qp.step_variables(x, target)
    assert bool(lim.inside(moved, tol=1e-12).all())
    return tight


@pytest.mark.parametrize("spec", [TDCR3, TYPE3], ids=["tdcr3", "type3_twisting"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_constraint_holds_on_random_states(spec, seed):
    model = ConstantCurvature(spec)
    gen = torch.Generator().manual_seed(seed)
    x = model.limits.sample(6, gen)
    x[:3] = model.limits.project(x[:3] + 10 * model.limits.scale * (torch.rand(x[:3].shape, generator=gen,
                                                                                dtype=F64) - 0.5))   # on bounds
    target = model.tip_and_jacobian(model.limits.sample(6, gen))[0]                        # far: steps saturate
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.0021, 0.008, size=8)                                      # near d_s: dampers bite
    jac = rng.normal(size=(8, model.limits.num_variables))
    cfg = QPConfig(max_step=0.08, joint_step=5e-4, safety=0.002, influence=0.02, damper_gain=0.004)
    qp = QPController(model, cfg, LinearClearance(d, jac))
    tight = assert_program_solution_meets_every_row(qp, x, target, lambda v: model.joints(v[None])[0])
    assert tight["joint_step"] > 0 and tight["damper"] > 0                   # the rows were tested, not idle


def test_a_clearance_below_safety_that_cannot_be_restored_is_relaxed_to_not_coming_closer():
    model = ConstantCurvature(TDCR3)
    x = model.rest.clone()[None]
    beta = model.limits.names.index("segments[0].beta")
    x[0, beta] = model.limits.upper[beta]                                      # moving away needs β₀ to grow
    jac = np.zeros((1, model.limits.num_variables))
    jac[0, beta] = 1.0
    qp = QPController(model, QPConfig(), LinearClearance(np.array([0.001]), jac))
    target = model.tip_and_jacobian(x)[0] + torch.tensor([0.0, 0.0, 0.01], dtype=F64)   # pulls β up too
    moved = qp.step_variables(x, target)
    assert qp.status == ["relaxed"] and abs(float(moved[0, beta] - x[0, beta])) <= 1e-12 * float(qp.scale[beta])


SCENE = {"obstacles": [{"type": "sphere", "center": [0.05, 0.01, 0.2], "radius": 0.02},
                       {"type": "capsule", "a": [-0.06, -0.05, 0.05], "b": [-0.02, 0.06, 0.15], "radius": 0.01},
                       {"type": "box", "center": [0.02, -0.07, 0.12], "half_extents": [0.01, 0.02, 0.03],
                        "rpy": [0.3, -0.2, 0.5]}]}


def central_differences(fn, x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """∂fn/∂x (..., D) of fn: (D,) → (...) by central differences with steps (D,) (error O(step²))."""
    cols = [(fn(x + step[i] * e) - fn(x - step[i] * e)) / (2 * step[i]) for i, e in enumerate(torch.eye(len(x),
                                                                                                    dtype=F64))]
    return torch.stack(cols, dim=-1)


@pytest.mark.parametrize("name", ["tdcr_3seg_coupled", "type3", "hetero_4seg_types"])
def test_the_body_jacobian_in_closed_form_matches_central_differences(name):
    model = ConstantCurvature(spec_by_name(name))
    x = interior(model, 2, seed=7, frac=0.9)
    tip, body, jac = cc_body_and_jacobian(model, x, 5)
    ref_body = model.body(x, 5)
    assert torch.allclose(body.points, ref_body.points, atol=1e-15, rtol=0)
    assert torch.equal(body.radius, ref_body.radius) and torch.equal(body.arc_length, ref_body.arc_length)
    for got, ref in zip(tip, model.tip_and_jacobian(x), strict=True):                      # the tip is the last point
        assert torch.allclose(got, ref, atol=1e-14, rtol=0)
    step = 1e-6 * model.limits.scale
    for b in range(2):
        fd = central_differences(lambda v: model.body(v[None], 5).points[0], x[b], step)
        assert (jac[b] - fd).abs().max() <= 1e-7 * fd.abs().max()


def test_clearance_rows_are_the_scene_distances_and_their_gradients_along_the_body():
    model = ConstantCurvature(TDCR3)
    qp = QPController(model, QPConfig(), scene=SCENE, points_per_segment=4)
    x = interior(model, 2, seed=8, frac=0.9)
    s = qp.sense(x)
    scene = load_scene(SCENE)
    assert s.distance.shape == (2, 13 * 3) and s.distance_jacobian.shape == (2, 13 * 3, 9)

    def clearance(v: torch.Tensor) -> torch.Tensor:
        body = model.body(v[None], 4)
        return (scene.distances(body.points[0])[0] - body.radius[:, None]).flatten()
    for b in range(2):
        points = reference_backbone(TDCR3, model.features(x[b:b + 1])[0].numpy(), 4)          # classic arcs
        assert np.allclose(s.distance[b].numpy(), numpy_distances(points, SCENE).ravel() - 0.008, atol=1e-12)
        fd = central_differences(clearance, x[b], 1e-6 * model.limits.scale)
        assert (s.distance_jacobian[b] - fd).abs().max() <= 1e-6 * fd.abs().max()


def test_the_whole_body_jacobian_composes_the_arm_and_the_robot(arm_model):
    model = arm_model
    x = torch.cat([READY, model.robot.rest])[None].repeat(2, 1)
    x[:, model.num_arm:] = interior(model.robot, 2, seed=9, frac=0.8)
    x[1, :model.num_arm] += 0.1
    qp = WholeBodyQPController(model, scene=SCENE, points_per_segment=4)
    body, jac = qp.body_of(x, model.kinematics(x))
    assert torch.allclose(body.points, model.body(x, 4).points, atol=1e-15, rtol=0)
    step = 1e-6 * model.limits.scale
    for b in range(2):
        fd = central_differences(lambda v: model.body(v[None], 4).points[0], x[b], step)
        assert (jac[b] - fd).abs().max() <= 1e-7 * fd.abs().max()


def test_direct_daqp_and_qpsolvers_give_the_same_step():
    model = ConstantCurvature(TDCR3)
    x = interior(model, 4, seed=10, frac=0.9)
    target = model.tip_and_jacobian(model.limits.sample(4, torch.Generator().manual_seed(11)))[0]
    steps = [QPController(model, QPConfig(max_step=0.08, joint_step=5e-4, direct=direct), scene=SCENE)
             .step_variables(x, target) for direct in (True, False)]
    assert torch.allclose(steps[0], steps[1], atol=1e-9, rtol=0)


def numpy_distances(points: np.ndarray, scene: dict) -> np.ndarray:
    """Signed distances (P, O) [m] of points (P, 3) to a scene dict's spheres and boxes (and capsules), in NumPy
    from the file's own numbers (URDF rpy: R = Rz·Ry·Rx)."""
    cols = []
    for o in scene["obstacles"]:
        if o["type"] == "sphere":
            cols.append(np.linalg.norm(points - o["center"], axis=-1) - o["radius"])
        elif o["type"] == "capsule":
            a, b = np.asarray(o["a"]), np.asarray(o["b"])
            t = np.clip((points - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
            cols.append(np.linalg.norm(points - a - t[:, None] * (b - a), axis=-1) - o["radius"])
        else:
            rot = Rotation.from_euler("xyz", o.get("rpy", [0, 0, 0])).as_matrix()
            q = np.abs((points - o["center"]) @ rot) - o["half_extents"]
            cols.append(np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0))
    return np.stack(cols, -1)


def independent_clearance(spec, q: np.ndarray, scene_file, base: np.ndarray | None = None) -> float:
    """The smallest clearance [m] of one joint vector's body (the encoder's features, accepted only when the
    independent joint geometry reproduces q; classic arcs at 64 points per segment, moved by ``base`` (4, 4)) to
    the scene file's obstacles, read with a YAML parser."""
    f = ClarkeEncoder(spec).to(F64)(torch.from_numpy(np.ascontiguousarray(q))).numpy()
    assert np.abs(reference_joint_vector(spec, f) - q).max() < 1e-9
    points = reference_backbone(spec, f, 64)
    if base is not None:
        points = points @ base[:3, :3].T + base[:3, 3]
    obstacles = yaml.safe_load(Path(scene_file).read_text())
    return float(numpy_distances(points, obstacles).min() - spec.segments[0].body_radius)


def test_the_example_robot_scene_has_no_collision_with_qp_and_one_without(tmp_path):
    example = load_example("qp_reach_behind_obstacle")
    summary = example.main(["--scene", "robot", "--steps", "80", "--hold", "20", "--points", "8",
                            "--out", str(tmp_path)])
    qp, rrc = summary["robot"]["results"]["qp"], summary["robot"]["results"]["resolved_rate"]
    assert qp["collisions"] == 0 and qp["limit_violations"] == 0 and qp["min_clearance_mm"] > 0
    assert rrc["collisions"] > 0 and rrc["limit_violations"] == 0
    assert qp["final_error_mm"] < 1.0
    paths = np.load(tmp_path / "paths.npz")
    clear = [independent_clearance(TDCR3, q, example.SCENES["robot"]) for q in paths["robot/qp"]]
    assert min(clear) > 0 and abs(1e3 * min(clear) - qp["min_clearance_mm"]) < 0.05
    assert all(robot_check(TDCR3, q)[1] for q in paths["robot/qp"])
    assert min(independent_clearance(TDCR3, q, example.SCENES["robot"]) for q in paths["robot/resolved_rate"]) < 0


@pytest.fixture(scope="module")
def arm_model():
    return Composite(load_arm(PANDA, "panda_link8"), torch.from_numpy(np.load(ROOT / "configs" / "arms" /
                                                                             "panda_mount.npy")), TDCR3)


def test_whole_body_without_an_active_constraint_is_the_whole_body_controller(arm_model):
    model = arm_model
    x = torch.cat([READY, model.robot.rest])[None].repeat(2, 1)
    x[:, model.num_arm:] = interior(model.robot, 2, seed=4, frac=0.3)
    base = model.base_pose(x[:, :model.num_arm])[0, :3, 3]
    port = Port(tuple(base.tolist()), 0.005)
    tip = model.pose_of_variables(x)
    target = tip.clone()
    target[:, :3, 3] += torch.tensor([[0.002, -0.001, 0.001], [-0.001, 0.0, 0.002]], dtype=F64)
    ref = WholeBodyController(model, WholeBodyConfig(gain=0.5, damping=1e-3, max_step=10.0), port)
    qp = WholeBodyQPController(model, QPConfig(gain=0.5, damping=1e-3, max_step=10.0), port)
    got = qp.step_variables(x, target)
    assert qp.status == ["ok", "ok"] and qp.active == [0, 0]
    assert torch.allclose(got, ref.step_variables(x, target), atol=1e-11, rtol=0)


def test_whole_body_keeps_the_port_the_velocity_limits_and_the_dampers(arm_model):
    model = arm_model
    n = model.num_arm
    gen = torch.Generator().manual_seed(5)
    x = torch.cat([READY, model.robot.rest])[None].repeat(3, 1)
    port = Port(tuple(model.base_pose(x[:1, :n])[0, :3, 3].tolist()), 0.005)
    target = model.pose_of_variables(model.limits.project(x + 0.3 * model.limits.scale * (
        torch.rand(x.shape, generator=gen, dtype=F64) - 0.5)))
    rng = np.random.default_rng(5)
    clearance = LinearClearance(rng.uniform(0.0021, 0.008, size=6), rng.normal(size=(6, n + 9)))
    dt = 0.01
    qp = WholeBodyQPController(model, QPConfig(max_step=0.1, joint_step=5e-4, damper_gain=0.003), port,
                               clearance, dt=dt)
    tight = assert_program_solution_meets_every_row(qp, x, target, lambda v: model.joints(v[None])[0, n:])
    assert tight["damper"] > 0
    velocity = torch.tensor(model.arm.chain.get_joint_velocity_limits()[1], dtype=F64)
    for _ in range(15):
        new = qp.step_variables(x, target)
        assert bool(((new[:, :n] - x[:, :n]).abs() <= velocity * dt * (1 + 1e-9)).all())
        x = new
        offset = model.base_pose(x[:, :n])[:, :3, 3] - torch.tensor(port.centre, dtype=F64)
        assert float(offset.norm(dim=-1).max()) <= port.radius


def test_bad_configuration_is_a_clear_value_error(arm_model):
    for kwargs, word in (({"gain": 0.0}, "gain"), ({"damping": 0.0}, "damping"), ({"max_step": -1.0}, "max_step"),
                         ({"safety": 0.03, "influence": 0.02}, "influence"), ({"disk_sides": 2}, "disk_sides"),
                         ({"damper_gain": 0.0}, "damper_gain"), ({"joint_step": 0.0}, "joint_step"),
                         ({"rotation_length": -1.0}, "rotation_length"), ({"solver": "nope"}, "solver")):
        with pytest.raises(ValueError, match=word):
            QPConfig(**kwargs)
    model = ConstantCurvature(TDCR3)
    qp = QPController(model)
    with pytest.raises(ValueError, match="x: expected"):
        qp.step_variables(torch.zeros(1, 3, dtype=F64), torch.zeros(1, 3, dtype=F64))
    with pytest.raises(ValueError, match="feedforward"):
        qp.step_variables(model.rest[None], torch.zeros(1, 3, dtype=F64), torch.zeros(1, 6, dtype=F64))
    with pytest.raises(ValueError, match="Composite"):
        WholeBodyQPController(model)
    with pytest.raises(ValueError, match="dt"):
        WholeBodyQPController(arm_model, dt=0.0)
    with pytest.raises(ValueError, match="port_weight"):
        WholeBodyQPController(arm_model, port_weight=0.0)

    with pytest.raises(ValueError, match="scene, distances"):
        QPController(model, scene=SCENE, distances=LinearClearance(np.zeros(1), np.zeros((1, 9))))
    with pytest.raises(ValueError, match="scene: expected"):
        QPController(model, scene=3.0)
    with pytest.raises(ValueError, match="has no body"):
        QPController(type("TipOnly", (ConstantCurvature,), {"body": SolverModel.body})(TDCR3), scene=SCENE)
    with pytest.raises(ValueError, match="points_per_segment"):
        QPController(model, scene=SCENE, points_per_segment=0)

    servo = ConstantCurvature(TDCR3)
    servo.space = None                                                # variables that are not Clarke features
    with pytest.raises(ValueError, match="joint_step"):
        QPController(servo, QPConfig(joint_step=1e-3))


@pytest.mark.slow
def test_the_example_arm_scene_has_no_collision_with_qp_and_keeps_the_port(tmp_path):
    example = load_example("qp_reach_behind_obstacle")
    summary = example.main(["--scene", "arm", "--steps", "48", "--hold", "30", "--points", "8",
                            "--out", str(tmp_path)])
    res = summary["arm"]["results"]
    qp = res["whole_body_qp"]
    assert qp["collisions"] == 0 and qp["limit_violations"] == 0 and qp["port_max_mm"] <= 5.0
    assert res["whole_body"]["collisions"] > 0 and res["whole_body"]["limit_violations"] == 0
    arm, mount = UrdfArm(PANDA, "panda_link8"), np.load(ROOT / "configs" / "arms" / "panda_mount.npy")
    n = len(arm.names)
    for q in np.load(tmp_path / "paths.npz")["arm/whole_body_qp"]:                # NumPy URDF chain, classic arcs
        assert arm.inside(q[:n]) and robot_check(TDCR3, q[n:])[1]
        assert independent_clearance(TDCR3, q[n:], example.SCENES["arm"], arm.tip_pose(q[:n]) @ mount) > 0


def test_sensing_as_a_module_drives_the_same_step():
    model = ConstantCurvature(TDCR3)
    x = interior(model, 2, seed=6)
    clearance = LinearClearance(np.array([0.004, 0.03]), np.ones((2, model.limits.num_variables)))
    qp = QPController(model, QPConfig(), clearance)
    fields = Sensing(qp)(x)
    assert len(fields) == 7 and fields[5].shape == (2, 0) and fields[6].shape == (2, 0)    # no base: empty
    fast = QPController(model, QPConfig(), sense=Sensing(qp))
    target = model.tip_and_jacobian(model.rest[None].expand(2, -1))[0]
    assert torch.equal(fast.step_variables(x, target), qp.step_variables(x, target))


def test_the_program_holds_the_dampers_within_the_influence_distance_only():
    model = ConstantCurvature(TDCR3)
    x = interior(model, 2, seed=12)
    d = np.array([0.003, 0.025, 0.0199, 0.02, 0.01])                           # d_i = 0.02: rows 0, 2, 4
    jac = np.random.default_rng(12).normal(size=(5, model.limits.num_variables))
    cfg = QPConfig(safety=0.002, influence=0.02, damper_gain=0.003, joint_step=1e-3)
    qp = QPController(model, cfg, LinearClearance(d, jac))
    s = qp.sense(x)
    rows = qp.program_rows(x, s, *qp.task(s, model.tip_and_jacobian(x)[0], None))
    fixed = 3 * cfg.disk_sides + 2 * TDCR3.num_joints
    for p in qp.programs(rows):
        assert p.G.shape == (fixed + 3, 9) and p.damper.tolist() == [False] * fixed + [True] * 3
        near = [0, 2, 4]
        assert np.allclose(p.G[fixed:], -jac[near] * qp.scale, atol=1e-15, rtol=0)
        assert np.allclose(p.h[fixed:], 0.003 * (d[near] - 0.002) / 0.018, atol=1e-15, rtol=0)
        assert np.allclose(p.h[:fixed][-2 * TDCR3.num_joints:], 1e-3, atol=0, rtol=0)


@pytest.mark.slow
def test_the_step_program_exported_drives_the_same_step():
    model = ConstantCurvature(TDCR3)
    qp = QPController(model, QPConfig(joint_step=1e-3), scene=SCENE, points_per_segment=4)
    x = interior(model, 1, seed=13, frac=0.9)
    q = model.joints(x)
    target = model.tip_and_jacobian(x)[0] + torch.tensor([[0.01, -0.01, 0.0]], dtype=F64)
    ff = torch.tensor([[0.001, 0.0, 0.0]], dtype=F64)
    exported = step_program(qp, q, target, ff)
    ops = {str(n.target) for n in exported.graph.nodes if n.op == "call_function"}
    assert not ops & {"aten.mm.default", "aten.bmm.default", "aten.addmm.default", "aten.matmul.default"}
    program = exported.module()
    assert int((program(q, target, ff)[-1] == 2).sum()) > 0                             # dampers in the program
    fast = ExportedStep.__new__(ExportedStep)                                   # the package's loader, unbuilt
    fast.controller, fast.shapes = qp, ((1, TDCR3.num_joints), (1, 3), (1, 3))
    fast.loader = type("Loader", (), {"run": staticmethod(lambda args: list(program(*args)))})()
    for feed in (ff, None):
        expected = qp.step(q, target, feed)
        status = list(qp.status)
        assert torch.allclose(fast.step(q, target, feed), expected, atol=1e-12, rtol=0) and qp.status == status
    with pytest.raises(ValueError, match="exported shapes"):
        fast.step(q.repeat(2, 1), target.repeat(2, 1))


def test_the_matrix_product_decompositions_are_the_products():
    gen = torch.Generator().manual_seed(14)
    for shapes in (((3, 4), (4, 5)), ((2, 3, 4), (2, 4, 1)), ((2, 1, 3, 4), (5, 4, 2)), ((4,), (2, 4, 3)),
                   ((2, 3, 4), (4,)), ((4,), (4,))):
        a, b = (torch.randn(sh, generator=gen, dtype=F64) for sh in shapes)
        for op in ("matmul", "mm", "bmm"):
            if op == "matmul" or (op == "mm" and a.dim() == b.dim() == 2) or (op == "bmm" and a.dim() == b.dim() == 3):
                got = SMALL_MATMULS[getattr(torch.ops.aten, op).default](a, b)
                assert torch.allclose(got, a @ b, atol=1e-14, rtol=0)
    c, a, b = (torch.randn(sh, generator=gen, dtype=F64) for sh in ((3, 5), (3, 4), (4, 5)))
    got = SMALL_MATMULS[torch.ops.aten.addmm.default](c, a, b, beta=0.5, alpha=2.0)
    assert torch.allclose(got, torch.addmm(c, a, b, beta=0.5, alpha=2.0), atol=1e-14, rtol=0)
