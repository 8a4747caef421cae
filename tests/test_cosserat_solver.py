"""Cosserat model, checks (c) and (d) and the solver's contracts: Newton's residual, the integrator's
order, global equilibrium, textbook cantilevers, gradients (gradcheck through the Newton solve),
batching, and failures that are reported instead of returned as garbage.

The solver checks are marked slow: `make test` runs them in its one-thread pass, beside the other tests; those
that compare at rounding level (tests/reduction_order.py) run again in its two-thread pass, with
OMP_WAIT_POLICY=PASSIVE: OpenMP's actively waiting worker made them 10-20x slower on a loaded machine
(test_batched_equals_per_sample: 1.9 s with PASSIVE, 25 s without)."""
from __future__ import annotations

import math

import pytest
import torch
from conftest import ROOT

from dacr_learn.cosserat import ConvergenceError, solve_statics
from dacr_learn.robot import RobotSpec

F64 = torch.float64
EPS = torch.finfo(F64).eps
COUPLED = ROOT / "configs" / "robots" / "tdcr_3seg_cosserat.yaml"


def loaded_problem():
    """Three-segment coupled robot, tensions in all segments, gravity, a tip and a mid-arc wrench."""
    spec = RobotSpec.from_yaml(COUPLED)
    tension = torch.tensor([[2.0, 0, 0.5, 0, 0, 1.5, 0, 0.2, 0.4, 0, 2.0, 0],
                            [0, 1.0, 0, 0.3, 0.8, 0, 0, 0, 0, 0.6, 0, 1.2]], dtype=F64)
    loads = {"gravity": torch.tensor([0.0, -9.81, 0.0], dtype=F64),
             "tip_wrench": torch.tensor([0.05, 0.0, -0.02, 0.0, 0.001, 0.0], dtype=F64),
             "point_wrenches": [(0.145, torch.tensor([0.0, 0.03, 0.0, 0.0005, 0.0, 0.0], dtype=F64))]}
    return spec, tension, loads


@pytest.mark.slow
def test_newton_residual_reaches_1e_10_and_rounding_level():
    spec, tension, loads = loaded_problem()
    for tol in (1e-10, 1e-13):
        sol = solve_statics(spec, tension, **loads, steps_per_segment=16, tol=tol)
        assert bool(sol.converged.all()) and float(sol.residual.max()) <= tol
        assert int(sol.iterations.max()) <= 12                        # Broyden: 9 steps here for 1e-13
        assert sol.tip[..., :2, 3].norm(dim=-1).min() > 0.15 * spec.total_length   # a large deflection


@pytest.mark.parametrize("case", ["cc_arc", pytest.param("loaded", marks=pytest.mark.slow)])
def test_integrator_error_falls_at_fourth_order(case):
    if case == "cc_arc":       # exact reference: the closed-form arc of one tendon (see test_cosserat_cc.py)
        spec = RobotSpec.from_dict({"segments": [{"type": "I", "length": 0.12, "radius": 0.006, "joints": 4}],
                                    "mechanics": {"youngs_modulus": 6.0e10, "poisson_ratio": 0.33,
                                                  "outer_radius": 0.0005}})
        tension, loads = torch.tensor([6.0, 0.0, 0.0, 0.0], dtype=F64), {}
        ei, ea = 6.0e10 * math.pi * 0.0005**4 / 4, 6.0e10 * math.pi * 0.0005**2
        kappa, beta = 6.0 * 0.006 / ei, 0.12 * (1 - 6.0 / ea)
        phi = kappa * 0.12
        exact = torch.tensor([beta * (1 - math.cos(phi)) / phi, 0.0, beta * math.sin(phi) / phi], dtype=F64)
    else:                      # self-convergence against 64 steps per segment (its own error ≈ 3e-11 l, 0.4 % of 16's)
        spec, tension, loads = loaded_problem()
        exact = solve_statics(spec, tension, **loads, steps_per_segment=64, tol=1e-13).tip[..., :3, 3]
    errors = [float((solve_statics(spec, tension, **loads, steps_per_segment=n, tol=1e-13).tip[..., :3, 3]
                     - exact).norm(dim=-1).max()) for n in (4, 8, 16)]
    orders = [math.log2(a / b) for a, b in zip(errors, errors[1:], strict=False)]
    assert all(3.8 <= p <= 4.3 for p in orders), (errors, orders)      # measured 4.0-4.04
    assert errors[-1] <= 1e-6 * spec.total_length                     # measured 5.9e-7 / 8e-9 at 16 steps


@pytest.mark.slow
def test_whole_robot_is_in_equilibrium():
    """Independent of the shooting residual: the total (rod + tendon) wrench at the base equals the external
    loads carried there along the solved shape (tip and point wrenches, the weight by Simpson's rule)."""
    spec, tension, loads = loaded_problem()
    sol = solve_statics(spec, tension, **loads, steps_per_segment=32, tol=1e-13)
    mech = spec.mechanics
    weight = mech.density * math.pi * mech.outer_radius**2 * loads["gravity"]          # [N/m]
    offsets = torch.tensor([[r * math.cos(a), r * math.sin(a), 0.0] for s in spec.segments
                            for a, r in zip(s.joint_angles, s.joint_radii, strict=True)], dtype=F64)
    v, u = sol.stretch[:, 0], sol.curvature[:, 0]
    path = v.unsqueeze(1) + torch.linalg.cross(u.unsqueeze(1).expand(-1, 12, 3), offsets.expand(2, 12, 3))
    t = path / path.norm(dim=-1, keepdim=True)
    total_n = sol.base_wrench[:, :3] + (tension.unsqueeze(-1) * t).sum(1)
    total_m = sol.base_wrench[:, 3:] + (tension.unsqueeze(-1) * torch.linalg.cross(offsets.expand(2, 12, 3), t)).sum(1)
    pos = sol.frames[..., :3, 3]
    tip_f, tip_m = loads["tip_wrench"][:3], loads["tip_wrench"][3:]
    (s_mid, w_mid), = loads["point_wrenches"]
    p_mid = sol.at([s_mid])[:, 0, :3, 3]
    moment_density = torch.linalg.cross(pos, weight.expand_as(pos))                    # p × f_e (B, K, 3)
    h = sol.arc[1:] - sol.arc[:-1]                                                     # uniform per segment
    simpson = sum(((moment_density[:, i] + 4 * moment_density[:, i + 1] + moment_density[:, i + 2]) * h[i] / 3)
                  for i in range(0, len(h), 2))
    ext_n = tip_f + w_mid[:3] + weight * spec.total_length
    ext_m = (torch.linalg.cross(pos[:, -1], tip_f.expand(2, 3)) + tip_m
             + torch.linalg.cross(p_mid, w_mid[:3].expand(2, 3)) + w_mid[3:] + simpson)
    scale_n, scale_m = tension.sum(-1, keepdim=True), tension.sum(-1, keepdim=True) * 0.008
    assert ((total_n - ext_n).abs() / scale_n).max() <= 1e-10      # measured 2e-12
    assert ((total_m - ext_m).abs() / scale_m).max() <= 1e-9       # measured 5e-11 (Simpson, 32 steps)


def test_textbook_cantilevers_in_the_linear_range():
    """Weight q: δ(x) = q x² (6L² − 4Lx + x²)/(24 EI); tip force P: δ(x) = P x² (3L − x)/(6 EI) (Euler–Bernoulli)."""
    length, radius, e = 0.6, 0.0008, 2.0e11
    spec = RobotSpec.from_dict({"segments": [{"type": "0", "length": length, "radius": radius, "joints": 3}],
                                "mechanics": {"youngs_modulus": e, "poisson_ratio": 0.33, "outer_radius": radius,
                                              "density": 7870.0}})
    ei = e * math.pi * radius**4 / 4
    q = 7870.0 * math.pi * radius**2 * 0.0981                         # g/100 along −x: deflection ≈ 0.07 % L
    tip_force = 1e-4
    zero = torch.zeros(3, dtype=F64)
    for loads, deflection in (
            ({"gravity": torch.tensor([-0.0981, 0.0, 0.0], dtype=F64)},
             lambda x: q * x**2 * (6 * length**2 - 4 * length * x + x**2) / (24 * ei)),
            ({"tip_wrench": torch.tensor([-tip_force, 0, 0, 0, 0, 0], dtype=F64)},
             lambda x: tip_force * x**2 * (3 * length - x) / (6 * ei))):
        sol = solve_statics(spec, zero, **loads, steps_per_segment=32)
        x = sol.frames[..., :3, 3]
        ref = -deflection(sol.arc)
        assert (x[:, 0] - ref).abs().max() <= 1e-4 * ref.abs().max()    # geometric nonlinearity ~ slope² ≈ 1e-6
        assert x[:, 1].abs().max() <= 100 * EPS * length


@pytest.mark.slow
@pytest.mark.parametrize("straight", [False, True])
def test_gradcheck_tip_pose_through_the_newton_solve(straight):
    spec = RobotSpec.from_yaml(COUPLED)
    spec = RobotSpec.from_dict({**spec.to_dict(), "segments": spec.to_dict()["segments"][:2]})
    if straight:
        tension = torch.zeros(1, 8, dtype=F64, requires_grad=True)
        extra = ()
    else:
        tension = torch.tensor([[1.0, 0.2, 0, 0.5, 0.3, 0, 0.8, 0.1]], dtype=F64, requires_grad=True)
        extra = (torch.tensor([0.02, -0.05, 0.01, 0.001, 0.0, -0.0005], dtype=F64, requires_grad=True),
                 torch.tensor([0.3, -1.0, -9.81], dtype=F64, requires_grad=True))

    def tip(tension, *loads):
        kw = dict(zip(("tip_wrench", "gravity"), loads, strict=False))
        sol = solve_statics(spec, tension, **kw, steps_per_segment=4, tol=1e-13)
        return torch.cat([sol.tip[..., :3, :].flatten(-2), sol.tendon_lengths], -1)

    # fast mode: the Jacobian checked along random directions (vᵀJu by finite differences and by autograd), one
    # difference pair instead of one per input (17 here): 2 s instead of 21 s
    assert torch.autograd.gradcheck(tip, (tension, *extra), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


@pytest.mark.slow
def test_batched_equals_per_sample():
    spec, tension, loads = loaded_problem()
    tension = torch.stack([tension, tension.flip(-1) * 0.5, tension * 0.3])       # (3, 2, 12)
    sol = solve_statics(spec, tension, **loads, steps_per_segment=8, tol=1e-13)
    assert sol.frames.shape[:2] == (3, 2) and sol.tip.shape == (3, 2, 4, 4) and sol.tendon_lengths.shape == (3, 2, 12)
    for i in range(3):
        for j in range(2):
            one = solve_statics(spec, tension[i, j], **loads, steps_per_segment=8, tol=1e-13)
            assert torch.allclose(one.frames, sol.frames[i, j], rtol=0, atol=1e-11 * spec.total_length)


@pytest.mark.slow
def test_chunks_in_threads_equal_one_serial_solve():
    """Uneven chunks solved in two threads give the serial solve's samples in the input order, a failing
    sample flagged in its own chunk only; a solve carrying a gradient still gets one."""
    spec, tension, loads = loaded_problem()
    scales = torch.linspace(0.1, 1.0, 7, dtype=F64)
    batch = torch.cat([tension * s for s in scales])                                # (14, 12), all different
    batch[9, 0] = 1.0e5                                                             # inadmissible: flagged
    serial = solve_statics(spec, batch, **loads, steps_per_segment=4, tol=1e-13, on_failure="flag", workers=1)
    threaded = solve_statics(spec, batch, **loads, steps_per_segment=4, tol=1e-13, on_failure="flag",
                             chunk_size=3, workers=2)
    assert serial.converged.tolist() == threaded.converged.tolist() == [i != 9 for i in range(14)]
    ok = serial.converged
    assert torch.allclose(threaded.frames[ok], serial.frames[ok], rtol=0, atol=1e-11 * spec.total_length)
    assert torch.allclose(threaded.tendon_lengths[ok], serial.tendon_lengths[ok], rtol=0, atol=1e-13)
    assert torch.isnan(threaded.tip[9, :3]).all()
    tau = tension[:1].clone().requires_grad_(True)
    solve_statics(spec, tau, **loads, steps_per_segment=4, workers=2).tip[..., :3, 3].sum().backward()
    assert tau.grad is not None and torch.isfinite(tau.grad).all() and tau.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="workers"):
        solve_statics(spec, tension, workers=0)


@pytest.mark.slow
def test_failures_raise_or_are_flagged_with_nan():
    spec = RobotSpec.from_yaml(COUPLED)
    tension = torch.zeros(3, 12, dtype=F64)
    tension[1, 0] = 1.0e5                    # a tendon folded back: no admissible straight-routing shape
    tension[2, 0] = 3.0
    with pytest.raises(ConvergenceError, match="1 did not converge|inadmissible"):
        solve_statics(spec, tension)
    sol = solve_statics(spec, tension, on_failure="flag")
    assert sol.converged.tolist() == [True, False, True]
    assert torch.isnan(sol.frames[1, :, :3]).all() and torch.isnan(sol.tendon_lengths[1]).all()
    assert torch.isfinite(sol.frames[[0, 2]]).all()
    _, loaded, loads = loaded_problem()
    with pytest.raises(ConvergenceError, match="2 did not converge"):
        solve_statics(spec, loaded, **loads, max_iter=1)
    flagged = solve_statics(spec, loaded, **loads, max_iter=1, on_failure="flag")
    assert not flagged.converged.any() and torch.isnan(flagged.tip[..., :3, :]).all()
    assert (flagged.residual > 1e-10).all()


def test_newton_never_moves_to_a_worse_point_and_returns_what_fun_kept_at_its_x():
    """Newton's line search on r(x) = x·w(t)/t along the ray x = t·x0, with a Jacobian of the wrong sign so that
    every trial x0 − α·J⁻¹r = (1 + α)·x0 lies on the ray: w(1 + α) = 1 + α (uphill) except ‖r‖ × 0.99999 at α = 1/2
    (a decrease, but short of the Armijo factor). The line search must keep that trial, not the last and worst
    one (α = 2⁻⁹), and newton must return what ``fun`` kept at the x it returns (no side effect to rely on)."""
    from dacr_learn.cosserat.shooting import newton

    x0 = torch.tensor([[1.0, -2.0, 0.5, 0.3, 0.2, -0.1], [0.5, 0.1, 0.2, -0.3, 0.4, 0.1]], dtype=F64)

    def fun(x, idx):
        t = x[:, 0] / x0[idx, 0]
        w = torch.where((t - 1.5).abs() < 1e-3, torch.full_like(t, 0.99999), t)
        return x * (w / t).unsqueeze(-1), 7 * x          # kept: any per-row quantity of the point

    x, res, iters, kept = newton(fun, x0, 1e-12, 1, coarse=lambda x, idx: -x)
    assert torch.allclose(x, 1.5 * x0, rtol=1e-8, atol=0) and iters.tolist() == [1, 1]    # J: differences, 1e-9
    assert torch.allclose(res, 0.99999 * x0.abs().amax(-1), rtol=1e-8, atol=0)     # before: 1.002 × the start
    assert torch.equal(kept, 7 * x)
    # a coarse J of the wrong sign again, the true one J = I: a step that cannot move differences J on ``fun`` itself
    x, res, iters, _ = newton(lambda x, idx: (x.clone(), None), x0, 1e-12, 5, coarse=lambda x, idx: -x)
    assert bool((res <= 1e-12).all()) and iters.tolist() == [3, 3]       # 1 failed step, then 2 Newton steps
    # r(x) = x − x0 + x0·(1 + 1e6·‖x − x0‖²): uphill from x0 at every α ≥ 2⁻⁹ whatever J: stays put, then stops
    x, res, iters, kept = newton(
        lambda x, idx: (x - x0[idx] + x0[idx] * (1 + 1e6 * (x - x0[idx]).square().sum(-1, keepdim=True)), None),
        x0, 1e-12, 5)
    assert torch.equal(x, x0) and torch.equal(res, x0.abs().amax(-1)) and iters.tolist() == [1, 1] and kept is None


def test_node_frames_are_those_of_the_returned_base_wrench():
    """Without a gradient the frames come from Newton's own integrations (no extra pass): they must be those of the
    returned base wrench, as the gradient path's, which integrates its x once more (one Newton step from it)."""
    spec, tension, loads = loaded_problem()
    plain = solve_statics(spec, tension, **loads, steps_per_segment=4, tol=1e-12)
    again = solve_statics(spec, tension.clone().requires_grad_(True), **loads, steps_per_segment=4, tol=1e-12)
    wrench_scale = tension.sum(-1, keepdim=True) * torch.tensor([1.0] * 3 + [0.01] * 3, dtype=F64)   # [N], [N·m]
    assert float(((again.base_wrench.detach() - plain.base_wrench) / wrench_scale).abs().max()) <= 1e-10
    assert torch.allclose(again.frames.detach(), plain.frames, rtol=0, atol=1e-10 * spec.total_length)


def test_newtons_jacobian_grid_keeps_two_steps_per_segment_at_the_hardwares_four():
    """The hardware models solve with 4 RK4 steps per segment; Newton's Jacobian on a quarter of them, one step per
    segment, was off by up to 1.1 % from the fine grid's on these loaded samples (two steps: 0.07 %)."""
    from dacr_learn.cosserat.grid import arc_grid
    from dacr_learn.cosserat.rod import Section
    from dacr_learn.cosserat.shooting import Loads, integrate, residual, residual_and_jacobian, wrench_scale
    from dacr_learn.cosserat.statics import jacobian_grid
    from dacr_learn.cosserat.tendon import tendon_routing
    from dacr_learn.hardware.cosserat_model import STEPS_PER_SEGMENT

    spec = RobotSpec.from_yaml(COUPLED)
    g = torch.Generator().manual_seed(0)
    tension = 2.0 * torch.rand(64, 12, generator=g, dtype=F64) * (torch.rand(64, 12, generator=g) < 0.4)
    gravity = torch.tensor([0.0, -9.81, 0.0], dtype=F64)
    routing, section = tendon_routing(spec, "own"), Section.from_mechanics(spec.mechanics)
    fine = arc_grid(routing.ends.tolist(), STEPS_PER_SEGMENT)
    coarse = jacobian_grid(fine)
    assert coarse.steps == 2 and jacobian_grid(arc_grid(routing.ends.tolist(), 16)).steps == 4
    scale = wrench_scale(section, spec.total_length)
    loads = Loads((section.mass_per_length * gravity).expand(64, 3), [])
    z = solve_statics(spec, tension, gravity=gravity, steps_per_segment=STEPS_PER_SEGMENT).base_wrench / scale

    def jacobian(grid):
        def fun(x, idx):
            end = integrate(x * scale, tension[idx], loads.select(idx), routing, section, grid, keep_nodes=False)[1]
            return residual(end, section, spec.total_length)
        return residual_and_jacobian(fun, z, torch.arange(64), central=True)[1]

    ref = jacobian(fine)
    error = (jacobian(coarse) - ref).flatten(1).norm(dim=-1) / ref.flatten(1).norm(dim=-1)
    assert float(error.max()) <= 2e-3, float(error.max())              # measured 6.5e-4 (one step: 1.1e-2)


def test_bad_inputs_name_the_argument():
    spec = RobotSpec.from_yaml(COUPLED)
    with pytest.raises(ValueError, match="tension"):
        solve_statics(spec, torch.zeros(2, 11, dtype=F64))
    with pytest.raises(ValueError, match="tension"):
        solve_statics(spec, torch.full((12,), math.nan, dtype=F64))
    with pytest.raises(ValueError, match="tip_wrench"):
        solve_statics(spec, torch.zeros(12, dtype=F64), tip_wrench=torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="point_wrenches"):
        solve_statics(spec, torch.zeros(12, dtype=F64), point_wrenches=[(0.5, torch.zeros(6, dtype=F64))])
    with pytest.raises(ValueError, match="on_failure"):
        solve_statics(spec, torch.zeros(12, dtype=F64), on_failure="ignore")
    with pytest.raises(ValueError, match="steps_per_segment"):
        solve_statics(spec, torch.zeros(12, dtype=F64), steps_per_segment=0)
    with pytest.raises(ValueError, match="mechanics"):
        solve_statics(RobotSpec.from_yaml(COUPLED.with_name("tdcr_3seg_coupled.yaml")), torch.zeros(12, dtype=F64))
