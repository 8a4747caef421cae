"""The data layer: synthetic datasets of every source (:mod:`.cc`: constant curvature over a robot's limits;
:mod:`.cosserat`: static shapes of the Cosserat-rod model) and the files they are kept in (:mod:`.store`).
Both sources return the same tensors (``q``, ``pose``, ``features``, …), so the datamodule serves either;
the names below are those of the CC source and the files.
"""
from .cc import SamplerOptions, bending_subsets, generate, sample_features, with_segment_frames
from .store import META_FILE, TENSOR_FILE, generate_or_load, load_dataset, options_record, save_dataset, tensors_sha256

__all__ = ["META_FILE", "TENSOR_FILE", "SamplerOptions", "bending_subsets", "generate", "generate_or_load",
           "load_dataset", "options_record", "sample_features", "save_dataset", "tensors_sha256",
           "with_segment_frames"]
