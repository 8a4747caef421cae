"""Errata of the source paper (docs/design.md §7), checked through the library's own code.

tests/test_clarke.py re-implements the paper's printed formulas in numpy and shows each of them
failing. This file adds what that leaves open: every test here runs the project's code
(clarke_matrix, ClarkeEncoder, forward_kinematics) in float64 *and* float32, with tolerances
tied to the dtype's eps and the quantity's scale, and shows the paper's version off by orders
of magnitude more than that tolerance.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import FAST, ROOT, classic_arc
from hypothesis import assume, given
from hypothesis import strategies as st

from dacr_learn.clarke import clarke_matrix, clarke_matrix_inverse
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec

DTYPES = (torch.float64, torch.float32)
angles = st.floats(-math.pi, math.pi)


def tol(dtype: torch.dtype, scale: float, factor: float = 64.0) -> float:
    """Absolute tolerance: ``factor`` units of round-off at the quantity's ``scale``."""
    return factor * torch.finfo(dtype).eps * scale


def one_segment(seg_type: str, **layout) -> RobotSpec:
    return RobotSpec.from_dict({"segments": [{"type": seg_type, "length": 0.1, "radius": 0.008, **layout}]})


# ------------------------------------------------------------------ erratum 1: (I − M_P⁻¹M_P)q = l·1


@FAST
@given(st.integers(3, 12), angles, st.floats(1e-3, 1e-2), angles, st.floats(0.05, 0.2))
def test_erratum1_minus_sign_with_library_matrices(n, offset, rho_norm, theta, length):
    """Eq. (l_ones) with the library's A = M_P⁻¹ and M_P: the sign must be minus, and the encoder's
    β of a symmetric type-I segment is 1ᵀ(I − M_P⁻¹M_P)q / n."""
    spec = one_segment("I", joints=n, offset=offset, limits={"length": [0.5 * length, 2 * length]})
    for dtype in DTYPES:
        psi = torch.tensor(spec.segments[0].joint_angles, dtype=torch.float64)
        a, mp = clarke_matrix_inverse(psi).to(dtype), clarke_matrix(psi).to(dtype)
        rho_c = rho_norm * torch.tensor([math.cos(theta), math.sin(theta)], dtype=dtype)
        q = length - a @ rho_c                                                   # Eq. (q)
        eye, atol = torch.eye(n, dtype=dtype), tol(dtype, length)
        corrected, paper = (eye - a @ mp) @ q, (eye + a @ mp) @ q
        assert (corrected - length).abs().max() <= atol
        # The printed sign adds −2ρ: at least 2·cos(π/3)·‖ρ_clarke‖ = 1 mm off, ≫ the tolerance.
        assert (paper - length).abs().max() >= rho_norm > 100 * atol
        assert (paper - length + 2 * a @ rho_c).abs().max() <= atol
        beta = ClarkeEncoder(spec).to(dtype)(q)[0, 2]
        assert abs(beta - corrected.mean()) <= atol and abs(beta - length) <= atol


# ------------------------------------------------------------------ erratum 2: arbitrary joint angles


@FAST
@given(st.integers(4, 8), st.integers(0, 2**31 - 1), st.floats(0.0, 1e-2), angles)
def test_erratum2_paper_length_bias_is_exact_and_encoder_is_exact(n, seed, rho_norm, theta):
    """Arbitrary angles (equal radii, so A is the paper's own Eq. MP_inverse): Eq. (forward_type-1_q)
    returns β·(1 + ‖P·1‖²/n) − 2·1ᵀAρ_clarke/n with P = A·M_P, the encoder returns β."""
    psi = np.sort(np.random.default_rng(seed).uniform(0, 2 * np.pi, n))
    a = np.stack([np.cos(psi), np.sin(psi)], axis=1)
    assume(np.linalg.cond(a) < 10)                                     # a layout robot.py accepts with margin
    mp = np.linalg.solve(a.T @ a, a.T)
    ones, beta = np.ones(n), 0.1
    rho_c = rho_norm * np.array([math.cos(theta), math.sin(theta)])
    q = beta * ones - a @ rho_c
    beta_paper = ones @ (np.eye(n) + a @ mp) @ q / n                                   # as printed
    p1 = a @ mp @ ones
    assert beta_paper == pytest.approx(beta * (1 + p1 @ p1 / n) - 2 * ones @ a @ rho_c / n, abs=tol(torch.float64, 1))
    spec = one_segment("I", joint_angles=psi.tolist())
    for dtype in DTYPES:
        feat = ClarkeEncoder(spec).to(dtype)(torch.tensor(q, dtype=dtype))[0]
        assert abs(feat[2].item() - beta) <= tol(dtype, beta, 256)       # seen: ≤ 50 units in float64
        assert np.abs(feat[:2].double().numpy() - rho_c).max() <= tol(dtype, beta, 256)


@pytest.mark.parametrize("seed", range(5))
def test_erratum2_five_random_angles_straight(seed):
    """5 random angles, l = 0.1 m, straight: the paper's length is > 5 % off; the encoder's is exact."""
    psi = np.sort(np.random.default_rng(seed).uniform(0, 2 * np.pi, 5))
    a = np.stack([np.cos(psi), np.sin(psi)], axis=1)
    q = 0.1 * np.ones(5)
    beta_paper = np.ones(5) @ (np.eye(5) + a @ np.linalg.pinv(a)) @ q / 5
    assert beta_paper > 0.105
    spec = one_segment("I", joint_angles=psi.tolist())
    for dtype in DTYPES:
        assert abs(ClarkeEncoder(spec).to(dtype)(torch.tensor(q, dtype=dtype))[0, 2].item() - 0.1) <= tol(dtype, 0.1)


# ------------------------------------------------------------------ erratum 3: block maps


def test_erratum3_printed_type1_matrix_is_mis_sized_too():
    """Eq. (forward_type-1) pairs the 2×n M_P with 0_{n×1}: it cannot be assembled either."""
    n = 4
    mp = clarke_matrix(torch.arange(n, dtype=torch.float64) * math.pi / 2).numpy()
    with pytest.raises(ValueError):
        np.block([[mp, np.zeros((n, 1))], [np.zeros((1, n)), np.ones((1, 1))]])
    assert np.block([[mp, np.zeros((2, 1))], [np.zeros((1, n)), np.ones((1, 1))]]).shape == (3, n + 1)


@pytest.mark.parametrize("n", [3, 5])
def test_erratum3_type3_block_map_with_joint_radius_unlike_reference(n):
    """block-diag(−M_P, I₂)·(q, β, α) with the library's M_P (joint radius r ≠ reference radius d)
    equals the encoder, when q runs on helices of radius r: q = sqrt((αr)² + β²)·1 − Aρ_clarke."""
    d, r = 0.008, 0.006
    layout = {"joint_angles": [0.3 + 2 * math.pi * i / n for i in range(n)], "joint_radii": [r] * n}
    spec = one_segment("III", **layout, limits={"twist": [-1.0, 1.0]})
    seg = spec.segments[0]
    psi, radii = (torch.tensor(x, dtype=torch.float64) for x in (seg.joint_angles, seg.joint_radii))
    a, mp = clarke_matrix_inverse(psi, radii, d), clarke_matrix(psi, radii, d)
    block = torch.block_diag(-mp, torch.eye(2, dtype=torch.float64))
    g = torch.Generator().manual_seed(n)
    for _ in range(5):
        rho_c = 0.01 * (2 * torch.rand(2, generator=g, dtype=torch.float64) - 1)
        u = torch.rand(2, generator=g, dtype=torch.float64)
        beta, alpha = 0.08 + 0.04 * u[:1], 2 * u[1:] - 1                        # β ∈ [0.08, 0.12] m, α ∈ [−1, 1] rad
        q = torch.sqrt((alpha * r) ** 2 + beta**2) - a @ rho_c
        expected = block @ torch.cat([q, beta, alpha])
        assert (expected - torch.cat([rho_c, beta, alpha])).abs().max() <= tol(torch.float64, 0.1)
        for dtype in DTYPES:
            feat = ClarkeEncoder(spec).to(dtype)(torch.cat([q, alpha]).to(dtype))[0]
            assert (feat.double() - expected).abs().max() <= tol(dtype, 0.1)


# ------------------------------------------------------------------ erratum 4: unequal radii, end to end


@FAST
@given(angles, st.floats(0.2, 1.5))
def test_erratum4_unequal_radii_tip_pose(theta, phi):
    """Joint lengths of a constant-curvature arc with unequal joint radii (q_i = l − d_i·φ·cos(θ − ψ_i)),
    encoded and passed to forward_kinematics, give the classic arc's tip; the paper's M_P (rows without
    d_i/d) misplaces it by ≥ 0.9 % of l·φ on this layout (checked on a 721 × 4 grid of θ, φ)."""
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / "asymmetric.yaml")
    seg = spec.segments[0]
    psi, radii = np.array(seg.joint_angles), np.array(seg.joint_radii)
    q = seg.length - radii * phi * np.cos(theta - psi)
    tip = classic_arc(theta, phi, seg.length)[:3, 3]
    a_paper = np.stack([np.cos(psi), np.sin(psi)], axis=1)
    rho_paper = np.linalg.pinv(a_paper) @ (seg.length - q)
    feat_paper = torch.tensor([[*rho_paper, seg.length, 0.0]])
    tip_paper = forward_kinematics(spec, feat_paper)[:3, 3].numpy()
    assert np.linalg.norm(tip_paper - tip) > 0.005 * seg.length * phi > 100 * tol(torch.float32, seg.length)
    for dtype in DTYPES:
        pose = forward_kinematics(spec, ClarkeEncoder(spec).to(dtype)(torch.tensor(q, dtype=dtype)))
        assert np.abs(pose[:3, 3].double().numpy() - tip).max() <= tol(dtype, seg.length)
