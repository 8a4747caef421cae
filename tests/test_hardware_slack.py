"""The slack-aware encoder (dacr_learn.hardware.slack): exact for consistent commands, a single pull bends towards its
tendon, gradients, the force balance (no torsion from straight tendons); the tendon QP by active-set enumeration
(:func:`solve_tendon_qp_enumerated` below: :func:`active_set_gains`, which HardwareFK uses folded, and the enumerated
solution of benchmarks/generated_fk.py) against the semi-smooth
Newton iteration :func:`solve_tendon_qp` and the optimality condition of the energy, in float64 and float32.
"""
from __future__ import annotations

import pytest
import torch
from conftest import FAST, ROOT, load_example, roundoff_tol
from hardware_testkit import V4_ROBOT
from hypothesis import given
from hypothesis import strategies as st

from dacr_learn.hardware.slack import (
    SlackAwareEncoder,
    active_set_gains,
    solve_tendon_qp,
)
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
SPECS = {"v4": RobotSpec.from_yaml(ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml"),
         "2seg-independent": RobotSpec.from_dict({"name": "two", "routing": "independent", "segments": [
             {"type": "0", "length": 0.08, "radius": 0.005, "joints": 4, "offset": 0.4},
             {"type": "0", "length": 0.07, "radius": 0.004, "joints": 3, "offset": -1.1}]})}


def solve_tendon_qp_enumerated(x, g, bend_w, tendon_w):
    """:func:`solve_tendon_qp` (energy form, no force map or load) by enumerating the active sets:
    x (B, N) [m] → ρ (B, D). The same minimiser; differentiable in x (not in the weights)."""
    generated = load_example("generated_fk", "benchmarks")
    sets, gain = active_set_gains(g, bend_w, tendon_w)
    return generated.enumerated_solution(x, sets, gain, generated.residual_maps(g, gain), tendon_w)


@pytest.mark.parametrize("routing", ["coupled", "independent"])
def test_slack_encoder_is_exact_for_consistent_commands(routing):
    d = RobotSpec.from_yaml(V4_ROBOT).to_dict() | {"routing": routing}
    spec = RobotSpec.from_dict(d)
    g = torch.Generator().manual_seed(0)
    feat = torch.zeros(64, 3, 4, dtype=torch.float64)
    feat[..., :2] = (torch.rand(64, 3, 2, generator=g, dtype=torch.float64) - 0.5) * 0.008
    feat[..., 2] = torch.tensor([s.length for s in spec.segments], dtype=torch.float64)
    decoder = ClarkeDecoder(spec)
    q = decoder(feat)
    x = decoder(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - q
    enc = SlackAwareEncoder(spec, compliance=1e-14)
    with torch.no_grad():
        got = enc(x)
    assert torch.allclose(got, feat, atol=1e-9)
    assert torch.allclose(got, ClarkeEncoder(spec)(q), atol=1e-9)


def test_slack_encoder_single_pull_bends_towards_the_tendon_with_equal_curvature(v4_spec):
    enc = SlackAwareEncoder(v4_spec, compliance=1e-14)
    x = torch.full((9,), -0.01, dtype=torch.float64)
    x[6] = 0.002                                                   # segment 3, joint 0 (ψ = 0)
    with torch.no_grad():
        rho = enc(x)[:, :2]
    lengths = torch.tensor([s.length for s in v4_spec.segments], dtype=torch.float64)
    assert torch.allclose(rho[:, 1], torch.zeros(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(rho[:, 0].sum(), torch.tensor(0.002, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(rho[:, 0] / lengths, (rho[0, 0] / lengths[0]).expand(3), rtol=1e-8)
    with torch.no_grad():
        slack = enc(torch.full((9,), -0.01, dtype=torch.float64))
        assert torch.equal(slack[:, :2], torch.zeros(3, 2, dtype=torch.float64))


def test_slack_encoder_gradients_match_finite_differences(v4_spec):
    enc = SlackAwareEncoder(v4_spec, compliance=2e-6, pretension=1e-4)
    x = torch.tensor([[2e-3, -1e-3, -1e-3, 1e-3, -3e-3, 0.0, 2e-3, -9e-3, 1e-3]], dtype=torch.float64)
    names = ["log_radius_scale", "rotation", "log_compliance", "pretension"]
    inputs = tuple(enc.get_parameter(n).detach().clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(
        lambda *p: torch.func.functional_call(enc, dict(zip(names, p, strict=True)), (x,))[..., :2], inputs,
        eps=1e-7, atol=1e-7)


def test_slack_encoder_balances_forces_so_straight_tendons_cause_no_torsion(v4_spec):
    """At the solution, each segment's bending energy gradient equals the force of the taut
    tendons through it (KKT stationarity of E), slack tendons carry nothing, and so each ρ⁽ᵏ⁾ is
    parallel to the total tendon force through segment k — the moment of straight-routed tendons
    about the backbone, cross(ρ⁽ᵏ⁾, F), vanishes (docs/hardware.md: the model predicts no twist).
    The tendon directions are rebuilt here from the spec's joint angles, not from the encoder."""
    enc = SlackAwareEncoder(v4_spec, compliance=2e-6, pretension=5e-5)
    with torch.no_grad():
        enc.rotation.copy_(torch.tensor([0.1, -0.2, 0.3]))
        enc.log_radius_scale.copy_(torch.tensor([0.05, -0.1, 0.0]))
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(200, 9, generator=g, dtype=torch.float64) - 0.6) * 8e-3   # mixes taut and slack tendons
    x[:50, 3:] = -0.01                                                        # parked slack, as in the pulls
    with torch.no_grad():
        rho = enc.clarke(x)                                                   # (n, 3, 2) at the effective radii
        gmap = enc.displacement_map()
        stretch = x + enc.pretension - rho.flatten(-2) @ gmap.mT
        tension = stretch.clamp_min(0) / enc.path_length                      # slack tendons: 0
        d = enc.effective_radius()
        bend_w = enc.log_compliance.exp() / (enc.lengths * d**2)
    lhs = bend_w[:, None] * rho
    rhs = (tension @ gmap).unflatten(-1, (3, 2))
    assert torch.allclose(lhs, rhs, atol=1e-12 * float(rhs.abs().max()))     # stationarity
    assert (stretch > 0).any() and (stretch < 0).any()
    psi = torch.tensor([a for s in v4_spec.segments for a in s.joint_angles], dtype=torch.float64)
    segment = torch.arange(3).repeat_interleave(3)
    psi = psi + enc.rotation.detach()[segment]
    force = torch.zeros(200, 3, 2, dtype=torch.float64)
    force.index_add_(1, segment, tension.unsqueeze(-1) * torch.stack([psi.cos(), psi.sin()], -1))
    through = force.flip(1).cumsum(1).flip(1)                                 # Σ over segments j ≥ k
    torque = rho[..., 0] * through[..., 1] - rho[..., 1] * through[..., 0]
    scale = rho.norm(dim=-1) * through.norm(dim=-1)
    assert float(scale.max()) > 0
    assert float((torque.abs() / scale.clamp_min(1e-30)).max()) < 1e-9
    # an explicit force map equal to G gives the same solution; a reduced one, its own balance
    flat = x + enc.pretension
    same = solve_tendon_qp(flat, gmap, bend_w.repeat_interleave(2), 1 / enc.path_length,
                           force_map=gmap.expand(200, -1, -1))
    tol = roundoff_tol(torch.float64, float(rho.abs().max()), ulps=1024)
    assert torch.allclose(same, rho.flatten(-2), rtol=0, atol=tol)
    reduced = gmap * torch.linspace(0.6, 1.0, 9, dtype=torch.float64)[:, None]
    rho_f = solve_tendon_qp(flat, gmap, bend_w.repeat_interleave(2), 1 / enc.path_length,
                            force_map=reduced.expand(200, -1, -1))
    tension_f = (flat - rho_f @ gmap.mT).clamp_min(0) / enc.path_length
    assert torch.allclose(bend_w.repeat_interleave(2) * rho_f, tension_f @ reduced, atol=1e-12 * float(rhs.abs().max()))
    assert not torch.allclose(rho_f, rho.flatten(-2), atol=1e-6)
    # an external load (e.g. gravity) enters the same balance: bend_w·ρ = Gᵀ·tension + load
    assert torch.allclose(enc.bend_weights(), bend_w.repeat_interleave(2), rtol=1e-14)
    load = (torch.rand(200, 6, generator=g, dtype=torch.float64) - 0.5) * 2e-3
    rho_l = solve_tendon_qp(flat, gmap, enc.bend_weights(), 1 / enc.path_length, load=load)
    tension_l = (flat - rho_l @ gmap.mT).clamp_min(0) / enc.path_length
    assert torch.allclose(bend_w.repeat_interleave(2) * rho_l, tension_l @ gmap + load,
                          atol=1e-12 * float(rhs.abs().max()))
    assert not torch.allclose(rho_l, rho.flatten(-2), atol=1e-6)


# --------------------------------------------------------------------------------------------------
# The tendon QP by active-set enumeration
# --------------------------------------------------------------------------------------------------


def _problem(spec: RobotSpec, log_c: float, pretension: float, seed: int, n: int = 300):
    """Encoder weights with perturbed radii / rotations and commands (n, N) [m] with many slack tendons."""
    enc = SlackAwareEncoder(spec, compliance=10.0**log_c, pretension=pretension)
    g = torch.Generator().manual_seed(seed)
    m = spec.num_segments
    with torch.no_grad():
        enc.log_radius_scale.copy_(0.1 * torch.randn(m, generator=g, dtype=F64))
        enc.rotation.copy_(0.1 * torch.randn(m, generator=g, dtype=F64))
        x = 4e-3 * torch.randn(n, enc.g_nominal.shape[0], generator=g, dtype=F64) + enc.pretension
        return x, enc.displacement_map(), enc.bend_weights(), 1.0 / enc.path_length


@pytest.mark.parametrize("name", sorted(SPECS))
@FAST
@given(log_c=st.floats(-8.0, -4.0), pretension=st.floats(0.0, 1e-3), seed=st.integers(0, 2**16))
def test_enumerated_qp_is_the_iterative_solution_and_optimal(name, log_c, pretension, seed):
    x, g, bend_w, tendon_w = _problem(SPECS[name], log_c, pretension, seed)
    rho = solve_tendon_qp_enumerated(x, g, bend_w, tendon_w)
    ref = solve_tendon_qp(x, g, bend_w, tendon_w)
    scale = float(ref.abs().max())
    assert (rho - ref).abs().max() <= roundoff_tol(F64, scale, ulps=4096)
    # independent of both solvers: the energy's gradient bend_w·ρ − Gᵀ W max(0, x − Gρ) vanishes (to the
    # rounding of x − Gρ, weighted)
    stretch = torch.relu(x - rho @ g.mT)
    force_scale = float(tendon_w.max() * x.abs().max() * g.abs().sum(0).max())
    assert (bend_w * rho - (tendon_w * stretch) @ g).abs().max() <= roundoff_tol(F64, force_scale, ulps=1024)
    assert bool((stretch == 0).any()) and bool((stretch > 0).any()), "slack and stretched tendons are exercised"


def test_enumerated_qp_in_float32_is_the_float64_solution_to_float32_rounding():
    x, g, bend_w, tendon_w = _problem(SPECS["v4"], -6.0, 1e-4, 3, n=2000)
    ref = solve_tendon_qp(x, g, bend_w, tendon_w)
    got = solve_tendon_qp_enumerated(x.float(), g, bend_w, tendon_w)
    assert got.dtype == torch.float32
    assert (got.double() - ref).abs().max() <= roundoff_tol(torch.float32, float(ref.abs().max()), ulps=1024)


def test_enumerated_qp_is_differentiable_in_the_commands():
    x, g, bend_w, tendon_w = _problem(SPECS["2seg-independent"], -6.0, 2e-4, 5, n=6)
    assert torch.autograd.gradcheck(lambda v: solve_tendon_qp_enumerated(v, g, bend_w, tendon_w),
                                    (x.requires_grad_(True),), eps=1e-9, atol=1e-7)


def test_active_set_gains_reject_too_many_tendons():
    g = torch.ones(13, 2, dtype=F64)
    with pytest.raises(ValueError, match="at most 12 tendons"):
        active_set_gains(g, torch.ones(2, dtype=F64), torch.ones(13, dtype=F64))
