"""Latency of the controller-facing inference modules: one thread, batch 1, many calls.

Builds the default FK model (the shape of configs/default.yaml; an IK model of the same shape;
weights are random, normalisation fitted on sampled data — latency does not depend on them),
writes them as checkpoints, exports them with ``dacr_learn.export`` (torch.export programs and
AOTInductor packages) and times, interleaved round by round on one CPU thread:

- ``fk_eager_lightning``: the Lightning model's FKModel (front-end + MLP + 6D head), eager;
- ``fk_eager_folded``: dacr_learn.deploy.inference.InferenceFK (folded front-end), eager;
- ``fk_export_program``: the ``fk.pt2`` torch.export program as loaded by ``export.load``;
- ``fk_aoti``: the ``fk.aoti.pt2`` AOTInductor package via ``export.load`` (input checks included);
- ``fk_aoti_runner``: the same package's C++ runner called directly (no checks, no reshapes);
- ``jacobian_eager`` / ``jacobian_aoti``, ``ik_eager_lightning`` / ``ik_aoti``;
- ``cc_fk_analytic``: dacr_learn.kinematics.forward_kinematics on a (1, m, 4) feature tensor;
- ``fk_torch_compile`` (with ``--compile``): torch.compile(InferenceFK, mode="max-autotune-no-cudagraphs");
- ``fk_compositional_{eager_lightning, eager_folded, export_program, aoti}``: the compositional FK of
  configs/fk_tdcr3_compositional.yaml (3-segment robot: per-segment network, twist head, products),
  exported the same way, and ``jacobian_compositional_{export_program, aoti}``: its Jacobian module
  (pose, J_f, J_q; ``--no-compositional`` skips these rows).
- ``hardware_{fk_eager, fk_export_program, jacobian_export_program, fk_aoti, fk_aoti_runner,
  jacobian_aoti}``: a hardware model (servo commands [mm] + play state → tip, tip_std, new state;
  dacr_learn.hardware.deploy.inference) of FTDCR v4's shape — the registry's
  ``cc_clarke_residual_history``, ``--hardware-members`` ensemble members, untrained (latency does
  not depend on the weights), or a saved model (``--hardware-ckpt``) — exported with
  ``dacr_learn.export`` (AOTInductor for ``fk`` and ``jacobian``). ``hardware_fk_vs_fk`` in the JSON
  and the side-by-side table: each hardware FK row's p50 next to the synthetic FK's row of the same
  kind (eager: ``fk_eager_folded``), measured in the same run, and their ratio (target ≤ 2 for the
  exported rows). ``--no-hardware`` skips these rows. Beside them ``hardware_fk_generated_{export_program,
  aoti}``: the same model's FK generated from its eager code (benchmarks/generated_fk.py), the
  same inputs (its package called through the C++ runner, like ``hardware_fk_aoti_runner``).

Every call is timed on its own (perf_counter_ns); reported are p50 and p99 over all calls [µs] (``calls`` in the
JSON: a row slower than ``--round-seconds`` / ``--calls`` per call runs fewer calls per round).
The machine may be shared and noisy: compare medians, run it twice.

    .venv/bin/python benchmarks/latency.py            # table
    .venv/bin/python benchmarks/latency.py --json     # one JSON line on stdout (table on stderr)
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import lightning
import numpy as np
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from timing import time_interleaved  # noqa: E402

from dacr_learn import export as dexport  # noqa: E402
from dacr_learn.console import quiet_third_party_warnings, run_cli  # noqa: E402
from dacr_learn.data import generate  # noqa: E402
from dacr_learn.deploy.inference import InferenceFK, InferenceJacobian  # noqa: E402
from dacr_learn.deploy.inference_compositional import InferenceCompositionalFK  # noqa: E402
from dacr_learn.kinematics import forward_kinematics  # noqa: E402
from dacr_learn.layers import ClarkeEncoder  # noqa: E402
from dacr_learn.training import FKModule, IKModule  # noqa: E402

DEFAULT_CONFIG = ROOT / "configs" / "default.yaml"
HARDWARE_ROBOT = ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml"
HARDWARE_TRAIN = ROOT / "data" / "ftdcr_v4" / "train.csv"
HARDWARE_RATIO_TARGET = 2.0
COMPOSITIONAL_CONFIG = ROOT / "configs" / "fk_tdcr3_compositional.yaml"
TARGETS_US = {"fk_aoti": 25.0, "jacobian_aoti": 80.0}


def default_modules(config: Path) -> tuple[FKModule, IKModule]:
    """FK and IK LightningModules of the config's shape, normalisation fitted on 4096 samples."""
    cfg = yaml.safe_load(config.read_text())
    args, robot = dict(cfg["model"]["init_args"]), str(ROOT / cfg["data"]["robot"])
    torch.manual_seed(0)
    fk = FKModule(robot=robot, **args)
    ik = IKModule(robot=robot, **{k: v for k, v in args.items() if k not in ("rotation", "rot_weight")})
    data = generate(fk.spec, 4096, seed=0)
    fk.model.fit_normalization(data["q"], data["pose"])
    ik.model.fit_normalization(data["q"], data["pose"])
    return fk.eval(), ik.eval()


def save_checkpoint(module: lightning.LightningModule, path: Path) -> Path:
    """A minimal Lightning checkpoint (weights + hyper-parameters) that load_from_checkpoint accepts."""
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": lightning.__version__}, path)
    return path


def export_all(fk: FKModule, ik: IKModule, out: Path, aoti: bool, autotune: bool = False) -> dict[str, float]:
    """Export both checkpoints into out/fk and out/ik; returns seconds spent per export."""
    seconds = {}
    for name, module in (("fk", fk), ("ik", ik)):
        t0 = time.perf_counter()
        dexport.export_checkpoint(save_checkpoint(module, out / f"{name}.ckpt"), out / name, aoti=aoti,
                                  autotune=autotune and aoti)
        seconds[name] = time.perf_counter() - t0
    return seconds


def candidates(fk: FKModule, ik: IKModule, out: Path, aoti: bool, compile_fk: bool) -> dict:
    """name → zero-argument callable doing one batch-1 call."""
    spec = fk.spec
    data = generate(spec, 1, seed=7)
    q, pose = data["q"], data["pose"]
    features = ClarkeEncoder(spec)(q)
    folded, jac = InferenceFK(fk.model).eval(), InferenceJacobian(fk.model).eval()
    fns = {"cc_fk_analytic": lambda: forward_kinematics(spec, features),
           "fk_eager_lightning": lambda: fk.model(q), "fk_eager_folded": lambda: folded(q),
           "fk_export_program": _bound(dexport.load(out / "fk" / "fk.pt2"), q),
           "jacobian_eager": lambda: jac(q), "ik_eager_lightning": lambda: ik.model(pose)}
    if aoti:
        loaded = dexport.load(out / "fk", "fk")
        fns.update(fk_aoti=_bound(loaded, q), fk_aoti_runner=_bound(loaded.runner, [q.contiguous()]),
                   jacobian_aoti=_bound(dexport.load(out / "fk", "jacobian"), q),
                   ik_aoti=_bound(dexport.load(out / "ik", "ik"), pose))
    if compile_fk:
        compiled = torch.compile(folded, mode="max-autotune-no-cudagraphs", dynamic=False)
        fns["fk_torch_compile"] = _bound(compiled, q)
    return fns


def compositional_candidates(config: Path, out: Path, aoti: bool, autotune: bool = False) -> dict:
    """Rows of the compositional FK (the config's shape, 3-segment robot; random weights): Lightning
    model, folded module, export program and AOTInductor package (``fk_compositional_*``)."""
    cfg = yaml.safe_load(config.read_text())
    torch.manual_seed(0)
    fk = FKModule(robot=str(ROOT / cfg["data"]["robot"]), **cfg["model"]["init_args"])
    fk.model.fit_normalization(generate(fk.spec, 4096, seed=0)["q"])
    fk.eval()
    dexport.export_checkpoint(save_checkpoint(fk, out / "fk_compositional.ckpt"), out / "fk_compositional", aoti=aoti,
                              autotune=autotune and aoti)
    q = generate(fk.spec, 1, seed=7)["q"]
    folded = InferenceCompositionalFK(fk.model).eval()
    fns = {"fk_compositional_eager_lightning": _bound(fk.model, q), "fk_compositional_eager_folded": _bound(folded, q),
           "fk_compositional_export_program": _bound(dexport.load(out / "fk_compositional" / "fk.pt2"), q)}
    fns["jacobian_compositional_export_program"] = _bound(dexport.load(out / "fk_compositional" / "jacobian.pt2"), q)
    if aoti:
        fns["fk_compositional_aoti"] = _bound(dexport.load(out / "fk_compositional", "fk"), q)
        fns["jacobian_compositional_aoti"] = _bound(dexport.load(out / "fk_compositional", "jacobian"), q)
    return fns


def hardware_checkpoint(out: Path, members: int) -> Path:
    """A saved hardware model of FTDCR v4's shape: the registry's cc_clarke_residual_history, ``members``
    untrained members on an uncalibrated CC model (latency does not depend on the weights)."""
    from dacr_learn.hardware.ccmodel import CalibratedCC
    from dacr_learn.hardware.deploy.checkpoint import HardwareModel, save_hardware_model
    from dacr_learn.hardware.learned import make_split
    from dacr_learn.hardware.recording import load_recording
    from dacr_learn.hardware.study.benchmark import resolve_robot
    from dacr_learn.hardware.study.registry import FitContext, build_model

    spec, smap, _ = resolve_robot(HARDWARE_ROBOT, None, None, out, "mm")
    rec = load_recording(HARDWARE_TRAIN, spec, "mm")
    cc = CalibratedCC(spec).requires_grad_(False)
    ctx = FitContext(cc, smap, rec.servo_ids, make_split(rec, spec, smap, cc))
    nets = [build_model("cc_clarke_residual_history", ctx, seed).eval() for seed in range(members)]
    model = HardwareModel("cc_clarke_residual_history", spec, smap, rec.servo_ids, cc, nets,
                          examples=1e3 * rec.servo[::25])
    return save_hardware_model(model, out / "hardware.pt")


def hardware_candidates(ckpt: Path, out: Path, aoti: bool, autotune: bool = False) -> dict:
    """Rows of a hardware model (``hardware_*``), batch 1: servo (1, S) [mm] and play state (1, m, 2)."""
    from dacr_learn.hardware.deploy.checkpoint import load_hardware_model
    from dacr_learn.hardware.deploy.export import modules

    dexport.export_checkpoint(ckpt, out / "hardware", aoti=("fk", "jacobian") if aoti else False,
                              autotune=autotune and aoti)
    model = load_hardware_model(ckpt)
    fk = modules(model, torch.float32)["fk"]          # HardwareFK, or the compositional model's FK
    servo = (model.examples[len(model.examples) // 2:][:1] if model.examples is not None else
             torch.zeros(1, len(model.servo_ids))).float()
    args = (servo, fk.initial_state(servo)) if model.history else (servo,)
    loaded = {n: dexport.load(out / "hardware" / f"{n}.pt2") for n in ("fk", "jacobian")}
    fns = {"hardware_fk_eager": lambda: fk(*args), "hardware_fk_export_program": lambda: loaded["fk"](*args),
           "hardware_jacobian_export_program": lambda: loaded["jacobian"](*args)}
    if aoti:
        package = dexport.load(out / "hardware" / "fk.aoti.pt2")   # the package itself: no silent program fallback
        fns["hardware_fk_aoti"] = lambda: package(*args)
        inputs = [a.contiguous() for a in args]
        fns["hardware_fk_aoti_runner"] = lambda: package.runner(inputs)
        jacobian = dexport.load(out / "hardware" / "jacobian.aoti.pt2")
        fns["hardware_jacobian_aoti"] = lambda: jacobian(*args)
    fns.update(generated_candidates(model, args, out / "hardware", aoti))
    return fns


def generated_candidates(model, args: tuple, out: Path, aoti: bool) -> dict:
    """Rows ``hardware_fk_generated_{export_program, aoti}``: GeneratedHardwareFK (the eager model's code
    traced, benchmarks/generated_fk.py) exported like the folded FK, the same inputs."""
    from generated_fk import GeneratedHardwareFK

    fk = GeneratedHardwareFK(model).eval()
    servo = model.examples[:2].float() if model.examples is not None else torch.zeros(2, len(model.servo_ids))
    files = dexport.write_module("fk_generated", fk, (servo, fk.initial_state(servo)) if model.history else (servo,),
                                 out, aoti)
    runners = {kind: dexport.module_runner(out / f, kind, {"torch_version": torch.__version__})
               for kind, f in files.items()}
    inputs = [a.contiguous() for a in args]
    rows = {"hardware_fk_generated_export_program": lambda: runners["export"](inputs)}
    if "aoti" in runners:
        rows["hardware_fk_generated_aoti"] = lambda: runners["aoti"](inputs)
    return rows


HARDWARE_PAIRS = {"eager": ("hardware_fk_eager", "fk_eager_folded"),
                  "export_program": ("hardware_fk_export_program", "fk_export_program"),
                  "aoti": ("hardware_fk_aoti", "fk_aoti")}


def hardware_ratios(results: dict) -> dict[str, dict]:
    """Per kind: p50 of the hardware FK row, of the synthetic FK row of the same kind (same run), their
    ratio, and (exported kinds) whether it meets the target."""
    out = {}
    for kind, (hw, fk) in HARDWARE_PAIRS.items():
        if hw in results and fk in results:
            ratio = results[hw]["p50_us"] / results[fk]["p50_us"]
            out[kind] = {"hardware_p50_us": results[hw]["p50_us"], "synthetic_p50_us": results[fk]["p50_us"],
                         "ratio": round(ratio, 2)}
            if kind != "eager":
                out[kind].update(target=HARDWARE_RATIO_TARGET, met=ratio <= HARDWARE_RATIO_TARGET)
    return out


def hardware_table(ratios: dict) -> str:
    """Side-by-side rows: kind, synthetic FK p50, hardware FK p50, ratio (target)."""
    lines = [f"{'hardware vs synthetic FK (same run)':<36} {'synthetic':>10} {'hardware':>10} {'ratio':>7}"]
    for kind, r in ratios.items():
        tgt = f"   target ≤ {r['target']:.0f}: {'met' if r['met'] else 'MISSED'}" if "target" in r else ""
        lines.append(f"{kind:<36} {r['synthetic_p50_us']:>10.1f} {r['hardware_p50_us']:>10.1f} "
                     f"{r['ratio']:>7.2f}{tgt}")
    return "\n".join(lines)


def _bound(fn, x):
    return lambda: fn(x)


def summarize(times: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    return {k: {"p50_us": round(float(np.percentile(v, 50)), 2), "p99_us": round(float(np.percentile(v, 99)), 2),
                "calls": int(v.size)} for k, v in times.items()}


def table(results: dict, targets: dict) -> str:
    lines = [f"{'module (batch 1, 1 thread)':<34} {'p50 µs':>9} {'p99 µs':>9}   target p50"]
    for k, r in results.items():
        tgt = f"≤ {targets[k]:.0f} µs {'met' if r['p50_us'] <= targets[k] else 'MISSED'}" if k in targets else ""
        lines.append(f"{k:<34} {r['p50_us']:>9.1f} {r['p99_us']:>9.1f}   {tgt}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", action="store_true", help="print one JSON line on stdout (the table goes to stderr)")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="model shape (model.init_args, data.robot)")
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--calls", type=int, default=500, help="calls per candidate per round")
    p.add_argument("--round-seconds", type=float, default=0.2,
                   help="a candidate slower than this / --calls per call runs about this long per round instead "
                        "(at least 20 calls; the op-by-op rows of ~2 ms: 100 calls); 0 = always --calls")
    p.add_argument("--no-aoti", action="store_true", help="skip AOTInductor (no C++ compiler needed)")
    p.add_argument("--compile", action="store_true", help="also time torch.compile of the folded FK")
    p.add_argument("--autotune", action="store_true",
                   help="export every AOTInductor package with dacr_learn.export's --autotune (C++ GEMM kernels)")
    p.add_argument("--out", type=Path, default=None, help="keep the exports here (default: a temp dir)")
    p.add_argument("--compositional-config", type=Path, default=COMPOSITIONAL_CONFIG,
                   help="shape of the compositional FK rows (fk_compositional_*)")
    p.add_argument("--no-compositional", action="store_true", help="skip the compositional FK rows")
    p.add_argument("--no-hardware", action="store_true", help="skip the hardware model rows (hardware_*)")
    p.add_argument("--hardware-ckpt", type=Path, default=None,
                   help="time this saved hardware model (python -m dacr_learn.hardware --save) instead of "
                        "an untrained one of FTDCR v4's shape")
    p.add_argument("--hardware-members", type=int, default=3, help="ensemble members of the untrained hardware model")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    quiet_third_party_warnings()
    fk, ik = default_modules(args.config)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        export_seconds = export_all(fk, ik, out, aoti=not args.no_aoti, autotune=args.autotune)
        fns = candidates(fk, ik, out, aoti=not args.no_aoti, compile_fk=args.compile)
        if not args.no_compositional:
            fns.update(compositional_candidates(args.compositional_config, out, aoti=not args.no_aoti,
                                                autotune=args.autotune))
        if not args.no_hardware:
            hw_ckpt = args.hardware_ckpt or hardware_checkpoint(out, args.hardware_members)
            fns.update(hardware_candidates(hw_ckpt, out, aoti=not args.no_aoti, autotune=args.autotune))
        with torch.inference_mode():
            seconds = time_interleaved(fns, args.rounds, args.calls, warmup=200,
                                       round_seconds=args.round_seconds or None)
        results = summarize({k: v * 1e6 for k, v in seconds.items()})   # µs
        deviation = json.loads((out / "fk" / dexport.METADATA_FILE).read_text())["max_abs_deviation"]
    report = {"benchmark": "latency", "batch": 1, "threads": torch.get_num_threads(), "aoti_autotune": args.autotune,
              "config": str(args.config.relative_to(ROOT) if args.config.is_relative_to(ROOT) else args.config),
              "model": {k: fk.hparams[k] for k in ("features", "width", "depth", "activation", "rotation")},
              "robot": fk.spec.name, "torch": torch.__version__, "cpu": platform.processor() or platform.machine(),
              "export_seconds": {k: round(v, 1) for k, v in export_seconds.items()},
              "max_abs_deviation_fk": deviation, "results": results, "hardware_fk_vs_fk": hardware_ratios(results),
              "hardware_model": None if args.no_hardware else str(args.hardware_ckpt or
                                                                  f"untrained, {args.hardware_members} members"),
              "targets_p50_us": {k: {"target": v, "met": k in results and results[k]["p50_us"] <= v}
                                 for k, v in TARGETS_US.items()}}
    print(table(results, TARGETS_US), file=sys.stderr if args.json else sys.stdout)
    if report["hardware_fk_vs_fk"]:
        print(hardware_table(report["hardware_fk_vs_fk"]), file=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps(report))
    return report


if __name__ == "__main__":
    sys.exit(run_cli(main))
