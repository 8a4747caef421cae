"""Displacement-controlled Cosserat statics (dacr_learn.cosserat.displacement): commanded tendon lengths →
tensions and shape, checked against the tension-driven solve it inverts and against the LCP's conditions."""
from __future__ import annotations

import itertools

import pytest
import torch

from dacr_learn.cosserat import ConvergenceError, solve_statics
from dacr_learn.cosserat.displacement import solve_displacements, solve_lcp, tension_scale
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
GRAVITY = torch.tensor([0.0, 0.0, -9.81], dtype=F64)


def robot() -> RobotSpec:
    """FTDCR-v4-like: three coupled type-0 segments, three tendons each at 4.5 mm, a 1 mm NiTi rod."""
    segs = [{"type": "0", "length": length, "radius": 0.0045, "joints": 3, "offset": offset, "limits": {"bend": 1.2}}
            for length, offset in ((0.06, -3.03), (0.0625, -2.53), (0.064, -2.01))]
    return RobotSpec.from_dict({"name": "v4-like", "routing": "coupled", "segments": segs, "mechanics": {
        "youngs_modulus": 6.0e10, "poisson_ratio": 0.33, "outer_radius": 0.0005, "density": 6450,
        "tendon_compliance": 1e-3}})


def commanded(spec: RobotSpec, n: int, seed: int, spring: torch.Tensor | None = None):
    """(true tensions (n, 9) with about half slack, the tension-driven solution, commanded rest lengths): taut
    tendons get exactly the length the solve implies, slack ones up to 2 mm more."""
    g = torch.Generator().manual_seed(seed)
    tau = 8 * torch.rand(n, 9, generator=g, dtype=F64)
    tau[torch.rand(n, 9, generator=g) < 0.5] = 0
    sol = solve_statics(spec, tau, gravity=GRAVITY, steps_per_segment=8)
    c = spec.mechanics.tendon_compliance
    rest = sol.tendon_rest_lengths if spring is None else sol.tendon_lengths - c * spring * tau
    slack = (tau == 0) * 2e-3 * torch.rand(n, 9, generator=g, dtype=F64)
    return tau, sol, rest + slack


@pytest.mark.parametrize("spring", [False, True])
def test_recovers_the_tensions_that_produced_the_commanded_lengths(spring):
    spec = robot()
    lengths = torch.tensor([0.06] * 3 + [0.1225] * 3 + [0.1865] * 3, dtype=F64) if spring else None
    tau, sol, ell = commanded(spec, 24, seed=0, spring=lengths)
    out = solve_displacements(spec, ell, gravity=GRAVITY, spring_lengths=lengths, steps_per_segment=8, tol=1e-10)
    assert bool(out.converged.all()) and float(out.violation.max()) <= 1e-10
    scale = tension_scale(spec)
    assert torch.allclose(out.tension, tau, rtol=0, atol=1e-5 * scale)
    tip_err = (out.tip[..., :3, 3] - sol.tip[..., :3, 3]).norm(dim=-1)
    assert float(tip_err.max()) < 1e-7 * spec.total_length


def test_solution_satisfies_the_complementarity_conditions():
    spec = robot()
    _, _, ell = commanded(spec, 16, seed=1)
    ell = ell + 1e-4 * torch.randn(ell.shape, generator=torch.Generator().manual_seed(5), dtype=F64)
    out = solve_displacements(spec, ell, gravity=GRAVITY, tol=1e-10)
    rest = out.statics.tendon_rest_lengths
    taut = out.tension > 0
    assert bool((out.tension >= 0).all())
    assert float((rest - ell)[taut].abs().max()) <= 1e-10                  # taut: the path uses all the tendon
    assert float((rest - ell)[~taut].max()) <= 1e-10                        # slack: the path needs no more
    assert bool(taut.any()) and bool((~taut).any())


def test_warm_start_from_a_nearby_solution_takes_fewer_steps():
    spec = robot()
    _, _, ell = commanded(spec, 16, seed=2)
    cold = solve_displacements(spec, ell, gravity=GRAVITY, tol=1e-10)
    moved = ell + 2e-5
    warm = solve_displacements(spec, moved, gravity=GRAVITY, tension_guess=cold.tension,
                               compliance_guess=cold.compliance, tol=1e-10)
    again = solve_displacements(spec, moved, gravity=GRAVITY, tol=1e-10)
    assert torch.allclose(warm.tension, again.tension, rtol=0, atol=1e-6 * tension_scale(spec))
    assert float(warm.iterations.float().mean()) < float(again.iterations.float().mean())


def test_batch_dims_are_kept():
    spec = robot()
    _, _, ell = commanded(spec, 6, seed=3)
    out = solve_displacements(spec, ell.reshape(2, 3, 9), gravity=GRAVITY)
    assert out.tension.shape == (2, 3, 9) and out.compliance.shape == (2, 3, 9, 9)
    assert out.tip.shape == (2, 3, 4, 4) and out.converged.shape == (2, 3)


def test_per_sample_gravity_and_spring_lengths_equal_separate_solves():
    """Parameter sets that share the robot (gravity, tendon spring lengths) solved in one batch give what each
    gives alone — the batched finite differences of the hardware Cosserat fit."""
    spec = robot()
    _, _, ell = commanded(spec, 5, seed=6)
    lengths = torch.tensor([0.06] * 3 + [0.1225] * 3 + [0.1865] * 3, dtype=F64)
    gravities = [GRAVITY, torch.tensor([3.0, -2.0, -8.0], dtype=F64), torch.zeros(3, dtype=F64)]
    springs = [lengths, 1.3 * lengths, 0.8 * lengths]
    alone = [solve_displacements(spec, ell, gravity=g, spring_lengths=s, tol=1e-10)
             for g, s in zip(gravities, springs, strict=True)]
    together = solve_displacements(spec, ell.repeat(3, 1), tol=1e-10,
                                   gravity=torch.cat([g.expand(5, 3) for g in gravities]),
                                   spring_lengths=torch.cat([s.expand(5, 9) for s in springs]))
    assert bool(together.converged.all())
    for k, one in enumerate(alone):
        part = slice(5 * k, 5 * k + 5)
        assert torch.allclose(together.tension[part], one.tension, rtol=0, atol=1e-5 * tension_scale(spec))
        assert float((together.tip[part, :3, 3] - one.tip[..., :3, 3]).norm(dim=-1).max()) < 1e-7 * spec.total_length
    assert float((alone[0].tip[..., :3, 3] - alone[1].tip[..., :3, 3]).norm(dim=-1).max()) > 1e-4   # they differ


def _lcp_brute_force(a: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """The LCP's solution by trying every set of positive unknowns (unique for SPD A)."""
    n = q.shape[0]
    for k in range(n + 1):
        for s in itertools.combinations(range(n), k):
            tau = torch.zeros(n, dtype=a.dtype)
            if s:
                idx = list(s)
                tau[idx] = torch.linalg.solve(a[idx][:, idx], -q[idx])
            w = a @ tau + q
            if bool((tau >= -1e-12).all()) and bool((w >= -1e-12).all()):
                return tau
    raise AssertionError("no solution")


def test_lcp_matches_enumeration_on_random_spd_problems():
    g = torch.Generator().manual_seed(0)
    b, n = 40, 6
    m = torch.randn(b, n, n, generator=g, dtype=F64)
    a = m @ m.mT + 0.05 * torch.eye(n, dtype=F64)
    q = torch.randn(b, n, generator=g, dtype=F64)
    tau = solve_lcp(a, q)
    expected = torch.stack([_lcp_brute_force(a[i], q[i]) for i in range(b)])
    assert torch.allclose(tau, expected, rtol=0, atol=1e-9)


def test_bad_inputs_are_refused_with_clear_errors():
    spec = robot()
    ell = torch.full((2, 9), 0.1, dtype=F64)
    with pytest.raises(ValueError, match="rest_lengths"):
        solve_displacements(spec, ell[:, :8])
    with pytest.raises(ValueError, match="non-positive"):
        solve_displacements(spec, -ell)
    with pytest.raises(ValueError, match="tension_guess"):
        solve_displacements(spec, ell, tension_guess=torch.zeros(3, 9, dtype=F64))
    with pytest.raises(ValueError, match="compliance_guess"):
        solve_displacements(spec, ell, compliance_guess=torch.zeros(2, 9, 8, dtype=F64))
    with pytest.raises(ValueError, match="spring_lengths"):
        solve_displacements(spec, ell, spring_lengths=torch.ones(8, dtype=F64))
    with pytest.raises(ValueError, match="spring_lengths"):
        solve_displacements(spec, ell, spring_lengths=torch.ones(3, 9, dtype=F64))      # not one per sample
    with pytest.raises(ValueError, match="gravity"):
        solve_displacements(spec, ell, gravity=torch.zeros(3, 3, dtype=F64))
    with pytest.raises(ValueError, match="on_failure"):
        solve_displacements(spec, ell, on_failure="ignore")
    no_mechanics = RobotSpec.from_dict({k: v for k, v in spec.to_dict().items() if k != "mechanics"})
    with pytest.raises(ValueError, match="mechanics"):
        solve_displacements(no_mechanics, ell)


def test_unreachable_command_raises_or_is_flagged():
    """A tendon shortened by a third of its path would fold the robot: not solved, never returned as a shape."""
    spec = robot()
    ell = torch.tensor([0.06] * 3 + [0.1225] * 3 + [0.1865] * 3, dtype=F64).repeat(2, 1)
    ell[1, 0] = 0.04
    with pytest.raises(ConvergenceError, match="solve_displacements"):
        solve_displacements(spec, ell, max_iter=4)
    out = solve_displacements(spec, ell, max_iter=4, on_failure="flag")
    assert bool(out.converged[0]) and not bool(out.converged[1])


def test_passing_at_the_segment_radius_kinks_only_where_radii_differ():
    """passing="segment" equals the default on equal radii, changes the shape on unequal ones, and is checked."""
    from dacr_learn.cosserat.tendon import tendon_routing

    spec = robot()
    tau = torch.tensor([[4.0, 0, 0, 0, 3.0, 0, 0, 0, 2.0]], dtype=F64)
    own = solve_statics(spec, tau, passing="own").tip
    # equal to the shooting tolerance (1e-10, scaled by the length): the extra disk jumps change only rounding
    assert torch.allclose(solve_statics(spec, tau, passing="segment").tip, own, rtol=0, atol=1e-9 * spec.total_length)
    d = spec.to_dict()
    d["segments"][0]["radius"] = 0.006
    wider = RobotSpec.from_dict(d)
    routing = tendon_routing(wider, "segment")
    assert torch.allclose(routing.offsets_in(0)[8].norm(), torch.tensor(0.006, dtype=F64))   # tendon 8 in segment 0
    assert torch.allclose(routing.offsets_in(2)[8].norm(), torch.tensor(0.0045, dtype=F64))
    moved = (solve_statics(wider, tau, passing="segment").tip - solve_statics(wider, tau).tip)[..., :3, 3]
    assert float(moved.norm()) > 1e-3
    with pytest.raises(ValueError, match="passing"):
        tendon_routing(spec, "through")


def test_a_sample_whose_warm_start_is_unusable_is_flagged_and_the_rest_solve():
    """A NaN chord matrix in the warm start (an earlier failed difference) leaves that sample unconverged: no error,
    no NaN fed into the next solve; NaN tensions are refused up front."""
    spec = robot()
    _, _, ell = commanded(spec, 4, seed=6)
    cold = solve_displacements(spec, ell, gravity=GRAVITY)
    chord = cold.compliance.clone()
    chord[2] = torch.nan
    out = solve_displacements(spec, ell + 1e-4, gravity=GRAVITY, tension_guess=cold.tension, compliance_guess=chord,
                              on_failure="flag")
    assert out.converged.tolist() == [True, True, False, True]
    assert bool(torch.isfinite(out.tip[[0, 1, 3]]).all())
    bad = cold.tension.clone()
    bad[1, 0] = torch.nan
    with pytest.raises(ValueError, match="tension_guess"):
        solve_displacements(spec, ell, tension_guess=bad)
