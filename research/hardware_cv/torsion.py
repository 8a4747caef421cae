"""Torsion from straight-routed tendons in the slack-aware CC model: the distributed torsional
moment on segment k is d·Σ_tendons T_i κ_k × ê_i = cross(ρ_k, Σ_{j≥k} F_j), with F_j the tendon
force vector of segment j. At the encoder's equilibrium each segment bends along the total tendon
force through it, so the cross product vanishes: the model predicts no twist. This script checks
that numerically (max |moment| relative to its scale), on train and on FTDCR v4's val.

Numbers: docs/history/hardware.md, "2026-11-21: Second round: hysteresis physics, selected by
cross-validation on train" (row `torsion.py`: relative moment ≤ 4e-12). ~5 s.
Run from the repository root: python -m research.hardware_cv.torsion
"""

import torch

from .common import fit, setup, val_data


def cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def main() -> None:
    torch.set_num_threads(1)
    d = setup()
    m = d.m
    cc = fit(d.x_tr, d.tip_tr)
    enc = cc.encoder
    for name, x in (("train", d.x_tr), ("val", val_data()[0])):
        with torch.no_grad():
            rho = enc.clarke(x)  # (n, m, 2)
            g = enc.displacement_map()  # (N, 2m)
            tension = (x + enc.pretension - rho.flatten(-2) @ g.mT).clamp_min(0) / enc.path_length
            own = g.unflatten(-1, (m, 2))[torch.arange(g.shape[0]), enc.segment_of_joint]
            direction = own / own.norm(dim=-1, keepdim=True)  # (N, 2) joint angle
            onehot = torch.nn.functional.one_hot(enc.segment_of_joint, m).to(x.dtype)
            force = torch.einsum("ni,ij,ic->njc", tension, onehot, direction)  # (n, m, 2)
            through = force.flip(-2).cumsum(-2).flip(-2)  # Σ_{j≥k}
            moment = cross(rho, through)
            scale = rho.norm(dim=-1) * through.norm(dim=-1)
        worst = float((moment.abs() / scale.clamp_min(1e-30)).max())
        print(f"{name}: max |cross(rho_k, F_through_k)| / (|rho_k| |F|) = {worst:.2e}")


if __name__ == "__main__":
    main()
