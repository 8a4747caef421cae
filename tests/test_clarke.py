"""Clarke matrices: the paper's properties (symmetric joints) and the errata of docs/design.md §7.

The paper's formulas are re-implemented here in numpy exactly as printed (with M_P⁻¹ from
its Eq. MP_inverse, i.e. rows (cos ψ_i, sin ψ_i) without d_i/d), so each erratum test shows
the printed formula failing where the project's code is right.

The second half (errata through the library's own code) leaves nothing of that open: every test
there runs the project's code (clarke_matrix, ClarkeEncoder, forward_kinematics) in float64 *and*
float32, with tolerances tied to the dtype's eps and the quantity's scale, and shows the paper's
version off by orders of magnitude more than that tolerance.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import FAST, ROOT, classic_arc
from hypothesis import assume, given
from hypothesis import strategies as st

from dacr_learn.clarke import clarke_matrix, clarke_matrix_inverse, joint_space_maps
from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeEncoder
from dacr_learn.robot import RobotSpec

TOL = 1e-12


def symmetric_angles(n: int, offset: float) -> np.ndarray:
    return offset + 2 * np.pi * np.arange(n) / n


def paper_mp_inverse(psi: np.ndarray) -> np.ndarray:
    """Paper Eq. (MP_inverse): rows (cos ψ_i, sin ψ_i) — no joint radii."""
    return np.stack([np.cos(psi), np.sin(psi)], axis=1)


def paper_mp(psi: np.ndarray) -> np.ndarray:
    """Paper Eq. (MP_inverse_pseudo): M_P = ((M_P⁻¹)ᵀM_P⁻¹)⁻¹(M_P⁻¹)ᵀ."""
    a = paper_mp_inverse(psi)
    return np.linalg.solve(a.T @ a, a.T)


symmetric_layouts = st.tuples(st.integers(3, 12), st.floats(-math.pi, math.pi))


# ------------------------------------------------------------------ paper properties (symmetric)


@FAST
@given(symmetric_layouts)
def test_symmetric_clarke_matrix_closed_form(layout):
    n, offset = layout
    psi = symmetric_angles(n, offset)
    mp = clarke_matrix(torch.tensor(psi)).numpy()
    assert mp.shape == (2, n)
    assert np.allclose(mp, 2 / n * np.stack([np.cos(psi), np.sin(psi)]), atol=TOL, rtol=0)


@FAST
@given(symmetric_layouts, st.integers(0, 2**31 - 1))
def test_symmetric_properties(layout, seed):
    n, offset = layout
    psi = torch.tensor(symmetric_angles(n, offset))
    mp, a = clarke_matrix(psi), clarke_matrix_inverse(psi)
    assert torch.allclose(mp @ torch.ones(n, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), atol=TOL)
    assert torch.allclose(mp @ a, torch.eye(2, dtype=torch.float64), atol=TOL, rtol=0)
    # ‖ρ_clarke‖² = (2/n)‖ρ‖² for ρ in the range of A
    rho_c = torch.randn(2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    rho = a @ rho_c
    assert torch.allclose(mp @ rho, rho_c, atol=TOL, rtol=0)
    assert torch.isclose(rho_c.square().sum(), 2 / n * rho.square().sum(), atol=0, rtol=1e-12)


@FAST
@given(st.integers(3, 8), st.integers(0, 2**31 - 1))
def test_arbitrary_clarke_matrix_is_left_inverse_with_radii(n, seed):
    g = np.random.default_rng(seed)
    psi = 2 * np.pi * (np.arange(n) + 0.6 * (g.uniform(size=n) - 0.5)) / n     # spread, well conditioned
    radii, d = g.uniform(0.005, 0.012, n), 0.008
    a = clarke_matrix_inverse(torch.tensor(psi), torch.tensor(radii), d).numpy()
    assert np.allclose(a, (radii / d)[:, None] * paper_mp_inverse(psi), atol=TOL, rtol=0)
    mp = clarke_matrix(torch.tensor(psi), torch.tensor(radii), d).numpy()
    assert np.allclose(mp, np.linalg.lstsq(a, np.eye(n), rcond=None)[0], atol=1e-10, rtol=0)
    assert np.allclose(mp @ a, np.eye(2), atol=1e-12, rtol=0)


def test_clarke_matrix_batched():
    psi = torch.tensor(np.stack([symmetric_angles(4, 0.0), symmetric_angles(4, 0.4)]))
    mp = clarke_matrix(psi)
    assert mp.shape == (2, 2, 4)
    for b in range(2):
        assert torch.allclose(mp[b], clarke_matrix(psi[b]), atol=TOL, rtol=0)


# ------------------------------------------------------------------ erratum 1: (I − M_P⁻¹M_P)q = l·1


@pytest.mark.parametrize("n", [3, 4, 6])
def test_erratum1_identity_has_minus_sign(n):
    psi = symmetric_angles(n, 0.3)
    a, mp = paper_mp_inverse(psi), paper_mp(psi)
    length, rho_c = 0.1, np.array([0.004, -0.006])
    q = length * np.ones(n) - a @ rho_c                     # Eq. (q)
    ones = np.ones(n)
    assert np.allclose((np.eye(n) - a @ mp) @ q, length * ones, atol=TOL, rtol=0)      # corrected
    paper = (np.eye(n) + a @ mp) @ q                                                   # Eq. (l_ones)
    assert np.abs(paper - length * ones).max() > 1e-3
    assert np.allclose(paper - length * ones, -2 * a @ rho_c, atol=TOL, rtol=0)
    # Eq. (l_from_l_ones) still gives l here only because 1ᵀM_P⁻¹ = 0 for symmetric joints
    assert np.allclose(ones @ a, 0, atol=TOL)
    assert ones @ paper / n == pytest.approx(length, abs=TOL)


# ------------------------------------------------------------------ erratum 2: arbitrary angles


def random_five_angles(seed: int) -> np.ndarray:
    return np.sort(np.random.default_rng(seed).uniform(0, 2 * np.pi, 5))


@pytest.mark.parametrize("seed", range(5))
def test_erratum2_paper_length_is_wrong_for_arbitrary_angles(seed):
    psi, length = random_five_angles(seed), 0.1
    spec = RobotSpec.from_dict({"segments": [{"type": "I", "length": length, "radius": 0.008,
                                              "joint_angles": psi.tolist()}]})
    a, mp, n = paper_mp_inverse(psi), paper_mp(psi), 5
    beta, rho_c = 0.105, np.array([0.003, -0.002])
    q = beta * np.ones(n) - a @ rho_c                                      # equal radii: A is the paper's
    # Eq. (forward_type-1_q) as printed
    rho_paper = -mp @ q
    beta_paper = np.ones(n) @ (np.eye(n) + a @ mp) @ q / n
    assert abs(beta_paper - beta) > 0.01 * beta, f"paper's length {beta_paper} unexpectedly right"
    assert np.abs(rho_paper - rho_c).max() > 1e-3                          # −M_P·q is biased by β
    assert np.abs(mp @ np.ones(n)).max() > 1e-2 and np.abs(np.ones(n) @ a).max() > 1e-2
    # the project: pseudo-inverse of [−A, 1]
    feat = ClarkeEncoder(spec)(torch.tensor(q)).numpy()[0]
    assert np.allclose(feat[:2], rho_c, atol=TOL, rtol=0)
    assert feat[2] == pytest.approx(beta, abs=TOL)
    w = np.linalg.lstsq(np.c_[-a, np.ones(n)], q, rcond=None)[0]           # independent reference
    assert np.allclose(w, [*rho_c, beta], atol=TOL, rtol=0)


def test_erratum2_straight_length_only():
    """Even with ρ = 0 the paper's length is off by the factor 1 + ‖P·1‖²/n."""
    psi = random_five_angles(0)
    a, mp = paper_mp_inverse(psi), paper_mp(psi)
    q = 0.1 * np.ones(5)
    beta_paper = np.ones(5) @ (np.eye(5) + a @ mp) @ q / 5
    p1 = a @ mp @ np.ones(5)
    assert beta_paper == pytest.approx(0.1 * (1 + p1 @ p1 / 5), abs=TOL)
    assert beta_paper > 0.101


# ------------------------------------------------------------------ erratum 3: type III map


def test_erratum3_printed_type3_matrix_is_mis_sized():
    n = 3
    mp = paper_mp(symmetric_angles(n, 0.0))
    with pytest.raises(ValueError):          # [[−M_P, 0_{n×2}], [0_{2×n}, I₂]] as printed
        np.block([[-mp, np.zeros((n, 2))], [np.zeros((2, n)), np.eye(2)]])


@pytest.mark.parametrize("n,seed", [(3, 0), (4, 1), (6, 2)])
def test_erratum3_encoder_matches_block_diagonal_map(n, seed):
    spec = RobotSpec.from_dict({"segments": [{"type": "III", "length": 0.1, "radius": 0.008, "joints": n,
                                              "offset": 0.2, "limits": {"twist": [-1.0, 1.0]}}]})
    psi, d = symmetric_angles(n, 0.2), 0.008
    a, mp = paper_mp_inverse(psi), paper_mp(psi)
    g = np.random.default_rng(seed)
    block = np.block([[-mp, np.zeros((2, 2))], [np.zeros((2, n)), np.eye(2)]])   # block-diag(−M_P, I₂)
    for _ in range(5):
        rho_c, beta, alpha = g.uniform(-0.01, 0.01, 2), g.uniform(0.08, 0.12), g.uniform(-1, 1)
        q = math.sqrt((alpha * d) ** 2 + beta**2) * np.ones(n) - a @ rho_c     # helical paths, consistent
        expected = block @ np.r_[q, beta, alpha]
        assert np.allclose(expected, [*rho_c, beta, alpha], atol=TOL, rtol=0)
        feat = ClarkeEncoder(spec)(torch.tensor(np.r_[q, alpha])).numpy()[0]
        assert np.allclose(feat, expected, atol=TOL, rtol=0)


# ------------------------------------------------------------------ erratum 4: unequal radii


def test_erratum4_unequal_radii_need_radius_ratio():
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / "asymmetric.yaml")
    seg = spec.segments[0]
    psi, radii, d = np.array(seg.joint_angles), np.array(seg.joint_radii), seg.radius
    assert len(set(seg.joint_radii)) > 1
    theta, phi = 0.7, 0.9
    rho = radii * phi * np.cos(theta - psi)              # CC geometry: displacement of joint i
    rho_c = d * phi * np.array([math.cos(theta), math.sin(theta)])
    # paper: A without d_i/d — neither M_P recovers ρ_c, nor A re-creates ρ
    a_paper, mp_paper = paper_mp_inverse(psi), paper_mp(psi)
    assert np.abs(mp_paper @ rho - rho_c).max() > 1e-4
    assert np.abs(a_paper @ rho_c - rho).max() > 1e-4
    # ours: both directions exact
    mp = clarke_matrix(torch.tensor(psi), torch.tensor(radii), d).numpy()
    a = clarke_matrix_inverse(torch.tensor(psi), torch.tensor(radii), d).numpy()
    assert np.allclose(mp @ rho, rho_c, atol=TOL, rtol=0)
    assert np.allclose(a @ rho_c, rho, atol=TOL, rtol=0)
    q = seg.length - rho
    feat = ClarkeEncoder(spec)(torch.tensor(q)).numpy()[0]
    assert np.allclose(feat, [*rho_c, seg.length, 0.0], atol=TOL, rtol=0)


# ------------------------------------------------------------------ joint_space_maps


def test_joint_space_maps_coupled_block_lower_triangular():
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml")
    maps = joint_space_maps(spec)
    assert maps.displacement.shape == (12, 6) and maps.path.shape == (12, 3)
    for j in range(3):
        rows = slice(4 * j, 4 * j + 4)
        assert torch.all(maps.displacement[rows, 2 * (j + 1):] == 0)
        assert torch.all(maps.path[rows, :j + 1] == 1) and torch.all(maps.path[rows, j + 1:] == 0)
    assert torch.allclose(maps.actuated_pinv @ maps.actuated, torch.eye(9, dtype=torch.float64), atol=1e-12)


# ==================================================================================================
# Errata through the library's own code, float64 and float32
# ==================================================================================================

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
