"""Hardware tip models built on the calibrated Cosserat rod (:mod:`.cosserat_model`), for the registry.

``cosserat``: the Cosserat model of the robot alone, calibrated on the training rows (starting from the
fitted CC model of the fold). ``cc_clarke_residual_cosserat``: the CC Clarke-residual model
(:class:`~.learned.CCClarkeResidual`, deployable and exported like it) whose correction network is first
trained on synthetic commands that bend all segments at once, with tips from the Cosserat model
calibrated on the same training rows in the CC model's frame, then fine-tuned on the recording with the
synthetic set kept in the loss (rehearsal), as ``pretrained_clarke`` does with CC data.
"""
from __future__ import annotations

import copy
import hashlib

import torch
from torch import Tensor, nn

from .ccmodel import CalibratedCC
from .cosserat_model import CalibratedCosserat
from .learned import (
    FINETUNE_STEPS,
    LR,
    PRETRAIN_SAMPLES,
    REHEARSAL,
    CCClarkeResidual,
    Split,
    synthetic_split,
    train_full_batch,
)
from .servo_map import ServoMap

_CALIBRATIONS: dict[str, tuple[CalibratedCosserat, dict]] = {}   # per process: the seeds of one fold share it


def calibrated_cosserat(cc: CalibratedCC, train: Split, **options) -> tuple[CalibratedCosserat, dict]:
    """The Cosserat model of ``cc`` calibrated on ``train`` (a copy; CalibratedCosserat.fit ``options``), and
    its fit report. Deterministic, so cached in the process by a checksum of the rows, the CC model and the
    options: the pre-trained models of several seeds of one fold calibrate once."""
    digest = hashlib.sha256()
    for t in (train.x, train.tip, *cc.state_dict().values()):
        digest.update(t.detach().to(torch.float64).contiguous().numpy().tobytes())
    digest.update(repr(sorted(options.items())).encode())
    key = digest.hexdigest()
    if key not in _CALIBRATIONS:
        model = CalibratedCosserat(cc)
        _CALIBRATIONS[key] = (model, model.fit(train.x, train.tip, **options))
    model, report = _CALIBRATIONS[key]
    return copy.deepcopy(model), dict(report)


class CosseratOnly(nn.Module):
    """The calibrated Cosserat model of ``cc``'s robot: ``fit`` calibrates it on the training split."""

    def __init__(self, cc: CalibratedCC, fit_options: dict | None = None):
        super().__init__()
        self.source = (cc, dict(fit_options or {}))   # not a submodule: the model holds no trained weights
        self.model: CalibratedCosserat | None = None

    def fit(self, train: Split) -> None:
        cc, options = self.source
        self.model, self.fit_report = calibrated_cosserat(cc, train, **options)

    def forward(self, split: Split) -> Tensor:
        """Tips (n, 3) [m]; a command whose displacement solve fails (an inadmissible shape for the fitted
        parameters) gets the CC model's tip, and ``self.fallbacks`` counts them."""
        if self.model is None:
            raise ValueError("CosseratOnly: call fit(train) before predicting")
        tip = self.model(split.x)
        failed = ~torch.isfinite(tip).all(-1)
        self.fallbacks = int(failed.sum())
        return torch.where(failed.unsqueeze(-1), split.cc_tip, tip)


class CCClarkeResidualCosserat(CCClarkeResidual):
    """:class:`CCClarkeResidual` pre-trained on all-segment synthetic data of the calibrated Cosserat model."""

    def __init__(self, cc: CalibratedCC, smap: ServoMap, servo_ids: tuple[str, ...], synthetic_seed: int,
                 samples: int = PRETRAIN_SAMPLES, fit_options: dict | None = None):
        super().__init__(cc)
        self.synthetic_source = (smap, tuple(servo_ids), samples, synthetic_seed)   # not a submodule
        self.fit_options = dict(fit_options or {})          # CalibratedCosserat.fit options (rows, starts, …)

    def fit(self, train: Split) -> None:
        for p in self.cc.parameters():
            p.requires_grad_(False)
        self.fit_normalization(train)
        smap, servo_ids, samples, seed = self.synthetic_source
        physics, self.fit_report = calibrated_cosserat(self.cc, train, free_frame=False, **self.fit_options)
        with torch.no_grad():
            synthetic = synthetic_split(self.cc, smap, servo_ids, samples, seed, tip_fn=physics)
        ok = torch.isfinite(synthetic.tip).all(-1)
        synthetic = synthetic.rows(torch.nonzero(ok).flatten())
        train_full_batch(self.net.parameters(), lambda: self.objective(synthetic))
        train_full_batch(self.net.parameters(),
                         lambda: self.objective(train) + REHEARSAL * self.objective(synthetic),
                         steps=FINETUNE_STEPS, lr=LR / 3)
