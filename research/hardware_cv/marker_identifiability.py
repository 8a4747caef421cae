"""Is the lateral marker offset of the calibrated CC model identifiable from train? (research script)

Fits ``CalibratedCC(spec, lateral_marker=False / True)`` on all of train and linearises the tip
predictions (n, 3) in the fit's scaled parameters z (θ = θ̂ + scale·z, central differences, the
scales of ``ccmodel.FIT_SCALES``). Reports per model: the singular values of the Jacobian (a
degenerate direction, e.g. a trade of the lateral offset against the joint rotations, base tilt or
translation, would show a singular value near 0), its condition number, and for the marker
parameters the nominal standard error [mm] (σ²·(JᵀJ)⁻¹ with σ² the residual variance; optimistic:
the residuals are correlated along the paths) and the largest correlation with another parameter.
One JSON line per model on stdout (the docs' lines: results/marker_identifiability.jsonl); ~1 min.

Numbers: docs/history/hardware.md, "2026-11-23: Lateral marker offset" (Identifiability).
Run from the repository root: [HW_ROBOT=v6] python -m research.hardware_cv.marker_identifiability
"""

import json

import torch

from dacr_learn.hardware.ccmodel import FIT_SCALES, CalibratedCC, fit_cc

from .common import setup

STEP = 1e-4   # in scaled units (a tenth of a micrometre for the marker, 5e-6 rad for the joint rotations)


def jacobian(cc: CalibratedCC, x_tr: torch.Tensor) -> tuple[torch.Tensor, list[str]]:
    """∂tip/∂z (n·3, P) [m per scaled unit] at the commands x_tr and the name of each column (parameter[index])."""
    base = {n: p.detach().clone() for n, p in cc.named_parameters()}
    cols, names = [], []
    for n, value in base.items():
        for i in range(value.numel()):
            delta = torch.zeros_like(value).flatten()
            delta[i] = FIT_SCALES[n] * STEP
            preds = []
            for sign in (1, -1):
                params = {**base, n: value + sign * delta.reshape(value.shape)}
                preds.append(torch.func.functional_call(cc, params, (x_tr,)))
            cols.append(((preds[0] - preds[1]) / (2 * STEP)).flatten())
            names.append(f"{n}[{i}]" if value.numel() > 1 else n)
    return torch.stack(cols, -1), names


def analyse(lateral: bool) -> dict:
    d = setup()
    x_tr, tip_tr = d.x_tr, d.tip_tr
    cc = CalibratedCC(d.spec, lateral_marker=lateral)
    fit = fit_cc(cc, x_tr, tip_tr)
    with torch.no_grad():
        jac, names = jacobian(cc, x_tr)
        res = (cc(x_tr) - tip_tr).flatten()
    sv = torch.linalg.svdvals(jac)
    cov = torch.linalg.inv(jac.T @ jac) * (res @ res) / (len(res) - len(names))
    std = cov.diagonal().sqrt()
    corr = cov / std[:, None] / std[None, :]
    marker = {}
    for i, n in enumerate(names):
        if "marker" in n or n == "tip_offset":
            others = corr[i].abs().clone()
            others[i] = 0
            j = int(others.argmax())
            scale = FIT_SCALES[n.split("[")[0]] * 1e3      # scaled unit → mm
            marker[n] = {"std_err_mm": round(float(std[i]) * scale, 3),
                         "max_corr": [names[j], round(float(corr[i, j]), 3)]}
    return {"robot": d.robot, "lateral_marker": lateral, "train_rms_mm": round(fit["rms_m"] * 1e3, 3),
            "parameters": len(names), "singular_values_min3": [round(float(v), 5) for v in sv[-3:]],
            "condition": round(float(sv[0] / sv[-1]), 1), "marker": marker, "report": cc.report()}


def main() -> None:
    torch.set_num_threads(1)
    for lateral in (False, True):
        print(json.dumps(analyse(lateral)), flush=True)


if __name__ == "__main__":
    main()
