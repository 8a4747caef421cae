"""The registry of hardware tip models: name → builder and flags (one place, unique names).

Every model is built from a :class:`FitContext` and a seed — from shapes and configuration only (the
number of servos or segments, the fitted CC model, the servo map): no training data goes into a
constructor — then trained with ``model.fit(ctx.train)`` (which also sets its data-dependent
statistics) and evaluated with ``model(split)`` → tip (n, 3) [m] (:mod:`dacr_learn.hardware.learned`). The
benchmark, the train-only selection proxies (:mod:`.selection`) and the held-out σ fits build models here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from .. import learned
from ..ccmodel import CalibratedCC
from ..compositional_model import CCCompositionalResidual
from ..cosserat_learned import CCClarkeResidualCosserat, CCClarkeResidualHistoryCosserat, CosseratOnly
from ..learned import Split
from ..servo_map import ServoMap

SYNTHETIC_SEED = 1000   # the pre-trained models' synthetic data of seed s is drawn with seed SYNTHETIC_SEED + s


@dataclass(frozen=True)
class FitContext:
    """What a model is built and fitted from: the CC model fitted on ``train``, the servo map and the servo ids
    (the builders read these), and the training split (the callers fit on it). ``cache_dir``: a folder where
    the worker processes of one benchmark share the Cosserat calibrations (:mod:`..cosserat_learned`), or None."""

    cc: CalibratedCC
    smap: ServoMap
    servo_ids: tuple[str, ...]
    train: Split
    cache_dir: Path | None = None

    def n_inputs(self, inputs: str) -> int:
        """Width of a network input: the number of servos ("raw") or 2m Clarke coordinates ("clarke")."""
        return len(self.servo_ids) if inputs == "raw" else 2 * self.cc.spec.num_segments

    def synthetic(self, seed: int, n: int = learned.PRETRAIN_SAMPLES) -> Split:
        """Synthetic all-segment data of the calibrated CC robot (:func:`~.learned.synthetic_split`), as the
        pre-trained models of seed ``seed`` draw it."""
        return learned.synthetic_split(self.cc, self.smap, self.servo_ids, n, seed=SYNTHETIC_SEED + seed)


def _pretrained(inputs: str) -> Callable[[FitContext, int], nn.Module]:
    return lambda c, s: learned.Pretrained(inputs, c.n_inputs(inputs), c.cc, c.smap, c.servo_ids, SYNTHETIC_SEED + s)


@dataclass(frozen=True)
class ModelInfo:
    """One registered model: ``inputs`` "raw" | "clarke"; ``static`` (False: uses the command history);
    ``deterministic`` (trained once); ``deployable`` (``--save`` and the export take it); ``outputs``: learned outputs
    per segment of a CC-based model (0: the CC model; large: not a per-segment correction); ``pretrained``: first
    trained on another model's synthetic data. See :func:`complexity`.
    """

    name: str
    build: Callable[[FitContext, int], nn.Module]
    inputs: str
    static: bool = True
    deterministic: bool = False
    deployable: bool = False
    outputs: int = 1000
    pretrained: bool = False
    instant: bool = False            # fitted in no time (the benchmark runs it in its own process, not a worker)

    @property
    def clarke_space(self) -> bool:
        return self.inputs == "clarke"


_MODELS = (
    ModelInfo("linear_raw", lambda c, s: learned.LinearRaw(len(c.servo_ids)), "raw", deterministic=True, instant=True),
    ModelInfo("mlp_raw", lambda c, s: learned.TipMLP("raw", c.n_inputs("raw")), "raw"),
    ModelInfo("mlp_clarke", lambda c, s: learned.TipMLP("clarke", c.n_inputs("clarke")), "clarke"),
    ModelInfo("cc", lambda c, s: learned.CCOnly(), "clarke", deterministic=True, deployable=True, outputs=0,
              instant=True),
    ModelInfo("cc_clarke_residual", lambda c, s: learned.CCClarkeResidual(c.cc), "clarke", deployable=True, outputs=2),
    ModelInfo("pretrained_clarke", _pretrained("clarke"), "clarke", pretrained=True),
    ModelInfo("cc_clarke_residual_history", lambda c, s: learned.CCClarkeResidualHistory(c.cc), "clarke",
              static=False, deployable=True, outputs=2),
    ModelInfo("cc_tip_residual", lambda c, s: learned.CCTipResidual(c.n_inputs("clarke")), "clarke"),
    ModelInfo("pretrained_raw", _pretrained("raw"), "raw"),
    ModelInfo("cc_compositional_residual", lambda c, s: CCCompositionalResidual(c.cc), "clarke",
              deployable=True, outputs=5),
    ModelInfo("cc_compositional_history", lambda c, s: CCCompositionalResidual(c.cc, history=True), "clarke",
              static=False, outputs=5),
    ModelInfo("cosserat", lambda c, s: CosseratOnly(c.cc, cache_dir=c.cache_dir), "clarke", deterministic=True,
              outputs=0),
    ModelInfo("cc_clarke_residual_cosserat",
              lambda c, s: CCClarkeResidualCosserat(c.cc, c.smap, c.servo_ids, SYNTHETIC_SEED + s,
                                                    cache_dir=c.cache_dir), "clarke",
              deployable=True, outputs=2, pretrained=True),
    ModelInfo("cc_clarke_residual_history_cosserat",
              lambda c, s: CCClarkeResidualHistoryCosserat(c.cc, c.smap, c.servo_ids, SYNTHETIC_SEED + s,
                                                           cache_dir=c.cache_dir), "clarke",
              static=False, deployable=True, outputs=2, pretrained=True),
)
REGISTRY: dict[str, ModelInfo] = {m.name: m for m in _MODELS}
MODELS: tuple[str, ...] = tuple(REGISTRY)
assert len({m.name for m in _MODELS}) == len(_MODELS), "model names must be unique"


def model_info(model: str) -> ModelInfo:
    """The registry entry of a model name (only registered models: what the study scores is what can ship)."""
    if model not in REGISTRY:
        raise ValueError(f"model: got {model!r}, expected one of {MODELS}")
    return REGISTRY[model]


def complexity(model: str) -> tuple[int, int, int]:
    """The order (lower is simpler) in which :func:`.selection.default_choice` prefers models the proxy cannot tell
    apart (docs/hardware.md): static before history, fewer learned outputs per segment, no pre-training first.
    """
    info = model_info(model)
    return (int(not info.static), info.outputs, int(info.pretrained))


def build_model(model: str, ctx: FitContext, seed: int) -> nn.Module:
    """A fresh, untrained registered model, torch seeded with ``seed`` first (its initial weights); the caller
    fits it, ``model.fit(ctx.train)``."""
    info = model_info(model)
    torch.manual_seed(seed)
    return info.build(ctx, seed)
