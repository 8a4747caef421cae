"""dacr_learn.viz.layout: metric groups (train and val of one quantity and unit in one plot), series styles and
the summary table."""
from __future__ import annotations

from dacr_learn.viz.layout import metric_groups, series_style, summary_markdown


def test_metric_groups_put_train_and_val_of_one_quantity_and_unit_together():
    names = ["epoch", "train/loss", "val/loss", "val/pos_err_mean_mm", "val/pos_err_p95_mm", "val/pos_err_mean_pct",
             "val/rot_err_mean_deg", "test/pos_err_mean_mm", "train_acc", "val_acc"]
    groups = metric_groups(names)
    assert groups == {"loss": ["train/loss", "val/loss"], "acc": ["train_acc", "val_acc"],
                      "tip position error [mm]": ["val/pos_err_mean_mm", "val/pos_err_p95_mm"],
                      "tip rotation error [°]": ["val/rot_err_mean_deg"]}
    assert list(groups)[0] == "loss"  # test metrics, epoch and the %-duplicate are in the table only
    assert series_style("val/pos_err_p95_mm")[0] == "val p95" and series_style("train_acc")[0] == "train acc"
    assert series_style("train/loss")[1] != series_style("val/loss")[1]
    table = summary_markdown({"val/pos_err_mean_mm": (10, 0.25), "test/pos_err_mean_mm": (12, 0.5), "epoch": (12, 3)})
    assert "| pos_err_mean_mm | 0.25 | 0.5 |  |" in table and "| epoch |  |  | 3 |" in table
    assert "step 12" in table
