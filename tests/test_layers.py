"""ClarkeEncoder / ClarkeDecoder: geometric reference, round trips, least squares, autograd, batching."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import (
    FAST,
    ROBOT_CONFIGS,
    random_features,
    reference_actuated_matrix,
    reference_joint_vector,
    robot_dicts,
    robots,
    roundoff_tol,
    seeds,
)
from hypothesis import given

from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.robot import RobotSpec

F64 = torch.float64


def layers(spec):
    return ClarkeEncoder(spec), ClarkeDecoder(spec)


# ---------------------------------------------------------------- decoder vs geometry, round trips


@FAST
@given(robots(), seeds)
def test_decoder_matches_geometric_reference(spec, seed):
    feat = random_features(spec, (4,), seed)
    q = ClarkeDecoder(spec)(feat)
    assert q.shape == (4, spec.num_joints) and q.dtype == F64
    for b in range(4):
        ref = reference_joint_vector(spec, feat[b].numpy())
        assert np.allclose(q[b].numpy(), ref, atol=1e-12, rtol=0)


@FAST
@given(robots(), seeds)
def test_round_trip_features_joints_features(spec, seed):
    enc, dec = layers(spec)
    feat = random_features(spec, (8,), seed)
    q = dec(feat)
    back = enc(q)
    assert back.shape == feat.shape
    assert (back - feat).abs().max() <= 1e-10
    assert (dec(back) - q).abs().max() <= 1e-10


@FAST
@given(robots(), seeds)
def test_round_trip_from_geometric_joint_vector(spec, seed):
    """The encoder inverts the independent reference (not only our own decoder)."""
    feat = random_features(spec, (3,), seed)
    q = torch.tensor(np.stack([reference_joint_vector(spec, f.numpy()) for f in feat]))
    assert (ClarkeEncoder(spec)(q) - feat).abs().max() <= 1e-10


@pytest.mark.parametrize("seg_type", ["0", "I", "II", "III"])
@pytest.mark.parametrize("routing", ["independent", "coupled"])
@pytest.mark.parametrize("layout", ["symmetric", "arbitrary"])
def test_round_trip_every_type_routing_layout(seg_type, routing, layout):
    """Deterministic coverage of each combination (hypothesis above samples them at random)."""
    def seg(t, k):
        d = {"type": t, "length": 0.1 - 0.01 * k, "radius": 0.008}
        if layout == "symmetric":
            d.update(joints=3 + k, offset=0.3 * k)
        else:
            n = 4 + k
            d["joint_angles"] = [2 * math.pi * (i + 0.3 * math.sin(3 * i + k)) / n for i in range(n)]
            d["joint_radii"] = ([0.009] * n if t in ("II", "III")
                                else [0.008 * (1 + 0.3 * math.cos(2 * i + k)) for i in range(n)])
        return d
    first = "I" if routing == "coupled" else seg_type
    spec = RobotSpec.from_dict({"routing": routing, "segments": [seg(first, 0), seg("0", 1), seg(seg_type, 2)]})
    enc, dec = layers(spec)
    feat = random_features(spec, (16,), 7)
    q = torch.tensor(np.stack([reference_joint_vector(spec, f.numpy()) for f in feat]))
    assert (dec(feat) - q).abs().max() <= 1e-12
    assert (enc(q) - feat).abs().max() <= 1e-10


# ---------------------------------------------------------------- least squares


def fixed_lengths(spec: RobotSpec, feat: np.ndarray) -> np.ndarray:
    """q₀: the known part of every joint length (helix lengths of the non-extending segments)."""
    q0 = []
    for j, seg in enumerate(spec.segments):
        passed = range(j + 1) if spec.routing == "coupled" else (j,)
        for di in seg.joint_radii:
            q0.append(sum(math.sqrt((feat[k, 3] * di) ** 2 + spec.segments[k].length ** 2)
                          for k in passed if not spec.segments[k].extends))
    return np.array(q0)


@FAST
@given(robots(), seeds)
def test_encoder_is_least_squares_projection(spec, seed):
    enc, dec = layers(spec)
    feat = random_features(spec, (4,), seed)
    q = dec(feat)
    n_len = spec.num_length_joints
    noise = 1e-4 * torch.randn(q.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)
    noise[..., n_len:] = 0                                   # α is measured directly
    q_noisy = q + noise
    est = enc(q_noisy)
    proj = dec(est)
    w_mat = reference_actuated_matrix(spec)
    ext = [k for k, s in enumerate(spec.segments) if s.extends]
    for b in range(4):
        f = est[b].numpy()
        # residual is orthogonal to the range of W (normal equations)
        resid = (q_noisy[b] - proj[b]).numpy()[:n_len]
        assert np.abs(w_mat.T @ resid).max() <= 1e-12
        # twist entries are copied through encoder and decoder, no arithmetic: exact on any CPU
        assert np.array_equal(proj[b].numpy()[n_len:], q_noisy[b].numpy()[n_len:])
        # and the estimate equals numpy's least-squares solution
        target = q_noisy[b].numpy()[:n_len] - fixed_lengths(spec, f)
        w_ref = np.linalg.lstsq(w_mat, target, rcond=None)[0]
        assert np.allclose(f[:, :2].reshape(-1), w_ref[:2 * spec.num_segments], atol=1e-10, rtol=0)
        for c, k in enumerate(ext):
            helix_r = spec.segments[k].joint_radii[0]
            beta_ref = math.sqrt(w_ref[2 * spec.num_segments + c] ** 2 - (f[k, 3] * helix_r) ** 2)
            assert f[k, 2] == pytest.approx(beta_ref, abs=1e-10)
    # the projection is idempotent
    assert (enc(proj) - est).abs().max() <= 1e-10


@FAST
@given(robot_dicts(types=("0",), routing="independent"), seeds)
def test_common_mode_offsets_vanish_symmetric_type0(d, seed):
    for seg in d["segments"]:                               # force symmetric layouts
        for key in ("joint_angles", "joint_radii"):
            seg.pop(key, None)
        seg.setdefault("joints", 4)
    spec = RobotSpec.from_dict(d)
    enc, dec = layers(spec)
    g = torch.Generator().manual_seed(seed)
    q = dec(random_features(spec, (5,), seed))
    offsets = torch.cat([torch.full((s.num_joints,), float(c)) for s, c in
                         zip(spec.segments, 0.01 * torch.randn(spec.num_segments, generator=g), strict=True)]).to(F64)
    shifted = enc(q + offsets + 0.003)
    # exact in exact arithmetic (M_P·1 = 0); rounding of the ~0.1 m lengths is all that may remain
    assert (shifted[..., :2] - enc(q)[..., :2]).abs().max() <= roundoff_tol(F64, float(q.abs().max()), ulps=1024)


# ---------------------------------------------------------------- autograd


GRAD_CONFIGS = ["tdcr_3seg_coupled", "type3", "asymmetric", "type1"]


def config(stem: str) -> RobotSpec:
    return RobotSpec.from_yaml(next(p for p in ROBOT_CONFIGS if p.stem == stem))


def mixed_robot() -> RobotSpec:
    return RobotSpec.from_dict({"segments": [
        {"type": "II", "length": 0.1, "radius": 0.008, "joints": 3},
        {"type": "III", "length": 0.08, "radius": 0.006, "joint_angles": [0, 2.2, 4.0], "joint_radii": [0.007] * 3},
        {"type": "I", "length": 0.07, "radius": 0.006, "joint_angles": [0.1, 2.0, 3.5, 5.0],
         "joint_radii": [0.005, 0.006, 0.007, 0.006]}]})


@pytest.mark.parametrize("straight", [False, True], ids=["generic", "straight"])
@pytest.mark.parametrize("which", GRAD_CONFIGS + ["mixed"])
def test_gradcheck_encoder_decoder(which, straight):
    spec = mixed_robot() if which == "mixed" else config(which)
    enc, dec = layers(spec)
    feat = random_features(spec, (2,), 3, straight=straight).requires_grad_(True)
    assert torch.autograd.gradcheck(dec, (feat,))
    q = dec(feat).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(enc, (q,))
    grad, = torch.autograd.grad(enc(q).sum(), q)
    assert torch.isfinite(grad).all()


# ---------------------------------------------------------------- batching, dtype, device


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_leading_batch_dims(batch):
    spec = mixed_robot()
    enc, dec = layers(spec)
    feat = random_features(spec, batch, 11)
    q = dec(feat)
    assert q.shape == (*batch, spec.num_joints)
    assert enc(q).shape == (*batch, spec.num_segments, 4)
    assert (enc(q) - feat).abs().max() <= 1e-10


@FAST
@given(robots(), seeds)
def test_batched_equals_per_sample_loop(spec, seed):
    enc, dec = layers(spec)
    feat = random_features(spec, (2, 3), seed)
    q = dec(feat)
    est = enc(q + 1e-4 * torch.randn(q.shape, generator=torch.Generator().manual_seed(seed), dtype=F64))
    tol = roundoff_tol(F64, float(q.abs().max()))   # joint lengths [m]; a least-squares encoder: more roundings
    for i in range(2):
        for j in range(3):
            assert torch.allclose(dec(feat[i, j]), q[i, j], atol=tol, rtol=0)
            noisy = q[i, j] + 1e-4 * torch.randn(q.shape, generator=torch.Generator().manual_seed(seed),
                                                 dtype=F64)[i, j]
            assert torch.allclose(enc(noisy), est[i, j], atol=16 * tol, rtol=0)


@pytest.mark.parametrize("stem", GRAD_CONFIGS)
def test_float32_follows_input_and_is_accurate(stem):
    spec = config(stem)
    enc, dec = layers(spec)
    feat64 = random_features(spec, (64,), 5)
    feat32 = feat64.float()
    q32 = dec(feat32)
    assert q32.dtype == torch.float32 and q32.device == feat32.device
    assert (q32.double() - dec(feat64)).abs().max() <= 1e-6
    est32 = enc(q32)
    assert est32.dtype == torch.float32
    assert (est32.double() - feat64).abs().max() <= 5e-5       # float32 cancellation in q − q₀


@pytest.mark.parametrize("to", [torch.float64, torch.float32])
def test_module_to_dtype(to):
    spec = mixed_robot()
    enc, dec = (m.to(to) for m in layers(spec))
    feat = random_features(spec, (3,), 1)
    out = enc(dec(feat))
    assert out.dtype == F64
    assert (out - feat).abs().max() <= (1e-10 if to == torch.float64 else 1e-5)
    assert dec(feat.float()).dtype == torch.float32


def test_buffers_follow_module_device_and_state_dict():
    enc = ClarkeEncoder(mixed_robot())
    names = dict(enc.named_buffers())
    assert {"actuated_pinv", "displacement", "path"} <= set(names)
    assert not list(enc.parameters())
    restored = ClarkeEncoder(mixed_robot())
    restored.load_state_dict(enc.state_dict())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_device_follows_input():
    spec = mixed_robot()
    enc, dec = (m.cuda() for m in layers(spec))
    feat = random_features(spec, (4,), 2).cuda()
    q = dec(feat)
    assert q.device == feat.device and enc(q).device == feat.device
    assert (enc(q) - feat).abs().max().item() <= 1e-10


# ---------------------------------------------------------------- invalid inputs


def bad_inputs(trailing: tuple[int, ...]):
    good = torch.ones(2, *trailing, dtype=F64)
    nan, inf = good.clone(), good.clone()
    nan[0, ...] = math.nan
    inf.view(-1)[1] = math.inf
    wrong = torch.ones(2, *trailing[:-1], trailing[-1] + 1, dtype=F64)
    short = torch.ones(2, *trailing[:-1], trailing[-1] - 1, dtype=F64)
    return {"nan": nan, "inf": inf, "too-long": wrong, "too-short": short,
            "scalar": torch.tensor(1.0, dtype=F64), "int": good.long()}


@pytest.mark.parametrize("kind", ["nan", "inf", "too-long", "too-short", "scalar", "int"])
def test_encoder_decoder_reject_bad_tensors(kind):
    spec = config("tdcr_3seg_coupled")
    enc, dec = layers(spec)
    for module, trailing in ((enc, (spec.num_joints,)), (dec, (spec.num_segments, 4))):
        x = bad_inputs(trailing)[kind]
        with pytest.raises(ValueError) as err:
            module(x)
        msg = str(err.value)
        if kind == "int":
            assert "floating" in msg and "int64" in msg, msg
            continue
        assert str(tuple(x.shape)) in msg, msg                                    # received shape
        if kind in ("nan", "inf"):
            assert "finite" in msg and "NaN/inf" in msg, msg
        else:
            assert f"expected shape (..., {', '.join(map(str, trailing))})" in msg, msg   # expected shape
