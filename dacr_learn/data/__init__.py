"""The data layer: synthetic datasets of every source, and the files they are kept in.

- :mod:`.cc`        constant-curvature samples over a robot's limits (optionally noisy, optionally only some
                    segments bent)
- :mod:`.cosserat`  static shapes of the Cosserat-rod model (:mod:`dacr_learn.cosserat`) under random tendon
                    tensions, and the CC model's error on them (:func:`~.cosserat.cc_baseline`)
- :mod:`.store`     dataset folders with checksums; :func:`generate_or_load` for any source

Both sources return the same tensors (``q``, ``pose``, ``features``, …), so the datamodule serves either.
The names below are those of the CC source and the files, as ``dacr_learn.data`` had them before the
Cosserat source moved here.
"""
from .cc import SamplerOptions, bending_subsets, generate, sample_features, with_segment_frames
from .store import (
    META_FILE,
    TENSOR_FILE,
    generate_or_load,
    load_dataset,
    options_record,
    save_dataset,
    tensors_sha256,
)

__all__ = ["META_FILE", "TENSOR_FILE", "SamplerOptions", "bending_subsets", "generate", "generate_or_load",
           "load_dataset", "options_record", "sample_features", "save_dataset", "tensors_sha256",
           "with_segment_frames"]
