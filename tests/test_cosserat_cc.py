"""Cosserat model, check (a): without external load a tendon-driven segment is an exact constant-curvature arc.

With no gravity or external wrench the total (rod + tendon) wrench vanishes at every cut, so the rod's
internal wrench is n = −Σ τ_i t_i, m = −Σ τ_i r_i × t_i. For straight routing the constant strains
u = K_bt⁻¹ Σ τ_i e3 × r_i, v = e3 − (Σ τ_i / EA) e3 (t_i = e3, no shear, no torsion) satisfy the
equations exactly (docs/cosserat.md §4): the shape is the CC arc with bending angle ‖u‖·l and
compressed length β = l·v_z, the axial strain included. The references are the library's CC kinematics
(``cc_transform``, ``forward_kinematics``) and Clarke decoder, evaluated on those closed-form
parameters; the Cosserat solution must match them to 1e-6 of the length at every station (the RK4
error at 32 steps per segment; the check below also shows it is the integrator, not the model).
"""
from __future__ import annotations

import math

import pytest
import torch
from conftest import ROOT

from dacr_learn.cosserat import solve_statics
from dacr_learn.kinematics import cc_transform, forward_kinematics
from dacr_learn.layers import ClarkeDecoder
from dacr_learn.robot import RobotSpec

MECH = {"youngs_modulus": 6.0e10, "poisson_ratio": 0.33, "outer_radius": 0.0005}
EPS = torch.finfo(torch.float64).eps


def one_segment(joints: int = 4, offset: float = 0.3) -> RobotSpec:
    return RobotSpec.from_dict({"segments": [{"type": "I", "length": 0.12, "radius": 0.006, "joints": joints,
                                              "offset": offset}], "mechanics": MECH})


def closed_form_features(spec: RobotSpec, tension: torch.Tensor) -> torch.Tensor:
    """(..., m, 4) CC features (ρ_re, ρ_im, β, 0) of each segment from u = K_bt⁻¹ Σ τ e3 × r, v_z = 1 − Σ τ/EA."""
    mech = spec.mechanics
    area, inertia = math.pi * mech.outer_radius**2, math.pi * mech.outer_radius**4 / 4
    ei, ea = mech.youngs_modulus * inertia, mech.youngs_modulus * area
    psi = torch.tensor([a for s in spec.segments for a in s.joint_angles], dtype=torch.float64)
    rad = torch.tensor([r for s in spec.segments for r in s.joint_radii], dtype=torch.float64)
    first = 0
    feats = []
    last_joint = torch.cumsum(torch.tensor([s.num_joints for s in spec.segments]), 0)
    for j, seg in enumerate(spec.segments):
        on = torch.arange(psi.numel()) >= first       # tendons of segments j.. pass segment j (coupled)
        tau = tension * on
        ux = (tau * -rad * torch.sin(psi)).sum(-1) / ei    # e3 × r = (−d sin ψ, d cos ψ, 0)
        uy = (tau * rad * torch.cos(psi)).sum(-1) / ei
        beta = seg.length * (1 - tau.sum(-1) / ea)
        rho = seg.radius * seg.length * torch.stack([uy, -ux], -1)   # CC bending vector l·(u_y, −u_x)
        feats.append(torch.cat([rho, beta.unsqueeze(-1), torch.zeros_like(beta).unsqueeze(-1)], -1))
        first = int(last_joint[j])
    return torch.stack(feats, -2)


@pytest.mark.parametrize("tensioned", [[0], [1], [0, 1]])
def test_one_segment_is_the_cc_arc_at_every_station(tensioned):
    spec = one_segment()
    tension = torch.zeros(4, dtype=torch.float64)
    tension[tensioned] = torch.tensor([6.0, 3.5][: len(tensioned)], dtype=torch.float64)
    sol = solve_statics(spec, tension, steps_per_segment=32)
    feats = closed_form_features(spec, tension)[0]
    frac = sol.arc / spec.total_length
    ref = cc_transform(feats[:2] / spec.segments[0].radius * frac.unsqueeze(-1), feats[2] * frac)
    length = spec.total_length
    assert feats[:2].norm() / spec.segments[0].radius > 1.0                  # a real bend: φ > 1 rad
    assert (sol.frames[..., :3, 3] - ref[..., :3, 3]).norm(dim=-1).max() <= 1e-6 * length
    assert (sol.frames[..., :3, :3] - ref[..., :3, :3]).abs().max() <= 1e-6
    # the solution's own strains are the closed form (to rounding: they are constant by the ODE)
    u_ref = torch.stack([-feats[1], feats[0]]) / (spec.segments[0].radius * length)
    assert torch.allclose(sol.curvature[..., :2], u_ref.expand(sol.arc.numel(), 2), rtol=1e-12, atol=1e-12)
    assert torch.allclose(sol.stretch[..., 2], feats[2] / length, rtol=0, atol=100 * EPS)
    assert sol.stretch[..., :2].abs().max() <= 100 * EPS and sol.curvature[..., 2].abs().max() <= 1e-12


def test_one_segment_tendon_lengths_are_the_clarke_decoder_joint_lengths():
    spec = one_segment(joints=5, offset=0.1)
    tension = torch.tensor([[1.5, 0.0, 0.0, 0.0, 0.7], [0.0, 0.0, 2.5, 0.0, 0.0]], dtype=torch.float64)
    sol = solve_statics(spec, tension, steps_per_segment=32)
    q = ClarkeDecoder(spec).to(torch.float64)(closed_form_features(spec, tension))
    assert (sol.tendon_lengths - q).abs().max() <= 1e-6 * spec.total_length


def test_coupled_three_segments_are_piecewise_cc_with_coupled_joint_lengths():
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / "tdcr_3seg_cosserat.yaml")
    tension = torch.zeros(2, 12, dtype=torch.float64)
    tension[0, [0, 5, 10]] = torch.tensor([4.0, 3.2, 2.4], dtype=torch.float64)   # one tendon per segment
    tension[1, [1, 2, 7, 11]] = torch.tensor([1.6, 3.6, 4.4, 2.0], dtype=torch.float64)
    sol = solve_statics(spec, tension, steps_per_segment=32)
    feats = closed_form_features(spec, tension)
    length = spec.total_length
    assert (feats[..., :2].norm(dim=-1) / 0.008).amax(-1).min() > 0.8     # bends up to 0.8 rad or more
    assert (sol.tip[..., :3, 3] - forward_kinematics(spec, feats)[..., :3, 3]).norm(dim=-1).max() <= 1e-6 * length
    assert (sol.tip[..., :3, :3] - forward_kinematics(spec, feats)[..., :3, :3]).abs().max() <= 1e-6
    q = ClarkeDecoder(spec).to(torch.float64)(feats)
    assert (sol.tendon_lengths - q).abs().max() <= 1e-6 * length
    compliance = spec.mechanics.tendon_compliance
    assert torch.allclose(sol.tendon_rest_lengths, q / (1 + compliance * tension), rtol=0, atol=1e-6 * length)
