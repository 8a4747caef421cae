"""The designed layouts (Rerun blueprints) of the recordings a user opens besides training runs:
examples/track_trajectory.py's track.rrd and the hardware benchmark's val_tip_paths.rrd.

Each recording is written under tmp_path and its blueprint read back with
``rerun.chunk.RrdReader`` (rerun-sdk 0.41): view classes, names, origins, time ranges, the
entities a view hides by default, and the time panel (play state 3 = following: opens at the end).
"""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader

from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]
FOLLOWING = 3     # rerun.blueprint.components.PlayState.Following
WHOLE_RANGE = {"start": None, "end": None}


def _blueprint(path: Path):
    (store,) = RrdReader(path).blueprints()
    return store


def _views(path: Path) -> dict[str, dict]:
    """View entity (``/view/<id>``) -> {"class", "name", "origin", "ranges", "hidden"} of the recording's
    blueprint; "hidden": the entities the view overrides with EntityBehavior(visible=False)."""
    fields = {"ViewBlueprint:class_identifier": "class", "ViewBlueprint:display_name": "name",
              "ViewBlueprint:space_origin": "origin", "VisibleTimeRanges:ranges": "ranges"}
    views: dict[str, dict] = {}
    for chunk in RrdReader(path).stream(store=_blueprint(path)):
        if not chunk.entity_path.startswith("/view/"):
            continue
        rb = chunk.to_record_batch()
        view = views.setdefault("/".join(chunk.entity_path.split("/")[:3]), {"hidden": set()})
        for column, key in fields.items():
            if column in rb.schema.names:
                row = rb.column(column).to_pylist()[-1]
                view[key] = row if key == "ranges" else row[0]
        if "EntityBehavior:visible" in rb.schema.names and rb.column("EntityBehavior:visible").to_pylist() == [[False]]:
            view["hidden"].add(chunk.entity_path.split("/overrides/")[1].removesuffix("/visualizers"))
    return views


def _time_panel(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream(store=_blueprint(path)):
        if chunk.entity_path == "/time_panel":
            rb = chunk.to_record_batch()
            out.update({n: rb.column(n).to_pylist()[-1] for n in rb.schema.names if n.startswith("TimePanel")})
    return out


def _data(path: Path) -> dict[str, dict[str, list]]:
    """Entity -> component column (``Archetype:field``) -> its rows of the recording's data."""
    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        for name in (n for n in rb.schema.names if ":" in n):
            out.setdefault(chunk.entity_path, {}).setdefault(name, []).extend(rb.column(name).to_pylist())
    return out


# ---------------------------------------------------------------------------------------------------------------
# examples/track_trajectory.py


def _example():
    spec = importlib.util.spec_from_file_location("track_trajectory", ROOT / "examples" / "track_trajectory.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _tracking_results(example, robot) -> dict[str, dict]:
    """What run_scenario returns, without a controller: the robot stays straight, the 'actual' tip is
    the reference plus a known offset (10 µm for the circle, 20 µm for the figure-8)."""
    from dacr_learn.control import ClarkeSpace

    spec, n = robot.spec, 40
    q = ClarkeSpace(spec).joints(torch.tensor(example._straight(spec), dtype=torch.float64))
    features = robot.features(q).numpy()
    results = {}
    for k, kind in enumerate(example.TRAJECTORIES, start=1):
        desired = example.trajectory(kind, spec, n, n // 2).numpy()
        results[kind] = {"desired": desired, "actual": desired + [0.0, 0.0, 1e-5 * k], "q": np.tile(q.numpy(), (n, 1)),
                         "features": np.repeat(features[None], n, axis=0), "step_us": np.full(n, 100.0)}
    return results


def test_tracking_recording_has_a_named_full_range_plot_per_trajectory_and_opens_at_the_end(tmp_path):
    example = _example()
    robot = example.SimulatedRobot(RobotSpec.from_yaml(ROOT / "configs" / "robots" / "type1.yaml"))
    path = tmp_path / "track.rrd"
    example.write_recording(path, robot, _tracking_results(example, robot), every=5)
    views = _views(path).values()
    plots = sorted((v for v in views if v["class"] == "TimeSeries"), key=lambda v: v["origin"])
    # one plot per trajectory, each titled with its own name (not two plots called …/tracking_error_mm)
    assert [v["origin"] for v in plots] == ["metrics/circle", "metrics/figure8"]
    assert plots[0]["name"].startswith("circle: tracking error [mm]")
    assert plots[1]["name"].startswith("figure-8: tracking error [mm]")
    assert "RMS 0.0100" in plots[0]["name"] and "RMS 0.0200" in plots[1]["name"]
    assert all(v["ranges"] == [{"timeline": "step", "range": WHOLE_RANGE}] for v in plots)  # every step
    # one 3D view of the reference and actual paths and the robot, for both trajectories
    (scene,) = [v for v in views if v["class"] == "3D"]
    assert scene["origin"] == "scene" and not scene["hidden"]
    assert all(w in scene["name"] for w in ("reference", "actual", "robot", "circle", "figure-8"))
    data = _data(path)
    assert {"/scene/circle/desired", "/scene/circle/actual", "/scene/figure8/robot/backbone",
            "/scene/figure8/title"} <= set(data)
    assert data["/metrics/figure8/tracking_error_mm"]["SeriesLines:names"][0][0].startswith("|actual − reference|")
    panel = _time_panel(path)
    assert panel["TimePanelBlueprint:timeline"] == ["step"] and panel["TimePanelBlueprint:play_state"] == [FOLLOWING]


# ---------------------------------------------------------------------------------------------------------------
# the hardware benchmark's val_tip_paths.rrd


class _FakeCC:
    """The CC model's backbone of a straight robot along z (enough for the recording)."""

    def backbone(self, x: torch.Tensor) -> torch.Tensor:
        return torch.linspace(0, 0.1, 5)[:, None] * torch.tensor([0.0, 0.0, 1.0]) + 0 * x[:, :1, None]


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
    views = _views(path).values()
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
    data = _data(path)
    ranked = [f"model_{k}" for k in range(10)] + ["cc"]
    for rank, name in enumerate(ranked, start=1):
        bar = data[f"/rmse/{rank}_{name}"]
        assert bar["BarChart:abscissa"][0][0]["buffer"] == [rank]
        assert bar["BarChart:color"] == data[f"/errors/{name}"]["SeriesLines:colors"]
        rmse = np.sqrt(np.mean(np.square(data[f"/errors/{name}"]["Scalars:scalars"])))
        assert bar["BarChart:values"][0][0]["buffer"][0] == pytest.approx(rmse, rel=1e-5)
    assert data["/errors/model_6"]["SeriesLines:names"][0][0].endswith("mm, default)")
    assert "| 7 | model_6 (default) |" in data["/summary"]["TextDocument:text"][0][0]
    panel = _time_panel(path)
    assert panel["TimePanelBlueprint:timeline"] == ["sample"] and panel["TimePanelBlueprint:play_state"] == [FOLLOWING]


def test_hardware_recording_without_a_default_shows_the_best_three(tmp_path):
    path = tmp_path / "hw.rrd"
    n = 30
    models = _hardware_recording(path, default=None, std={"model_1": torch.full((n,), 1e-3),
                                                          "model_5": torch.full((n,), 1e-3)})
    views = _views(path).values()
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
