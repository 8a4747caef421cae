"""Benchmark: batched CC forward kinematics vs an equivalent pytorch_kinematics rigid chain.

Both evaluate the same N random single-segment configurations (float32, one CPU thread):

- ours: ``dacr_learn.kinematics.forward_kinematics(spec, features)`` with features (N, 1, 4);
- reference: a URDF chain rz θ, ry φ/2, prismatic z (chord 2β·sin(φ/2)/φ), ry φ/2, rz −θ,
  evaluated by ``pytorch_kinematics`` with 5 joint values per sample (precomputed, not timed).

Reports the median wall time of several interleaved repeats, the speed ratio (of the medians, and
of the best times as a load-insensitive check), the max abs difference of the 4×4 poses, and the
Clarke encoder throughput for a coupled 3-segment TDCR.

    .venv/bin/python benchmarks/kinematics.py            # readable table
    .venv/bin/python benchmarks/kinematics.py --json     # also one JSON line
"""
from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import platform
import statistics
from pathlib import Path

import pytorch_kinematics as pk
import torch
from timing import time_interleaved

from dacr_learn.kinematics import forward_kinematics
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]
SEGMENT_CONFIG = ROOT / "configs" / "robots" / "type1.yaml"
ENCODER_CONFIG = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
TARGET_SPEEDUP, TARGET_AGREEMENT = 30.0, 1e-5

_LIMIT = '<limit lower="-100" upper="100" effort="1" velocity="1"/>'
_JOINTS = [("revolute", "0 0 1"), ("revolute", "0 1 0"), ("prismatic", "0 0 1"),
           ("revolute", "0 1 0"), ("revolute", "0 0 1")]


def equivalent_chain(dtype: torch.dtype) -> pk.SerialChain:
    """Rigid-link chain whose tip pose equals one constant-curvature segment."""
    links = "".join(f'<link name="l{i}"/>' for i in range(6))
    joints = "".join(f'<joint name="j{i}" type="{kind}"><parent link="l{i}"/><child link="l{i + 1}"/>'
                     f'<axis xyz="{axis}"/>{_LIMIT}</joint>' for i, (kind, axis) in enumerate(_JOINTS))
    urdf = f'<robot name="cc_segment">{links}{joints}</robot>'
    return pk.build_serial_chain_from_urdf(urdf, "l5").to(dtype=dtype)


def random_configurations(spec: RobotSpec, n: int, seed: int, dtype: torch.dtype):
    """N features (N, 1, 4) uniform over the segment's limits, and the chain's joint values (N, 5)."""
    seg = spec.segments[0]
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(n, 3, generator=g, dtype=torch.float64)
    phi, theta = seg.bend * torch.sqrt(r[:, 0]), 2 * math.pi * r[:, 1]
    lo, hi = seg.length_range or (seg.length, seg.length)
    beta = lo + (hi - lo) * r[:, 2]
    feat = torch.stack([seg.radius * phi * torch.cos(theta), seg.radius * phi * torch.sin(theta),
                        beta, torch.zeros_like(beta)], dim=-1).unsqueeze(1)
    chord = beta * torch.sinc(phi / (2 * math.pi))
    joints = torch.stack([theta, phi / 2, chord, phi / 2, -theta], dim=-1)
    return feat.to(dtype), joints.to(dtype)


def run(n: int, repeats: int, seed: int) -> dict:
    torch.set_num_threads(1)
    dtype = torch.float32
    spec = RobotSpec.from_yaml(SEGMENT_CONFIG)
    feat, joints = random_configurations(spec, n, seed, dtype)
    chain = equivalent_chain(dtype)

    with torch.inference_mode():
        ours = forward_kinematics(spec, feat)
        ref = chain.forward_kinematics(joints).get_matrix()
        max_diff = (ours - ref).abs().max().item()
        times = time_interleaved({"ours": lambda: forward_kinematics(spec, feat),
                                  "pytorch_kinematics": lambda: chain.forward_kinematics(joints).get_matrix()},
                                 repeats)

        enc_spec = RobotSpec.from_yaml(ENCODER_CONFIG)
        enc = ClarkeEncoder(enc_spec)
        enc_feat = torch.stack([random_configurations(RobotSpec.from_dict({"segments": [s.to_dict()]}),
                                                      n, seed + k, dtype)[0][:, 0]
                                for k, s in enumerate(enc_spec.segments)], dim=1)
        q = ClarkeDecoder(enc_spec)(enc_feat)
        enc_err = (enc(q) - enc_feat).abs().max().item()
        enc_times = time_interleaved({"encoder": lambda: enc(q)}, repeats)["encoder"]

    med = {k: statistics.median(v) for k, v in times.items()}
    enc_med = statistics.median(enc_times)
    return {
        "n": n, "repeats": repeats, "dtype": "float32", "threads": torch.get_num_threads(),
        "torch": torch.__version__, "pytorch_kinematics": importlib.metadata.version("pytorch-kinematics"),
        "cpu": platform.processor() or platform.machine(),
        "fk_ours_s": med["ours"], "fk_pk_s": med["pytorch_kinematics"],
        "fk_ours_all_s": times["ours"], "fk_pk_all_s": times["pytorch_kinematics"],
        "speedup": med["pytorch_kinematics"] / med["ours"],
        "speedup_best": min(times["pytorch_kinematics"]) / min(times["ours"]), "max_abs_diff": max_diff,
        "encoder_robot": enc_spec.name, "encoder_batch": n, "encoder_s": enc_med,
        "encoder_per_s": n / enc_med, "encoder_max_abs_err": enc_err,
    }


def print_table(r: dict) -> None:
    rows = [
        ("forward kinematics, ours", f"{r['fk_ours_s'] * 1e3:9.2f} ms",
         f"{r['n'] / r['fk_ours_s'] / 1e6:8.2f} M poses/s"),
        ("forward kinematics, pytorch_kinematics", f"{r['fk_pk_s'] * 1e3:9.2f} ms",
         f"{r['n'] / r['fk_pk_s'] / 1e6:8.2f} M poses/s"),
        (f"Clarke encoder, {r['encoder_robot']}", f"{r['encoder_s'] * 1e3:9.2f} ms",
         f"{r['encoder_per_s'] / 1e6:8.2f} M joint vectors/s"),
    ]
    print(f"N = {r['n']} configurations, {r['dtype']}, {r['threads']} thread, median of {r['repeats']} "
          f"repeats (torch {r['torch']}, {r['cpu']})")
    print(f"{'':42s} {'median':>12s} {'throughput':>24s}")
    for name, t, thr in rows:
        print(f"{name:42s} {t:>12s} {thr:>24s}")
    ok_speed = "ok" if r["speedup"] >= TARGET_SPEEDUP else f"BELOW target {TARGET_SPEEDUP:.0f}x"
    ok_diff = "ok" if r["max_abs_diff"] <= TARGET_AGREEMENT else f"ABOVE target {TARGET_AGREEMENT:g}"
    print(f"speed ratio (pytorch_kinematics / ours): {r['speedup']:.1f}x of medians   [{ok_speed}]"
          f"   ({r['speedup_best']:.1f}x of best times)")
    print(f"max |pose difference|: {r['max_abs_diff']:.2e}   [{ok_diff}]")
    print(f"encoder round-trip max error (float32): {r['encoder_max_abs_err']:.2e} m")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=100_000, help="number of configurations (batch size)")
    p.add_argument("--repeats", type=int, default=11, help="timed repeats per method (median reported)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="also print the results as one JSON line")
    args = p.parse_args()
    result = run(args.n, args.repeats, args.seed)
    print_table(result)
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
