"""Ablation runner (dacr_learn.ablation): quick grid end to end, common-mode invariance, resume."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from conftest import ROOT, no_ablation_reports

import dacr_learn.cli.ablation as ablation_cli
from dacr_learn.ablation import COLUMNS, load_config, make_jobs, report, runner
from dacr_learn.cli.ablation import main
from dacr_learn.data import SamplerOptions, generate
from dacr_learn.robot import RobotSpec
from dacr_learn.training import FKModule

CONFIG = ROOT / "configs" / "ablation" / "default.yaml"


def read_csv(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("ablation_quick")
    result = main(["--config", str(CONFIG), "--quick", "--out", str(out), "--workers", "1", "--no-progress"])
    return out, result


@pytest.mark.slow
def test_quick_grid_writes_every_column_and_report(quick_run):
    out, result = quick_run
    cfg = load_config(CONFIG, quick=True)
    jobs = make_jobs(cfg)
    assert result["ran"] == len(jobs) and result["skipped"] == 0
    rows = read_csv(out / "results.csv")
    assert list(rows[0]) == COLUMNS
    assert len(rows) == sum(len(runner.conditions(cfg, j)) for j in jobs)
    assert {r["task"] for r in rows} == {"fk", "ik"} and {r["features"] for r in rows} == {"clarke", "raw"}
    assert {r["condition"] for r in rows} == {"clean", "joint_noise", "offset", "pose_noise", "transfer_n6"}
    for r in rows:
        raw_transfer = r["condition"] == "transfer_n6" and r["features"] == "raw"
        for col in ("pos_err_mean_mm", "pos_err_mean_pct", "rot_err_mean_deg"):
            assert math.isnan(float(r[col])) == raw_transfer, (col, r)
        assert float(r["train_seconds"]) > 0
        if r["task"] == "ik" and not raw_transfer:
            assert math.isfinite(float(r["constraint_residual_max_m"])) and math.isfinite(float(r["joint_err_mean_mm"]))
        if raw_transfer:
            assert "cannot be fed" in r["note"]
    # IK with Clarke features satisfies the displacement constraint by construction; raw does not.
    ik = [r for r in rows if r["task"] == "ik" and r["condition"] == "clean"]
    assert max(float(r["constraint_residual_max_m"]) for r in ik if r["features"] == "clarke") < 1e-6
    assert min(float(r["constraint_residual_max_m"]) for r in ik if r["features"] == "raw") > 1e-6
    summary = (out / "summary.md").read_text()
    assert "| type0_n4 | clean | 1000 |" in summary and "### IK" in summary
    assert {p.name for p in out.glob("*.png")} >= {"fk_clean.png", "fk_offset.png", "ik_clean.png"}
    assert (out / "ablation.rrd").stat().st_size > 0


@pytest.mark.slow
def test_resume_skips_finished_jobs(quick_run, tmp_path, monkeypatch):
    out, _ = quick_run
    rows = read_csv(out / "results.csv")
    # A second call on a complete directory trains nothing.
    monkeypatch.setattr(ablation_cli, "write_reports", no_ablation_reports)
    monkeypatch.setattr(runner, "fit", lambda *a, **k: pytest.fail("a finished job was trained again"))
    again = main(["--config", str(CONFIG), "--quick", "--out", str(out), "--no-progress"])
    assert again["ran"] == 0 and again["skipped"] == len(make_jobs(load_config(CONFIG, quick=True)))
    assert read_csv(out / "results.csv") == rows
    # Interrupted grid: the last job's rows are cut off mid-write → only that job runs again.
    monkeypatch.undo()
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "config.json").write_text((out / "config.json").read_text())
    last = tuple(rows[-1][k] for k in runner.KEY)
    kept = [r for r in rows if tuple(r[k] for k in runner.KEY) != last]
    partial = [r for r in rows if tuple(r[k] for k in runner.KEY) == last][:1]
    runner.rewrite(cut / "results.csv", kept + partial)
    with (cut / "results.csv").open("a") as f:
        f.write("type0_n4,fk,cla")                          # a truncated line, as after a kill
    trained = []
    real_fit = runner.fit
    monkeypatch.setattr(ablation_cli, "write_reports", no_ablation_reports)
    monkeypatch.setattr(runner, "fit", lambda cfg, job, spec: trained.append(job) or real_fit(cfg, job, spec))
    resumed = main(["--config", str(CONFIG), "--quick", "--out", str(cut), "--no-progress"])
    assert resumed["ran"] == 1 and [j.key for j in trained] == [last]
    new = read_csv(cut / "results.csv")
    assert len(new) == len(rows)
    assert {tuple(r[k] for k in ("robot", "task", "features", "n_train", "seed", "condition")) for r in new} == \
        {tuple(r[k] for k in ("robot", "task", "features", "n_train", "seed", "condition")) for r in rows}


def test_resume_refuses_other_settings(tmp_path):
    (tmp_path / "config.json").write_text('{"model": {"width": 1}}')
    with pytest.raises(SystemExit, match="different settings"):
        runner.check_frozen(load_config(CONFIG, quick=True), tmp_path)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("robot", ["type0_n3", "type0_n4", "type0_n6"])
def test_common_mode_offset_leaves_clarke_fk_unchanged(robot, dtype, tol):
    """Symmetric type-0 joints: M_P·1 = 0, so the Clarke encoder removes a common offset exactly and the
    Clarke FK model's prediction does not move, trained or not: to round-off in float64 (1e-12) and in
    float32 (1e-5: q ≈ 0.1 m is rounded to ~1e-8 m, and the standardisation and the network amplify
    that ulp). The raw model has no such guarantee: its prediction moves (asserted below)."""
    spec = RobotSpec.from_yaml(ROOT / "configs" / "robots" / f"{robot}.yaml")
    clean = generate(spec, 256, seed=3, dtype=dtype)
    shifted = generate(spec, 256, seed=3, options=SamplerOptions(common_offset=1e-3), dtype=dtype)
    assert torch.allclose(shifted["q"] - clean["q"], torch.full_like(clean["q"], 1e-3), atol=1e-7)
    moved = {}
    for features in ("clarke", "raw"):
        torch.manual_seed(0)
        module = FKModule(robot=spec.to_dict(), features=features, width=32, depth=2).to(dtype).eval()
        module.model.fit_normalization(clean["q"])
        with torch.no_grad():
            moved[features] = (module(clean["q"]) - module(shifted["q"])).abs().max().item()
    assert moved["clarke"] < tol
    assert moved["raw"] > 1e-3 and moved["raw"] > 1e3 * tol      # the raw model's prediction changes


@pytest.mark.slow          # the quick grid's rows: with the other grid tests, so the grid runs in one process
def test_offset_condition_rows_match_clean_for_symmetric_clarke(quick_run):
    """In the grid itself: for the symmetric robot the Clarke FK rows of 'offset' equal 'clean'."""
    out, _ = quick_run
    rows = [r for r in read_csv(out / "results.csv") if r["robot"] == "type0_n4" and r["task"] == "fk"]
    for r in rows:
        if r["features"] == "clarke" and r["condition"] == "offset":
            clean = next(c for c in rows if c["condition"] == "clean" and
                         all(c[k] == r[k] for k in ("features", "n_train", "seed")))
            assert float(r["pos_err_mean_mm"]) == pytest.approx(float(clean["pos_err_mean_mm"]), abs=1e-4)


def test_structure_axis_applies_to_clarke_fk_only():
    cfg = load_config(CONFIG, quick=True)
    assert cfg["structures"] == ["monolithic"]                      # default: the grid is unchanged
    plain = make_jobs(cfg)
    cfg["structures"] = ["monolithic", "compositional"]
    jobs = make_jobs(cfg)
    extra = [j for j in jobs if j.structure == "compositional"]
    assert [j for j in jobs if j.structure == "monolithic"] == plain
    assert extra and all(j.task == "fk" and j.features == "clarke" for j in extra)
    assert len(extra) == len(cfg["robots"]) * len(cfg["n_train"]) * len(cfg["seeds"])
    assert len({j.key for j in jobs}) == len(jobs)


def test_unknown_structure_is_refused(tmp_path):
    text = CONFIG.read_text() + "\nstructures: [monolithic, tree]\n"
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(ValueError, match=r"structures: unknown \['tree'\]"):
        load_config(tmp_path / "c.yaml")


@pytest.mark.parametrize("data,match", [("{source: cosserrat}", "data: expected source"),
                                        ("{source: cosserat, cache: x}", "data: expected source"),
                                        ("{source: cosserat, cosserat: {tension: 1.0}}", "unknown option")])
def test_a_bad_data_block_is_refused_before_the_first_job(tmp_path, data, match):
    (tmp_path / "c.yaml").write_text(CONFIG.read_text() + f"\ndata: {data}\n")
    with pytest.raises(ValueError, match=match):
        load_config(tmp_path / "c.yaml")


def test_model_kwargs_merge_task_then_structure():
    cfg = {"model": {"width": 8, "lr": 1.0}, "model_by_task": {"ik": {"pose_weight": 1.0}},
           "model_by_structure": {"compositional": {"rotation": "twist", "width": 4}}}
    assert runner.model_kwargs(cfg, "ik") == {"width": 8, "lr": 1.0, "pose_weight": 1.0}
    assert runner.model_kwargs(cfg, "fk") == {"width": 8, "lr": 1.0}
    assert runner.model_kwargs(cfg, "fk", "compositional") == {"width": 4, "lr": 1.0, "rotation": "twist",
                                                                 "structure": "compositional"}


def test_rows_before_the_structure_axis_are_monolithic_and_reported_as_their_features():
    old = {"robot": "r", "task": "fk", "features": "clarke", "n_train": "10", "seed": "0", "condition": "clean",
           "pos_err_mean_mm": "1.0", "rot_err_mean_deg": "0.5"}
    assert runner.row_key(old) == ("r", "fk", "clarke", "10", "0", "monolithic")
    comp = {**old, "structure": "compositional", "pos_err_mean_mm": "0.25"}
    raw = {**old, "features": "raw", "structure": "monolithic", "pos_err_mean_mm": "2.0"}
    summary = report.summary_markdown([old, raw, comp])
    assert "clarke/compositional" in summary
    assert "| r | clean | 10 | 1 | 1 ± 0 | 2 ± 0 | 2.00 | 0.5 ± 0 | 0.5 ± 0 | 0.25 ± 0 | 4.00 | 0.5 ± 0 |" in summary
    assert "compositional" not in report.summary_markdown([old, raw]).split("\n", 2)[2]


def test_structure_grid_runs_compositional_fk(tmp_path):
    """The quick structure grid: one monolithic Clarke, one raw and one compositional FK run of the
    3-segment robot (40 steps); each gives a row per condition, the compositional ones named so."""
    config = ROOT / "configs" / "ablation" / "structure.yaml"
    result = main(["--config", str(config), "--quick", "--out", str(tmp_path), "--no-progress"])
    rows = read_csv(tmp_path / "results.csv")
    assert result["ran"] == 3
    assert sorted({(r["features"], r["structure"]) for r in rows}) == [
        ("clarke", "compositional"), ("clarke", "monolithic"), ("raw", "monolithic")]
    assert len(rows) == 3 * 3 and all(math.isfinite(float(r["pos_err_mean_mm"])) for r in rows)
    assert "clarke/compositional" in (tmp_path / "summary.md").read_text()


@pytest.mark.parametrize("robots", [1, 4, 5])
def test_plot_curves_draws_one_panel_per_robot_with_a_short_last_row(robots, tmp_path):
    rows = [{"robot": f"r{k}", "task": "fk", "features": "clarke", "n_train": str(n), "seed": "0",
             "condition": "clean", "pos_err_mean_mm": str(1.0 + k), "rot_err_mean_deg": "0.5"}
            for k in range(robots) for n in (10, 100)]
    paths = report.plot_curves(rows, tmp_path)
    assert [p.name for p in paths] == ["fk_clean.png"] and paths[0].stat().st_size > 0
