"""Reports of an ablation results CSV: Markdown summary (mean ± std over seeds), PNG plots, Rerun .rrd."""
from __future__ import annotations

import math
import statistics
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import rerun as rr

FEATURE_STYLE = {"clarke": dict(color="tab:blue", marker="o"), "raw": dict(color="tab:orange", marker="s"),
                 "compositional": dict(color="tab:green", marker="^")}


def variant(row: dict) -> str:
    """The model variant of a row: its feature mode, or its structure if not monolithic (a compositional
    model has Clarke features). Rows written before the structure axis existed are monolithic."""
    structure = row.get("structure") or "monolithic"
    return row["features"] if structure == "monolithic" else structure


def _num(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def aggregate(rows: list[dict]) -> dict[tuple, dict[str, tuple[float, float, int]]]:
    """(robot, task, condition, n_train, variant) → {metric: (mean, std, seeds)} over seeds (NaN skipped)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["robot"], r["task"], r["condition"], int(r["n_train"]), variant(r)), []).append(r)
    out = {}
    for key, rs in groups.items():
        stats = {}
        for m in ("pos_err_mean_mm", "rot_err_mean_deg", "joint_err_mean_mm", "constraint_residual_max_m",
                  "train_seconds"):
            vals = [v for v in (_num(r.get(m)) for r in rs) if not math.isnan(v)]
            mean = statistics.fmean(vals) if vals else math.nan
            std = statistics.stdev(vals) if len(vals) > 1 else (0.0 if vals else math.nan)
            stats[m] = (mean, std, len(vals))
        stats["note"] = next((r.get("note", "") for r in rs if r.get("note")), "")
        stats["seeds"] = len(rs)
        out[key] = stats
    return out


def _pm(stat: tuple[float, float, int] | None, fmt: str = ".3g") -> str:
    if stat is None or math.isnan(stat[0]):
        return "n/a"
    return f"{stat[0]:{fmt}} ± {stat[1]:{fmt}}"


def _ratio(a, b) -> str:
    if a is None or b is None or math.isnan(a[0]) or math.isnan(b[0]) or a[0] == 0:
        return "n/a"
    return f"{b[0] / a[0]:.2f}"


def _order(values, preferred):
    return [v for v in preferred if v in values] + sorted(v for v in values if v not in preferred)


def _cells(agg: dict, key: tuple, ik: bool, compositional: bool) -> list[str]:
    """Table cells of one (robot, task, condition, n_train) row: Clarke, raw and (if present) compositional."""
    c, r, m = (agg.get((*key, v)) for v in ("clarke", "raw", "compositional"))
    seeds = max(s["seeds"] for s in (c, r, m) if s)
    cells = [key[0], key[2], str(key[3]), str(seeds), _pm(c and c["pos_err_mean_mm"]), _pm(r and r["pos_err_mean_mm"]),
             _ratio(c and c["pos_err_mean_mm"], r and r["pos_err_mean_mm"]),
             _pm(c and c["rot_err_mean_deg"]), _pm(r and r["rot_err_mean_deg"])]
    if compositional:
        cells += [_pm(m and m["pos_err_mean_mm"]), _ratio(m and m["pos_err_mean_mm"], c and c["pos_err_mean_mm"]),
                  _pm(m and m["rot_err_mean_deg"])]
    if ik:
        cells += [_pm(c and c["constraint_residual_max_m"], ".2g"), _pm(r and r["constraint_residual_max_m"], ".2g")]
    return cells


def summary_markdown(rows: list[dict], robots_order: list[str] | None = None) -> str:
    """Markdown tables, one per task: Clarke vs raw (and compositional, where run) per robot, condition and
    n_train (mean ± std over seeds)."""
    agg = aggregate(rows)
    robots = _order({k[0] for k in agg}, robots_order or [])
    cond_order = ["clean", "joint_noise", "offset", "pose_noise"]
    lines = [f"Results: {len(rows)} rows. Metrics are means over the fixed test set, then mean ± std over "
             f"seeds; `raw/clarke` is the ratio of the mean position errors (> 1: Clarke is better), "
             f"`clarke/compositional` that of the monolithic and compositional Clarke models.", ""]
    for task in _order({k[1] for k in agg}, ["fk", "ik"]):
        ik, comp = task == "ik", any(k[1] == task and k[4] == "compositional" for k in agg)
        head = ["robot", "condition", "n_train", "seeds", "pos err clarke [mm]", "pos err raw [mm]", "raw/clarke",
                "rot err clarke [deg]", "rot err raw [deg]"]
        head += ["pos err compositional [mm]", "clarke/compositional", "rot err compositional [deg]"] if comp else []
        head += ["constraint residual max clarke [m]", "constraint residual max raw [m]"] if ik else []
        lines += [f"### {task.upper()}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        keys = {(k[0], k[2], k[3]) for k in agg if k[1] == task}
        for robot in robots:
            for cond in _order({c for r, c, _ in keys if r == robot}, cond_order):
                for n in sorted({n for r, c, n in keys if r == robot and c == cond}):
                    lines.append("| " + " | ".join(_cells(agg, (robot, task, cond, n), ik, comp)) + " |")
        lines.append("")
    notes = sorted({s["note"] for k, s in agg.items() if s["note"]})
    if notes:
        lines += ["Notes:", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(lines)


def plot_curves(rows: list[dict], out: Path, robots_order: list[str] | None = None) -> list[Path]:
    """One PNG per (task, condition): mean position error vs n_train per robot, one line per model variant."""
    agg = aggregate(rows)
    robots = _order({k[0] for k in agg}, robots_order or [])
    paths = []
    for task, cond in sorted({(k[1], k[2]) for k in agg}):
        present = [r for r in robots if any(k[0] == r and k[1] == task and k[2] == cond for k in agg)]
        cols = min(4, len(present))
        nrows = math.ceil(len(present) / cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(3.4 * cols, 2.9 * nrows), squeeze=False)
        for ax, robot in zip(list(axes.flat)[:len(present)], present, strict=True):   # a last row may be short
            for feat, style in FEATURE_STYLE.items():
                pts = sorted((k[3], s["pos_err_mean_mm"]) for k, s in agg.items() if k[:3] == (robot, task, cond)
                             and k[4] == feat and not math.isnan(s["pos_err_mean_mm"][0]))
                if pts:
                    ax.errorbar([p[0] for p in pts], [p[1][0] for p in pts], yerr=[p[1][1] for p in pts],
                                label=feat, capsize=3, **style)
            ax.set(xscale="log", yscale="log", xlabel="n_train", ylabel="mean tip position error [mm]")
            ax.set_title(robot, fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
        for ax in list(axes.flat)[len(present):]:
            ax.axis("off")
        fig.suptitle(f"{task.upper()}, test condition: {cond} (mean ± std over seeds)")
        fig.tight_layout()
        path = out / f"{task}_{cond}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def log_rerun(rows: list[dict], pngs: list[Path], summary: str, rrd_path: Path) -> None:
    """Write the aggregated curves (timeline ``n_train``), the plots and the summary to an .rrd file."""
    rec = rr.RecordingStream("dacr_learn_ablation")
    rec.save(str(rrd_path))
    rec.log("summary", rr.TextDocument(summary, media_type=rr.MediaType.MARKDOWN), static=True)
    for png in pngs:
        rec.log(f"plots/{png.stem}", rr.EncodedImage(path=png), static=True)
    for (robot, task, cond, n, feat), s in sorted(aggregate(rows).items()):
        rec.set_time("n_train", sequence=n)
        for m in ("pos_err_mean_mm", "rot_err_mean_deg"):
            if not math.isnan(s[m][0]):
                rec.log(f"ablation/{task}/{cond}/{robot}/{m}/{feat}", rr.Scalars(s[m][0]))
    rec.flush()
    rec.disconnect()


def write_reports(rows: list[dict], out: Path, robots_order: list[str] | None = None, title: str = "") -> dict:
    """summary.md, the PNGs and ablation.rrd in ``out``; returns their paths."""
    summary = summary_markdown(rows, robots_order)
    (out / "summary.md").write_text((f"# {title}\n\n" if title else "") + summary)
    pngs = plot_curves(rows, out, robots_order)
    log_rerun(rows, pngs, summary, out / "ablation.rrd")
    return {"summary": out / "summary.md", "plots": pngs, "rrd": out / "ablation.rrd"}
