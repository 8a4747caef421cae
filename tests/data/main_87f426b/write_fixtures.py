"""How the files of this folder were written, with the code of main at 87f426b (before issue 29's moves).

    OMP_NUM_THREADS=1 .venv/bin/python tests/data/main_87f426b/write_fixtures.py

- ``fk.ckpt``, ``fk_compositional.ckpt``, ``ik.ckpt``: ``train.py fit`` of configs/default.yaml,
  configs/fk_tdcr3_compositional.yaml and configs/ik_type1.yaml for one epoch of 512 samples, width 8, depth 1
  (their ``last.ckpt``; untrained in effect: they only have to load);
- ``hardware_model.pt``: ``save_hardware_model`` of the synthetic history model of tests/hardware_testkit.py
  (2 ensemble members);
- ``outputs.pt``: inputs and what that code computed from each file (float64): ``load_model`` of the
  checkpoints, ``HardwareModel.predict`` of the hardware model.

tests/test_legacy_checkpoints.py loads them with today's code. Re-running this script with later code
would defeat its purpose: it records what 87f426b wrote.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
sys.path.insert(0, str(ROOT / "tests"))

TINY = ["--trainer.max_epochs", "1", "--data.n_train", "512", "--data.n_val", "64", "--data.n_test", "64",
        "--data.batch_size", "128", "--model.init_args.width", "8", "--model.init_args.depth", "1",
        "--rerun_spawn", "false"]
RUNS = {"fk": "configs/default.yaml", "fk_compositional": "configs/fk_tdcr3_compositional.yaml",
        "ik": "configs/ik_type1.yaml"}


def main() -> None:
    from hardware_testkit import command_recording, synthetic_model

    from dacr_learn import load_model
    from dacr_learn.data import generate
    from dacr_learn.hardware.deploy.checkpoint import save_hardware_model

    outputs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, config in RUNS.items():
            subprocess.run([sys.executable, "train.py", "fit", "--config", config, *TINY, "--run_name", name,
                            "--runs_dir", tmp], cwd=ROOT, check=True)
            shutil.copy(Path(tmp) / name / "version_0" / "checkpoints" / "last.ckpt", HERE / f"{name}.ckpt")
    for name in RUNS:
        model = load_model(HERE / f"{name}.ckpt", torch.float64)
        data = generate(model.spec, 16, seed=7, dtype=torch.float64)
        x = data["q"] if model.task == "fk" else data["pose"]
        with torch.no_grad():
            outputs[name] = {"input": x, "output": model(x)}
    hardware = synthetic_model(history=True, members=2)
    save_hardware_model(hardware, HERE / "hardware_model.pt")
    servo = 1e3 * command_recording(32, 5).servo
    mean, sigma = hardware.predict(servo)
    outputs["hardware_model"] = {"input": servo, "output": mean, "sigma": sigma}
    torch.save(outputs, HERE / "outputs.pt")


if __name__ == "__main__":
    main()
