"""The benchmark's process pool (dacr_learn.hardware.study.pool): a model built in a worker is the one built here."""
from __future__ import annotations

import pytest
import torch

from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.learned import make_split
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoMap
from dacr_learn.hardware.study.pool import TaskPool
from dacr_learn.hardware.study.registry import FitContext, build_model
from dacr_learn.robot import RobotSpec

pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_model_built_in_a_worker_process_equals_the_one_built_here(labelled_robot_dir):
    ctx = _context(labelled_robot_dir)
    with TaskPool(jobs=2) as pool:
        remote = pool.submit(build_model, "mlp_clarke", ctx, 0)
        here = pool.run_here(build_model, "mlp_clarke", ctx, 0)
        (got, seconds), (want, _) = remote.result(), here.result()
    assert seconds > 0
    for (key, a), b in zip(got.state_dict().items(), want.state_dict().values(), strict=True):
        assert torch.allclose(a, b, rtol=0, atol=1e-7), key                # seeded in the worker: the same start
    other = build_model("mlp_clarke", ctx, 1).net[0].weight
    assert not torch.allclose(got.net[0].weight, other)                    # …and the seed matters
    with pytest.raises(ValueError, match="jobs >= 1"):
        TaskPool(jobs=0)


def _context(labelled_robot_dir) -> FitContext:
    data, robot = labelled_robot_dir
    spec = RobotSpec.from_yaml(robot)
    smap = ServoMap.from_yaml(robot.parent / "servo_maps" / robot.name)
    rec = load_recording(data / "train.csv", spec)
    cc = CalibratedCC(spec)
    for p in cc.parameters():
        p.requires_grad_(False)
    return FitContext(cc, smap, rec.servo_ids, make_split(rec, spec, smap, cc))


def test_shared_pieces_log_a_progress_line_each_as_they_finish(monkeypatch):
    """submit_warmups: each shared piece (one per key, whichever fits ask for it) is submitted once, and a line is
    logged when it finishes, in the order they finish (here a pool whose futures finish when told to)."""
    from concurrent.futures import Future

    from dacr_learn.hardware.study import benchmark

    pieces = {"a": [("cal-1", print, ()), ("cal-1-synthetic-4000-0", print, ())], "b": [("cal-1", print, ())],
              "c": [("cal-2", print, ())]}
    monkeypatch.setattr(benchmark, "build_model", lambda name, ctx, seed: name)
    monkeypatch.setattr(benchmark, "warmups", lambda model, train: pieces[model])
    monkeypatch.setattr(benchmark, "model_seeds", lambda name, seeds: list(seeds))

    class Pool:
        jobs = 2

        def __init__(self):
            self.futures: list[Future] = []

        def submit(self, fn, *args):
            self.futures.append(Future())
            return self.futures[-1]

    class Ctx:
        train = None

    pool, lines = Pool(), []
    futures = benchmark.submit_warmups(pool, [(Ctx, name, [0]) for name in "abc"], lines.append)
    assert len(futures) == 3 and lines == []                                 # cal-1 once, cal-2, the synthetic tips
    for k, seconds in ((2, 5.0), (0, 61.0)):
        pool.futures[k].set_result((None, seconds))
    pool.futures[1].set_exception(RuntimeError("failed"))                   # surfaced by the caller, not logged
    assert lines == ["[shared 1/3] Cosserat synthetic tips ready (5 s)",
                     "[shared 2/3] Cosserat calibration ready (61 s)"]
