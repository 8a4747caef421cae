"""dacr_learn.combination_shift (library functions; the study itself is a script): the train / held-out /
all-bending regimes and the summary's mean, std and ratio."""
from __future__ import annotations

import pytest
import torch
from conftest import TDCR3

from dacr_learn.combination_shift import combination_split, summarize_rows


def test_combination_split_regimes():
    split = combination_split(TDCR3, 300, 200, seed=0, max_bending=2)
    bends = {k: (v["features"][..., :2].abs().sum(-1) > 0).sum(-1) for k, v in split.items()}
    assert int(bends["train"].max()) <= 2 and int(bends["heldout"].max()) <= 2
    assert bool((bends["all_bending"] == 3).all())
    assert not torch.equal(split["train"]["q"][:200], split["heldout"]["q"])
    with pytest.raises(ValueError, match="max_bending"):
        combination_split(TDCR3, 10, 10, seed=0, max_bending=3)


def test_summary_reports_mean_std_and_ratio():
    rows = [{"study": "shift", "model": "c", "seed": s, "test": t, "pos_err_mean_mm": e, "pos_err_mean_pct": e,
             "rot_err_mean_deg": 2 * e} for s, (t, e) in enumerate([("heldout", 1.0), ("heldout", 3.0),
                                                                   ("all_bending", 4.0), ("all_bending", 4.0)])]
    s = summarize_rows(rows)["shift/c"]
    assert s["heldout"]["pos_err_mean_mm"] == pytest.approx(2.0)
    assert s["heldout"]["pos_err_mean_mm_std"] == pytest.approx(2 ** 0.5)
    assert s["ratio_all_bending_to_heldout"]["pos_err_mean_mm"] == pytest.approx(2.0)
