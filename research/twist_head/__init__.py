"""The twisting-segment study of docs/history/compositional.md, "Twisting segments: the roll (2026-11-26)": frozen
research scripts, not part of the ``dacr_learn`` library, run from the repository root as
``python -m research.twist_head.<script>``.

- :mod:`research.twist_head.representation`: an affine twist against Rz(α)·T_cc, with and without the roll.
- :mod:`research.twist_head.segment_errors`: per-segment error of a trained compositional model.
"""
