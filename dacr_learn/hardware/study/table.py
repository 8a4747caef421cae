"""The hardware benchmark's results table (results.md and the CLI's table): every model's train-only proxies with
their bootstrap σ and, when a validation recording exists, its metrics (mean ± std over seeds)."""
from __future__ import annotations


def _pm(d: dict | None) -> str:
    if d is None:
        return "–"
    return f"{d['mean']:.2f} ± {d['std']:.2f}" if len(d["per_seed"]) > 1 else f"{d['mean']:.2f}"


def markdown_table(results: dict, scores: dict | None = None, default: str | None = None) -> str:
    """Results table in Markdown: proxies (train only), val metrics when present (mean ± std over seeds)."""
    scores = scores or {}
    lines = ["| model | inputs | family CV [mm] | singles→pairs [mm] (± bootstrap σ) | val RMSE, offset removed [mm] | "
             "val mean [mm] | val p95 [mm] | train RMSE [mm] | seeds |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        v, t, p = r.get("val", {}), r["train"], scores.get(name, {})
        inputs = ("Clarke" if r["clarke_space"] else "raw servo") + ("" if r["static"] else " + history")
        proxy = [(f"{p[k]:.2f} ± {p[k + '_std']:.2f}" if k + "_std" in p else f"{p[k]:.2f}") if k in p else "–"
                 for k in ("cv", "extrap")]
        shown = f"**`{name}`** (default)" if name == default else f"`{name}`"
        lines.append(f"| {shown} | {inputs} | {proxy[0]} | {proxy[1]} | {_pm(v.get('rmse_mm'))} | "
                     f"{_pm(v.get('mean_mm'))} | {_pm(v.get('p95_mm'))} | {_pm(t['rmse_mm'])} | {len(r['seeds'])} |")
    return "\n".join(lines)
