"""Hardware tip models built on the calibrated Cosserat rod (:mod:`.cosserat_model`), for the registry.

``cosserat`` (:class:`CosseratOnly`, calibrated on the training rows from the fold's CC fit),
``cc_clarke_residual_cosserat`` and ``cc_clarke_residual_history_cosserat`` (:class:`CCClarkeResidualCosserat`:
pre-trained on the Cosserat model's synthetic tips, saved and exported as their CC Clarke-residual counterparts):
docs/hardware.md, "The models".

The calibration and the synthetic tips are deterministic functions of the training rows, the CC model and the
options, so they are computed once and shared: within a process and, given a ``cache_dir``
(:attr:`~.study.registry.FitContext.cache_dir`), between worker processes through files (:func:`warmups`).
"""
from __future__ import annotations

import copy
import fcntl
import hashlib
import pickle
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn

from .ccmodel import CalibratedCC
from .cosserat_model import CalibratedCosserat
from .learned import PRETRAIN_SAMPLES, CCClarkeResidual, Split, pretrain_and_finetune, synthetic_split
from .servo_map import ServoMap

_SHARED: dict[str, object] = {}   # per process: the calibrations and synthetic tips computed or read here


def _shared(key: str, compute: Callable[[], object], cache_dir: Path | None) -> object:
    """``compute()`` once per ``key``: in this process, and with ``cache_dir`` once for all processes that share
    the folder (a file lock per key: the first computes and writes, the others wait and read)."""
    if key in _SHARED:
        return _SHARED[key]
    if cache_dir is None:
        _SHARED[key] = compute()
        return _SHARED[key]
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = cache_dir / f"{key}.pkl"
    with open(cache_dir / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if path.exists():
                value = pickle.loads(path.read_bytes())
            else:
                value = compute()
                tmp = path.with_suffix(".tmp")
                tmp.write_bytes(pickle.dumps(value))
                tmp.replace(path)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    _SHARED[key] = value
    return value


def calibration_key(cc: CalibratedCC, train: Split, options: dict) -> str:
    """A checksum of what a calibration depends on: the training rows, the CC model and the fit options."""
    digest = hashlib.sha256()
    for t in (train.x, train.tip, *cc.state_dict().values()):
        digest.update(t.detach().to(torch.float64).contiguous().numpy().tobytes())
    digest.update(repr(sorted(options.items())).encode())
    return "cosserat-" + digest.hexdigest()[:32]


def calibrated_cosserat(cc: CalibratedCC, train: Split, cache_dir: Path | None = None,
                        **options) -> tuple[CalibratedCosserat, dict]:
    """The Cosserat model of ``cc`` calibrated on ``train`` (a copy; CalibratedCosserat.fit ``options``), and
    its fit report, computed once per process (and per ``cache_dir``, :func:`_shared`)."""
    def compute() -> tuple[CalibratedCosserat, dict]:
        model = CalibratedCosserat(cc)
        return model, model.fit(train.x, train.tip, **options)

    model, report = _shared(calibration_key(cc, train, options), compute, cache_dir)
    return copy.deepcopy(model), dict(report)


def synthetic_cosserat_split(cc: CalibratedCC, train: Split, smap: ServoMap, servo_ids: tuple[str, ...],
                             samples: int, seed: int, cache_dir: Path | None = None,
                             **options) -> tuple[Split, dict]:
    """(synthetic all-segment commands of the CC robot with the tips of the Cosserat model calibrated on
    ``train`` in the CC model's frame — rows whose solve failed left out —, the calibration's report)."""
    options = {"free_frame": False, **options}
    physics, report = calibrated_cosserat(cc, train, cache_dir, **options)
    key = f"{calibration_key(cc, train, options)}-synthetic-{samples}-{seed}"

    def compute() -> Tensor:
        with torch.no_grad():
            return synthetic_split(cc, smap, servo_ids, samples, seed, tip_fn=physics).tip

    tip = _shared(key, compute, cache_dir)
    synthetic = synthetic_split(cc, smap, servo_ids, samples, seed)          # the commands (cheap), CC tips
    synthetic.tip = synthetic.cc_tip = tip
    ok = torch.isfinite(tip).all(-1)
    return synthetic.rows(torch.nonzero(ok).flatten()), report


class CosseratOnly(nn.Module):
    """The calibrated Cosserat model of ``cc``'s robot: ``fit`` calibrates it on the training split."""

    def __init__(self, cc: CalibratedCC, fit_options: dict | None = None, cache_dir: Path | None = None):
        super().__init__()
        self.source = (cc, dict(fit_options or {}), cache_dir)   # not a submodule: the model holds no trained weights
        self.model: CalibratedCosserat | None = None

    def fit(self, train: Split) -> None:
        cc, options, cache_dir = self.source
        self.model, self.fit_report = calibrated_cosserat(cc, train, cache_dir, **options)

    def physics_report(self) -> dict:
        """The calibrated physical parameters (:meth:`CalibratedCosserat.report`) and the fit's RMS [mm]."""
        return {**self.model.report(), "fit_rms_mm": round(self.fit_report["rms_m"] * 1e3, 4)}

    def warmups(self, train: Split) -> list[tuple[str, Callable, tuple]]:
        """[(key, fn, args)]: the calibration, to compute ahead of the fits that need it (:func:`warmups`)."""
        cc, options, cache_dir = self.source
        return [(calibration_key(cc, train, options), _calibrate, (cc, train, cache_dir, options))]

    def forward(self, split: Split) -> Tensor:
        """Tips (n, 3) [m]; a command whose displacement solve fails (an inadmissible shape for the fitted
        parameters) gets the CC model's tip, and ``self.fallbacks`` counts them."""
        if self.model is None:
            raise ValueError("CosseratOnly: call fit(train) before predicting")
        tip = self.model(split.x)
        failed = ~torch.isfinite(tip).all(-1)
        self.fallbacks = int(failed.sum())
        return torch.where(failed.unsqueeze(-1), split.cc_tip, tip)


def _calibrate(cc: CalibratedCC, train: Split, cache_dir: Path | None, options: dict) -> None:
    calibrated_cosserat(cc, train, cache_dir, **options)


def _synthesize(cc: CalibratedCC, train: Split, smap: ServoMap, servo_ids: tuple[str, ...], samples: int, seed: int,
                cache_dir: Path | None, options: dict) -> None:
    synthetic_cosserat_split(cc, train, smap, servo_ids, samples, seed, cache_dir, **options)


class CCClarkeResidualCosserat(CCClarkeResidual):
    """:class:`CCClarkeResidual` pre-trained on all-segment synthetic data of the calibrated Cosserat model."""

    def __init__(self, cc: CalibratedCC, smap: ServoMap, servo_ids: tuple[str, ...], synthetic_seed: int,
                 samples: int = PRETRAIN_SAMPLES, fit_options: dict | None = None, cache_dir: Path | None = None):
        super().__init__(cc)
        self.synthetic_source = (smap, tuple(servo_ids), samples, synthetic_seed)   # not a submodule
        self.fit_options = dict(fit_options or {})          # CalibratedCosserat.fit options (rows, starts, …)
        self.cache_dir = cache_dir

    def synthetic(self, train: Split) -> Split:
        """The pre-training split (:func:`synthetic_cosserat_split`); sets ``fit_report`` (the calibration's)."""
        smap, servo_ids, samples, seed = self.synthetic_source
        synthetic, self.fit_report = synthetic_cosserat_split(self.cc, train, smap, servo_ids, samples, seed,
                                                              self.cache_dir, **self.fit_options)
        options = {"free_frame": False, **self.fit_options}
        self.physics = calibrated_cosserat(self.cc, train, self.cache_dir, **options)[0].report()
        return synthetic

    def physics_report(self) -> dict:
        """The physical parameters of the Cosserat model it was pre-trained on (in the CC model's frame) and that
        calibration's RMS [mm]."""
        return {**self.physics, "fit_rms_mm": round(self.fit_report["rms_m"] * 1e3, 4)}

    def warmups(self, train: Split) -> list[tuple[str, Callable, tuple]]:
        """[(key, fn, args)]: the calibration, then the synthetic tips of this seed (:func:`warmups`)."""
        smap, servo_ids, samples, seed = self.synthetic_source
        options = {"free_frame": False, **self.fit_options}
        key = calibration_key(self.cc, train, options)
        return [(key, _calibrate, (self.cc, train, self.cache_dir, options)),
                (f"{key}-synthetic-{samples}-{seed}", _synthesize,
                 (self.cc, train, smap, servo_ids, samples, seed, self.cache_dir, self.fit_options))]

    def fit(self, train: Split) -> None:
        self.cc.requires_grad_(False)
        self.fit_normalization(train)
        synthetic = self.synthetic(train)
        pretrain_and_finetune(list(self.net.parameters()), lambda: self.objective(synthetic),
                              lambda: self.objective(train))


class CCClarkeResidualHistoryCosserat(CCClarkeResidualCosserat):
    """:class:`CCClarkeResidualCosserat` with the motion memory of each segment as extra input (as
    :class:`~.learned.CCClarkeResidualHistory`; the synthetic commands have none, memory 0)."""

    history = True


def warmups(model: nn.Module, train: Split) -> list[tuple[str, Callable, tuple]]:
    """The shared pieces a model's fit on ``train`` will ask for, [(key, fn, args)] (none for other models):
    the benchmark runs each key once, ahead of the fits, so that no worker waits for another's calibration."""
    return model.warmups(train) if hasattr(model, "warmups") else []
