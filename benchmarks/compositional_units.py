"""Equal brief training on a heterogeneous robot: compositional FK in strain units vs metric units vs monolithic.

    .venv/bin/python benchmarks/compositional_units.py [--steps 1000]

hetero_3seg_coupled (segments of three lengths, radii, types and joint counts), 1 000 Adam steps each
(one-cycle, batch 256, 4 096 samples, seed 0), mean test tip error on 2 000 fresh samples. The claim (moved here
from tests/test_compositional.py, where it cost 3 × 1 000 steps of every `make test`): the compositional model
in strain units < 0.8 × the same in metric units, and that < 0.6 × the monolithic network (measured there:
1.18, 1.84 and 5.12 mm). Exits 1 when the claim fails.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from dacr_learn.data import generate
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

ROBOT = Path(__file__).resolve().parents[1] / "configs" / "robots" / "hetero_3seg_coupled.yaml"


def briefly_trained_error(spec: RobotSpec, steps: int = 1000, **model) -> float:
    """Mean test tip error [m] after ``steps`` Adam steps (one-cycle, batch 256) on 4 096 samples, seed 0."""
    data, test = generate(spec, 4096, seed=0), generate(spec, 2000, seed=1)
    torch.manual_seed(0)
    module = FKModule(robot=spec.to_dict(), rot_weight=0.1, **model)
    module.model.fit_normalization(data["q"], data["pose"])
    opt = torch.optim.Adam(module.parameters(), lr=model["lr"])
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, model["lr"], total_steps=steps)
    rows = torch.randint(0, 4096, (steps, 256), generator=torch.Generator().manual_seed(0))
    for idx in rows:
        loss = module.loss({"q": data["q"][idx], "pose": data["pose"][idx]})
        opt.zero_grad()
        loss.backward()
        opt.step()
        schedule.step()
    with torch.no_grad():
        return (module(test["q"])[:, :3, 3] - test["pose"][:, :3, 3]).norm(dim=-1).mean().item()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    spec = RobotSpec.from_yaml(ROBOT)
    comp = dict(structure="compositional", rotation="twist", width=32, depth=2, lr=0.01)
    strain = briefly_trained_error(spec, args.steps, **comp)
    metric = briefly_trained_error(spec, args.steps, **comp, units="metric")
    monolithic = briefly_trained_error(spec, args.steps, structure="monolithic", width=64, depth=3, lr=0.003)
    print(f"mean tip error [mm]: compositional (strain units) {1e3 * strain:.2f}, compositional (metric units) "
          f"{1e3 * metric:.2f}, monolithic {1e3 * monolithic:.2f}")
    ok = strain < 0.8 * metric and metric < 0.6 * monolithic
    print("claim strain < 0.8·metric and metric < 0.6·monolithic:", "holds" if ok else "FAILS")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
