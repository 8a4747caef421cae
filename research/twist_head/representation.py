"""Diagnosis (issue 22): can a twist that is affine in a twisting segment's strain-unit features give its
transform Rz(α)·T_cc exactly?  Least-squares affine fit of log(T_k) against x_k = (ρ/d, β/l, α), k a type-II/III
segment of hetero_4seg_types, and the pose error of exp(fit); the same for log(Rz(−α)·T_k) (the twist left
once the roll α is applied first). Numbers: docs/history/compositional.md, "Twisting segments: the roll (2026-11-26)".

    .venv/bin/python -m research.twist_head.representation
"""
import torch

from dacr_learn.data import generate
from dacr_learn.kinematics import effective_features, segment_poses
from dacr_learn.lie import bending_coefficients, hat, third_coefficient, twist_exp, vee
from dacr_learn.robot import RobotSpec

F64 = torch.float64


def twist_log(t):
    r, p = t[..., :3, :3], t[..., :3, 3]
    cos = ((r.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    phi = torch.acos(cos)
    w = vee(r) * (phi / torch.sin(phi).clamp_min(1e-300)).unsqueeze(-1)
    s, f = bending_coefficients(phi**2)
    g = third_coefficient(phi**2, s)
    wh = hat(w)
    v_mat = torch.eye(3, dtype=t.dtype) + f[..., None, None] * wh + g[..., None, None] * wh @ wh
    v = torch.linalg.solve(v_mat, p.unsqueeze(-1)).squeeze(-1)
    return torch.cat([v, w], -1)


def rz(alpha):
    c, s = torch.cos(alpha), torch.sin(alpha)
    out = torch.zeros(*alpha.shape, 4, 4, dtype=alpha.dtype)
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = out[..., 3, 3] = 1
    return out


def fit_error(x, t, length):
    xi = twist_log(t)
    xi[..., :3] /= length
    a = torch.cat([x, torch.ones_like(x[..., :1])], -1)
    coef = torch.linalg.pinv(a) @ xi                                   # rank-deficient: constant columns
    fit = a @ coef
    fit[..., :3] *= length
    t_hat = twist_exp(fit)
    pos = (t_hat[..., :3, 3] - t[..., :3, 3]).norm(dim=-1)
    rel = t_hat[..., :3, :3].mT @ t[..., :3, :3]
    ang = torch.acos(((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    return pos, torch.rad2deg(ang), coef


def main():
    spec = RobotSpec.from_yaml("configs/robots/hetero_4seg_types.yaml")
    data = generate(spec, 20000, seed=0, dtype=F64)
    feats = effective_features(spec, data["features"])
    poses = segment_poses(spec, data["features"])
    for k, seg in enumerate(spec.segments):
        x = feats[:, k] / torch.tensor([seg.radius, seg.radius, seg.length, 1.0], dtype=F64)
        t = poses[:, k]
        check = (twist_exp(twist_log(t)) - t).abs().max().item()
        pos, ang, _ = fit_error(x, t, seg.length)
        line = (f"segment {k} type {seg.type:3s}: affine twist -> T_k: "
                f"pos {pos.mean() / seg.length * 100:.4f} % of l_k ({pos.mean() * 1e3:.4f} mm, "
                f"max {pos.max() * 1e3:.3f}), rot {ang.mean():.4f} deg (max {ang.max():.3f})")
        if seg.twists:
            pos2, ang2, _ = fit_error(x, rz(-x[:, 3]) @ t, seg.length)
            line += f"; Rz(alpha)*exp(affine twist): pos {pos2.mean() * 1e3:.2e} mm, rot {ang2.mean():.2e} deg"
        print(line, f"[log check {check:.1e}]")


if __name__ == "__main__":
    main()
