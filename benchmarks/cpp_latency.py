"""The exported modules called from C++ (cpp/, docs/cpp.md) and from Python, side by side, and the C++ real-time loops.

Exports (unless ``--reuse`` finds them in ``--out``) the FK and Jacobian packages of an FK model of the 3-segment
robot (configs/robots/tdcr_3seg_coupled.yaml; the default network shape, 64 × 4 SiLU, trained for ``--epochs`` on
20,000 samples so that the control loop has a sensible model — latency does not depend on the weights) and its IK
refinement (3 LM iterations), builds the C++
side (``cpp/build.sh``), then

1. batch-1 latency, rounds interleaved: a Python round (``dacr_learn.load_exported`` with its input checks, and the
   package's runner alone) then a C++ round (``dacr_rt bench``: the plain-buffer API), both pinned to ``--cpu``;
   per row the median over rounds of each round's p50 / p99;
2. ``dacr_rt rrc``: resolved-rate control at 1 kHz for ``--seconds`` (a 5 mm circle around the start tip);
3. ``dacr_rt ik``: the warm-started refinement tracking a moving target at 1 kHz for ``--seconds`` (a smooth
   back-and-forth between two random configurations, one lap per 2 s; the targets are written here).

    .venv/bin/python benchmarks/cpp_latency.py [--rounds 7 --calls 1000 --seconds 10 --cpu 1] [--json]
        [--compare OTHER_OUT ...] [--glibc-default]

``--compare``: the packages of other ``--out`` folders (e.g. written by an earlier version) measured in the same
rounds (rows ``*_<folder name>``, and their ratios to this folder's) and in loops of their own (``rrc_<folder name>``,
after this folder's); ``--glibc-default``: the C++ rounds once more with glibc's default malloc cache (rows
``cpp_*_glibc``; ``dacr_rt`` otherwise runs with ``GLIBC_TUNABLES=glibc.malloc.tcache_count=64``, docs/cpp.md).

Targets (the issue's): FK + Jacobian (one ``jacobian`` call gives the pose and both Jacobians) p50 ≤ 25 µs,
p99 ≤ 60 µs; refinement p50 ≤ 200 µs; each loop ≤ 0.1 % overruns.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import lightning
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from dacr_learn import export as dexport  # noqa: E402
from dacr_learn.console import quiet_third_party_warnings, run_cli  # noqa: E402
from dacr_learn.data import generate  # noqa: E402
from dacr_learn.datamodule import KinematicsDataModule  # noqa: E402
from dacr_learn.ik.exported import IKRefinement, export_refinement  # noqa: E402
from dacr_learn.robot import RobotSpec  # noqa: E402
from dacr_learn.training import FKModule  # noqa: E402

ROBOT = ROOT / "configs" / "robots" / "tdcr_3seg_coupled.yaml"
BUILD = ROOT / "cpp" / "build"
TARGETS = {"jacobian_p50_us": 25.0, "jacobian_p99_us": 60.0, "refine_p50_us": 200.0, "overrun_fraction": 1e-3}


def export_packages(out: Path, width: int, depth: int, epochs: int, refine: bool) -> None:
    """The FK model (trained for ``epochs`` on 20,000 samples; 0: random weights) and the refinement, exported."""
    torch.manual_seed(0)
    fk = FKModule(robot=str(ROBOT), features="clarke", width=width, depth=depth, activation="silu", rotation="6d",
                  lr=3e-3, rot_weight=0.1)
    out.mkdir(parents=True, exist_ok=True)
    if epochs:
        dm = KinematicsDataModule(robot=str(ROBOT), n_train=20000, n_val=500, n_test=500, batch_size=256)
        lightning.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                          enable_model_summary=False, accelerator="cpu", devices=1).fit(fk, datamodule=dm)
    else:
        data = generate(fk.spec, 4096, seed=0)
        fk.model.fit_normalization(data["q"], data["pose"])
    torch.save({"state_dict": fk.state_dict(), "hyper_parameters": dict(fk.hparams),
                "pytorch-lightning_version": lightning.__version__}, out / "fk.ckpt")
    dexport.export_checkpoint(out / "fk.ckpt", out / "fk")
    if refine:
        export_refinement(ROBOT, out / "refine", iterations=3)


def write_targets(path: Path, ticks: int, lap_s: float = 2.0, rate: float = 1000.0) -> None:
    """float64: the start joints (N), then one target pose (4 × 4) per tick: x(t) moves between two random admissible
    configurations and back, (1 − cos(2πt / lap)) / 2 of the way (the admissible set is convex)."""
    model = IKRefinement(RobotSpec.from_yaml(ROBOT)).model
    x = model.limits.sample(2, torch.Generator().manual_seed(1))
    t = torch.arange(ticks, dtype=torch.float64) / rate
    w = ((1 - torch.cos(2 * torch.pi * t / lap_s)) / 2).unsqueeze(-1)
    xs = x[:1] + w * (x[1:] - x[:1])
    pos, rot, _ = model.tip_and_jacobian(xs)
    pose = torch.zeros(ticks, 4, 4, dtype=torch.float64)
    pose[:, :3, :3], pose[:, :3, 3], pose[:, 3, 3] = rot, pos, 1.0
    np.concatenate([model.joints(xs[:1])[0].numpy(), pose.numpy().reshape(-1)]).tofile(path)


def python_round(fns: dict, calls: int) -> dict[str, dict[str, float]]:
    out = {}
    for name, fn in fns.items():
        ts = np.empty(calls)
        for i in range(calls):
            t0 = time.perf_counter_ns()
            fn()
            ts[i] = time.perf_counter_ns() - t0
        out[name] = {"p50_us": float(np.percentile(ts, 50)) / 1e3, "p99_us": float(np.percentile(ts, 99)) / 1e3}
    return out


def python_rows(out: Path, targets: Path, refine: bool, compare: list[Path]) -> dict:
    fk, jac = dexport.load(out / "fk", "fk"), dexport.load(out / "fk", "jacobian")
    q = torch.full((1, fk.inputs[0][1][0]), 0.01)
    rows = {"python_fk": lambda: fk(q), "python_jacobian": lambda: jac(q), "python_fk_runner": lambda: fk.runner([q]),
            "python_jacobian_runner": lambda: jac.runner([q])}
    data = np.fromfile(targets)
    if refine:
        ref = dexport.load(out / "refine", "refine")
        n = ref.inputs[1][1][0]
        q0 = torch.from_numpy(data[:n].copy()).unsqueeze(0)
        pose = torch.from_numpy(data[n:n + 16].copy()).reshape(1, 4, 4)
        rows.update(python_refine=lambda: ref(pose, q0), python_refine_runner=lambda: ref.runner([pose, q0]))
    for other in compare:                              # the other folders' packages, through their runners
        for name in ("fk", "jacobian"):
            runner = dexport.load(other / "fk", name).runner
            rows[f"python_{name}_runner_{other.name}"] = (lambda r: lambda: r([q]))(runner)
        if refine:
            runner = dexport.load(other / "refine", "refine").runner
            rows[f"python_refine_runner_{other.name}"] = (lambda r: lambda: r([pose, q0]))(runner)
    with torch.no_grad():
        for fn in rows.values():
            for _ in range(50):
                fn()
    return rows


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "runs" / "cpp_latency"), help="exports, targets and the JSON")
    p.add_argument("--reuse", action="store_true", help="reuse the packages in --out if they are there")
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--depth", type=int, default=4)
    p.add_argument("--epochs", type=int, default=5, help="training epochs of the FK model (0: random weights)")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--calls", type=int, default=1000, help="calls per row and round")
    p.add_argument("--seconds", type=float, default=10.0, help="length of each 1 kHz loop")
    p.add_argument("--cpu", type=int, default=1, help="the CPU both sides are pinned to")
    p.add_argument("--no-refine", action="store_true", help="skip the IK refinement (its package builds for minutes)")
    p.add_argument("--compare", nargs="+", default=[], help="other --out folders measured in the same rounds")
    p.add_argument("--glibc-default", action="store_true", help="C++ rounds with glibc's malloc defaults too")
    p.add_argument("--json", action="store_true", help="one JSON line on stdout")
    args = p.parse_args(argv)
    quiet_third_party_warnings()
    out = Path(args.out)
    refine = not args.no_refine
    wanted = ("fk/fk.aoti.pt2", "fk/jacobian.aoti.pt2") + (("refine/refine.aoti.pt2",) if refine else ())
    have = all((out / f).is_file() for f in wanted)
    if not (args.reuse and have):
        t0 = time.perf_counter()
        export_packages(out, args.width, args.depth, args.epochs, refine)
        print(f"exported in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    t0 = time.perf_counter()
    subprocess.run(["bash", str(ROOT / "cpp" / "build.sh")], check=True, env={**os.environ, "PYTHON": sys.executable},
                   stdout=subprocess.DEVNULL)
    build_s = time.perf_counter() - t0
    targets = out / "targets.bin"
    write_targets(targets, int(round(args.seconds * 1000)))
    torch.set_num_threads(1)
    os.sched_setaffinity(0, {args.cpu})
    compare = [Path(c) for c in args.compare]
    rows = python_rows(out, targets, refine, compare)
    rt = [str(BUILD / "dacr_rt")]

    def package_args(folder: Path) -> list[str]:
        packages = ["--fk", str(folder / "fk" / "fk.aoti.pt2"), "--jacobian", str(folder / "fk" / "jacobian.aoti.pt2")]
        return packages + (["--refine", str(folder / "refine" / "refine.aoti.pt2"), "--targets", str(targets)]
                           if refine else [])
    packages = package_args(out)
    variants = [("", packages, os.environ)]                      # (row suffix, packages, environment)
    variants += [(f"_{other.name}", package_args(other), os.environ) for other in compare]
    if args.glibc_default:        # glibc's own default tcache_count: dacr_rt sees it set and does not re-execute
        variants.append(("_glibc", packages, {**os.environ, "GLIBC_TUNABLES": "glibc.malloc.tcache_count=7"}))
    load = {"before": os.getloadavg()}
    rounds: dict[str, list[dict]] = {}
    setup = None
    for k in range(args.rounds):
        with torch.no_grad():
            for name, r in python_round(rows, args.calls).items():
                rounds.setdefault(name, []).append(r)
        for suffix, pkgs, env in variants[k % len(variants):] + variants[:k % len(variants)]:   # each first in turn
            cpp = json.loads(subprocess.run(rt + ["bench", *pkgs, "--calls", str(args.calls), "--rounds", "1",
                                                  "--cpu", str(args.cpu)],
                                            check=True, capture_output=True, text=True, env=env).stdout)
            setup = setup or {k: cpp[k] for k in ("pinning", "scheduler", "memory", "malloc")}
            for name in ("fk", "jacobian") + (("refine",) if refine else ()):
                rounds.setdefault(f"cpp_{name}{suffix}", []).append({**cpp[name], "new": cpp["new_per_call"][name]})
    latency = {name: {k: float(np.median([r[k] for r in rs])) for k in ("p50_us", "p99_us")}
               for name, rs in rounds.items()}
    for name, rs in rounds.items():
        if "new" in rs[0]:
            latency[name]["new_per_call"] = rs[0]["new"]
    loops = {}
    for suffix, pkgs, _ in variants[:1 + len(compare)]:    # the loops of each folder's packages, one after the other
        for mode, extra in (("rrc", pkgs[2:4]), ("ik", pkgs[4:8]))[:2 if refine else 1]:
            command = rt + [mode, *extra, "--seconds", str(args.seconds), "--cpu", str(args.cpu)]
            run = subprocess.run(command, check=True, capture_output=True, text=True)
            loops[mode + suffix] = json.loads(run.stdout)
    load["after"] = os.getloadavg()
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "loadavg": load, "cpu_count": os.cpu_count(),
              "torch": torch.__version__, "cpp_build_s": build_s, "setup": setup, "latency": latency, "loops": loops,
              "args": vars(args)}
    (out / "cpp_latency.json").write_text(json.dumps(report, indent=2))
    lines = [f"{'row (batch 1)':<34}{'p50 µs':>10}{'p99 µs':>10}{'new/call':>10}"]
    lines += [f"{name:<34}{v['p50_us']:>10.1f}{v['p99_us']:>10.1f}{v.get('new_per_call', float('nan')):>10.0f}"
              for name, v in sorted(latency.items())]
    for other in compare:                  # this folder's packages against each other one's, measured side by side
        for name in ("fk", "jacobian") + (("refine",) if refine else ()):
            mine, theirs = latency[f"cpp_{name}"], latency[f"cpp_{name}_{other.name}"]
            lines.append(f"C++ {name}: {other.name} / this, p50 {theirs['p50_us'] / mine['p50_us']:.2f}×, "
                         f"p99 {theirs['p99_us'] / mine['p99_us']:.2f}×")
    for mode, r in loops.items():
        lines.append(f"loop {mode}: tick p50 {r['tick']['p50_us']:.1f} / p99 {r['tick']['p99_us']:.1f} / max "
                     f"{r['tick']['max_us']:.1f} µs, overruns {r['overruns']} of {r['ticks']} "
                     f"({100 * r['overrun_fraction']:.3f} %), allocations per tick: {r['new_per_tick']:.0f} new, "
                     f"{r['tensor_allocations_per_tick']:.0f} tensors, "
                     f"wake-up late max {r['wakeup_late']['max_us']:.0f} µs")
    lines.append(f"{setup}; load average {load['before'][0]:.1f} → {load['after'][0]:.1f} on {os.cpu_count()} cores")
    print("\n".join(lines), file=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps(report))
    return report


if __name__ == "__main__":
    sys.exit(run_cli(lambda argv=None: main(argv) and None))
