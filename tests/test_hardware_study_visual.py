"""dacr_learn.hardware.study.visual: the benchmark's plot colours and its Rerun recording (val_tip_paths.rrd): one
error plot with every model, the default and the best two shown beside an RMSE bar chart, the others hidden (not
dropped), σ bands, opening at the end.

Each recording is written under tmp_path and read back with tests/rerun_testkit.py (``rerun.chunk.RrdReader``).
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader
from rerun_testkit import (
    FOLLOWING,
    WHOLE_RANGE,
    rrd_chunks,
    rrd_column,
    rrd_data,
    rrd_data_chunks,
    rrd_time_panel,
    rrd_verify,
    rrd_views,
)

pytestmark = pytest.mark.usefixtures("one_thread")


def test_every_registered_model_gets_its_own_plot_colour():
    """The PNG and the Rerun recording colour model k (registry order, from 1) by _color(name, k): no two
    models of the registry (and not the measured path) may share a colour."""
    from dacr_learn.hardware.study.registry import MODELS
    from dacr_learn.hardware.study.visual import _color

    colours = [_color("measured", 0)] + [_color(name, k) for k, name in enumerate(MODELS, start=1)]
    assert len(set(colours)) == len(colours), dict(zip(["measured", *MODELS], colours, strict=True))
    # the PNG shows a few models, the recording all: a model's colour does not depend on its plot position
    assert all(_color(name, 1) == _color(name, k) for k, name in enumerate(MODELS, start=1))


class _FakeCC:
    """The CC model's backbone of a straight robot along z (enough for the recording)."""

    def backbone(self, x: torch.Tensor) -> torch.Tensor:
        return torch.linspace(0, 0.1, 5)[:, None] * torch.tensor([0.0, 0.0, 1.0]) + 0 * x[:, :1, None]


def test_hardware_recording_has_one_plot_with_every_model_and_opens_at_the_end(tmp_path):
    from dacr_learn.hardware.study.visual import log_rerun

    n, g = 30, torch.Generator().manual_seed(0)
    tip = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.05
    labels = tuple(["sweep"] * 15 + ["circle"] * 15)
    setup = SimpleNamespace(val=SimpleNamespace(tip=tip, x=torch.zeros(n, 4)), spec=SimpleNamespace(name="fake"),
                            val_rec=SimpleNamespace(labels=labels, source="val.csv"), cc=_FakeCC())
    preds = {f"model_{k}": tip + 0.001 * k * torch.randn(n, 3, generator=g, dtype=torch.float64) for k in range(10)}
    std = {"model_3": torch.full((n,), 0.002), "model_4": torch.full((n, 3), 0.001)}
    path = tmp_path / "hw.rrd"
    log_rerun(setup, preds, path, std=std)
    rrd_verify(path)
    chunks = rrd_chunks(path)
    assert {f"/errors/model_{k}" for k in range(10)} <= set(chunks)  # every model, not the first 8
    assert {"/sigma/model_3", "/sigma/model_4", "/world/band_2sigma/model_3"} <= set(chunks)
    assert len(rrd_column(chunks["/errors/model_5"], "Scalars:scalars")) == n
    assert rrd_column(chunks["/errors/model_5"], "SeriesLines:names")[0][0].startswith("model_5 (")
    twice_sigma = rrd_column(chunks["/sigma/model_4"], "Scalars:scalars")[0][0]
    assert twice_sigma == pytest.approx(2e3 * 0.001 * np.sqrt(3), rel=1e-5)  # 2‖σ‖ [mm]
    # error plot and 3D path of a model share one colour
    line = rrd_column(chunks["/errors/model_5"], "SeriesLines:colors")[0]
    strip = rrd_column(chunks["/world/paths/model_5"], "LineStrips3D:colors")[0]
    assert line == strip
    assert rrd_data_chunks(path) <= 3 * len(chunks)  # columns, not one chunk per sample
    (store,) = RrdReader(path).blueprints()
    views = rrd_views(path, store).values()
    plots = [v for v in views if v["class"] == "TimeSeries"]
    assert sorted(v["origin"] for v in plots) == ["errors", "sigma"]  # one error plot (+ the 2σ one)
    assert any(v["class"] == "3D" and v["origin"] == "world" for v in views)
    assert rrd_time_panel(path, store)["TimePanelBlueprint:play_state"] == [3]  # following: opens at the end
    # the 3D view shows the 3 lowest-RMSE models (and cc): the other paths are hidden there, not dropped
    hidden = set()
    for chunk in RrdReader(path).stream(store=store):
        rb = chunk.to_record_batch()
        if "EntityBehavior:visible" in rb.schema.names and rb.column("EntityBehavior:visible").to_pylist() == [[False]]:
            hidden.add(chunk.entity_path.split("/overrides/")[1].removesuffix("/visualizers"))
    assert {f"world/paths/model_{k}" for k in range(3, 10)} == {h for h in hidden if h.startswith("world/paths/")}
    (recording,) = RrdReader(path).recordings()
    assert recording.application_id == "dacr_learn_hardware"
    with pytest.raises(ValueError, match="std"):
        log_rerun(setup, preds, tmp_path / "bad.rrd", std={"model_0": torch.ones(n + 1)})


def _hardware_recording(path: Path, default: str | None, std: dict | None = None) -> list[str]:
    """A val recording of 10 models whose RMSE grows with their number (model_0 best), plus 'cc' (worst);
    returns the model names."""
    from dacr_learn.hardware.study.visual import log_rerun

    n, g = 30, torch.Generator().manual_seed(0)
    tip = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.05
    noise = torch.randn(n, 3, generator=g, dtype=torch.float64)
    setup = SimpleNamespace(val=SimpleNamespace(tip=tip, x=torch.zeros(n, 4)), spec=SimpleNamespace(name="fake"),
                            val_rec=SimpleNamespace(labels=("sweep",) * n, source="val.csv"), cc=_FakeCC())
    preds = {f"model_{k}": tip + 1e-3 * (k + 1) * noise for k in range(10)} | {"cc": tip + 0.02 * noise}
    log_rerun(setup, preds, path, default=default, std=std)
    return list(preds)


def test_hardware_recording_plots_the_default_and_the_best_two_beside_an_rmse_bar_chart(tmp_path):
    path = tmp_path / "hw.rrd"
    models = _hardware_recording(path, default="model_6")
    views = rrd_views(path).values()
    shown = {"model_6", "model_0", "model_1"}                  # the default and the two lowest RMSEs
    (errors,) = [v for v in views if v["class"] == "TimeSeries"]
    assert errors["origin"] == "errors" and errors["ranges"] == [{"timeline": "sample", "range": WHOLE_RANGE}]
    assert errors["hidden"] == {f"errors/{m}" for m in models if m not in shown}  # in the recording, hidden
    assert "default model_6" in errors["name"] and "8 more hidden" in errors["name"]
    # the 3D view shows the same models and the CC model (the reference); the others' paths are hidden
    (scene,) = [v for v in views if v["class"] == "3D"]
    assert {h for h in scene["hidden"] if h.startswith("world/paths/")} == {
        f"world/paths/{m}" for m in models if m not in shown | {"cc"}}
    # every model's RMSE as a bar, ranked (x = rank, best first), in the colour of its error curve
    (bars,) = [v for v in views if v["class"] == "BarChart"]
    assert bars["origin"] == "rmse" and not bars["hidden"]
    data = rrd_data(path)
    ranked = [f"model_{k}" for k in range(10)] + ["cc"]
    for rank, name in enumerate(ranked, start=1):
        bar = data[f"/rmse/{rank}_{name}"]
        assert bar["BarChart:abscissa"][0][0]["buffer"] == [rank]
        assert bar["BarChart:color"] == data[f"/errors/{name}"]["SeriesLines:colors"]
        rmse = np.sqrt(np.mean(np.square(data[f"/errors/{name}"]["Scalars:scalars"])))
        assert bar["BarChart:values"][0][0]["buffer"][0] == pytest.approx(rmse, rel=1e-5)
    assert data["/errors/model_6"]["SeriesLines:names"][0][0].endswith("mm, default)")
    assert "| 7 | model_6 (default) |" in data["/summary"]["TextDocument:text"][0][0]
    panel = rrd_time_panel(path)
    assert panel["TimePanelBlueprint:timeline"] == ["sample"] and panel["TimePanelBlueprint:play_state"] == [FOLLOWING]


def test_hardware_recording_without_a_default_shows_the_best_three(tmp_path):
    path = tmp_path / "hw.rrd"
    n = 30
    models = _hardware_recording(path, default=None, std={"model_1": torch.full((n,), 1e-3),
                                                          "model_5": torch.full((n,), 1e-3)})
    views = rrd_views(path).values()
    plots = {v["origin"]: v for v in views if v["class"] == "TimeSeries"}
    hidden = {m for m in models if m not in {"model_0", "model_1", "model_2"}}
    assert plots["errors"]["hidden"] == {f"errors/{m}" for m in hidden}
    assert plots["sigma"]["hidden"] == {f"sigma/{m}" for m in hidden}
    assert "the best 3" in plots["errors"]["name"]


def test_error_axis_leaves_the_top_free_for_the_legend_and_hides_no_point():
    from dacr_learn.hardware.study.visual import LEGEND_ROOM, error_axis_max, shown_models

    errors = {"a": np.array([1.0, 9.0]), "b": np.array([2.0, 3.0]), "c": np.array([50.0, 0.0])}
    assert shown_models(errors, "c", 2) == ["c", "b"] and shown_models(errors, None, 2) == ["b", "a"]
    assert shown_models(errors, "not a model") == ["b", "a", "c"]
    top = error_axis_max({k: errors[k] for k in ("a", "b")})
    assert top * (1 - LEGEND_ROOM) == pytest.approx(9.0)
    assert error_axis_max({"perfect": np.zeros(4)}) > 0
