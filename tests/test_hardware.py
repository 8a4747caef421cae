"""Hardware recordings: loader, servo map, slack-aware encoder, calibration, metric, CLI.

The calibration check on data/ftdcr_v4 uses the pattern labels (``rep1_tendon<k>_id<servo>_pull``)
only as the independent answer: tendon k belongs to segment k // 3, joint k % 3. The
calibration itself never reads the labels. A synthetic second robot (other servo ids, column
order, joint count and routing) checks that nothing depends on this robot's files.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
import re
from pathlib import Path

import pytest
import torch
from conftest import assert_tree_close, roundoff_tol

from dacr_learn.hardware.calibration import calibrate
from dacr_learn.hardware.ccmodel import CalibratedCC
from dacr_learn.hardware.learned import play_operator
from dacr_learn.hardware.metrics import offset_removed_rmse, tip_metrics
from dacr_learn.hardware.recording import load_recording
from dacr_learn.hardware.servo_map import ServoAssignment, ServoMap
from dacr_learn.hardware.slack import SlackAwareEncoder, solve_tendon_qp
from dacr_learn.layers import ClarkeDecoder, ClarkeEncoder
from dacr_learn.robot import RobotSpec

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "ftdcr_v4"
ROBOT = ROOT / "configs" / "robots" / "ftdcr_v4.yaml"
CALIBRATED = ROOT / "configs" / "robots" / "ftdcr_v4_calibrated.yaml"
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def spec() -> RobotSpec:
    return RobotSpec.from_yaml(ROBOT)


@pytest.fixture(scope="module")
def pulls(spec):
    return load_recording(DATA / "tendon_pull.csv", spec)


def write_csv(path: Path, header: list[str], rows: list[list]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


def read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(open(path)))
    return rows[0], rows[1:]


# ------------------------------------------------------------------------------------- loader


def test_loader_reads_the_recordings_in_si_units(spec):
    rec = load_recording(DATA / "train.csv", spec)
    assert rec.servo.shape == (1620, 9) and rec.tip.shape == (1620, 3) and len(rec.labels) == 1620
    assert rec.servo.dtype == torch.float64
    assert rec.servo_ids == ("4", "3", "9", "5", "2", "8", "6", "1", "7")
    # README: about (-2, 8, 188) mm when straight; first row is straight.
    assert torch.allclose(rec.tip[0], torch.tensor([-2.085078e-3, 8.168024e-3, 187.961009e-3], dtype=torch.float64))
    assert rec.servo.min() > -0.0101 and rec.servo.max() < 0.02
    assert rec.labels[0] == "rep1_tendon0_id4_pull"
    assert bool((rec.timestamp[1:] > rec.timestamp[:-1]).all())


def _mutated(tmp_path: Path, name: str, fn) -> Path:
    header, rows = read_csv(DATA / "val.csv")
    header, rows = fn(header, [list(r) for r in rows[:40]])
    return write_csv(tmp_path / name, header, rows)


@pytest.mark.parametrize("case, message", [
    ("missing_tip", "missing column 'tip_z'"),
    ("missing_label", "missing column 'pattern_label'"),
    ("no_servos", "no servo columns"),
    ("nan", "NaN"),
    ("text", "cannot parse"),
    ("metres_as_mm", "look too small"),
    ("mm_as_metres", "look too large"),
    ("unit_suffix", "unit mismatch"),
    ("servo_count", "servo columns but the robot"),
    ("time_backwards", "timestamps must increase"),
])
def test_loader_errors(tmp_path, spec, case, message):
    def drop(col):
        def fn(h, rows):
            i = h.index(col)
            return h[:i] + h[i + 1:], [r[:i] + r[i + 1:] for r in rows]
        return fn

    def scale(factor, cols):
        def fn(h, rows):
            for r in rows:
                for i, name in enumerate(h):
                    if name.startswith(cols):
                        r[i] = str(float(r[i]) * factor)
            return h, rows
        return fn

    def set_cell(row, col, value):
        def fn(h, rows):
            rows[row][h.index(col)] = value
            return h, rows
        return fn

    cases = {
        "missing_tip": drop("tip_z"),
        "missing_label": drop("pattern_label"),
        "no_servos": lambda h, rows: (h[:2] + h[11:], [r[:2] + r[11:] for r in rows]),
        "nan": set_cell(5, "servo_9_mm", "nan"),
        "text": set_cell(3, "tip_x", "abc"),
        "metres_as_mm": scale(1e-3, ("servo", "tip")),
        "mm_as_metres": scale(1e3, ("tip",)),
        "unit_suffix": lambda h, rows: ([c.replace("servo_4_mm", "servo_4_m") for c in h], rows),
        "servo_count": drop("servo_7_mm"),
        "time_backwards": set_cell(10, "timestamp", "0.0"),
    }
    path = _mutated(tmp_path, f"{case}.csv", cases[case])
    with pytest.raises(ValueError, match=re.escape(message)):
        load_recording(path, spec)


def test_loader_accepts_metres_when_declared(tmp_path, spec):
    header, rows = read_csv(DATA / "val.csv")
    header = [c.replace("_mm", "_m") for c in header]
    rows = [[r[0], r[1]] + [str(float(v) * 1e-3) for v in r[2:]] for r in rows[:30]]
    rec_m = load_recording(write_csv(tmp_path / "m.csv", header, rows), spec, units="m")
    rec_mm = load_recording(DATA / "val.csv", spec)
    assert torch.allclose(rec_m.tip, rec_mm.tip[:30]) and torch.allclose(rec_m.servo, rec_mm.servo[:30])


# ---------------------------------------------------------------------------------- servo map


def test_servo_map_reorders_signs_and_round_trips(tmp_path, spec, pulls):
    ids = pulls.servo_ids
    servos = tuple(ServoAssignment(sid, k % 3, k // 3, sign=-1 if k == 4 else 1, zero=1e-3 * k)
                   for k, sid in enumerate(ids))
    smap = ServoMap(spec.name, servos, -0.01)
    smap.to_yaml(tmp_path / "map.yaml")
    assert ServoMap.from_yaml(tmp_path / "map.yaml") == smap
    x = smap.displacements(spec, pulls)
    # joint (segment j, joint i) is column 3i + j here
    for j in range(3):
        for i in range(3):
            k = 3 * i + j
            expected = (-1 if k == 4 else 1) * (pulls.servo[:, k] - 1e-3 * k)
            assert torch.allclose(x[:, 3 * j + i], expected)
    assert torch.allclose(smap.servo_values(spec, ids, x), pulls.servo)
    broken = ServoMap(spec.name, servos[:-1] + (ServoAssignment(ids[-1], 0, 0),), -0.01)
    with pytest.raises(ValueError, match="slots missing"):
        broken.check(spec)


# ------------------------------------------------------------------------- slack-aware encoder


@pytest.mark.parametrize("routing", ["coupled", "independent"])
def test_slack_encoder_is_exact_for_consistent_commands(routing):
    d = RobotSpec.from_yaml(ROBOT).to_dict() | {"routing": routing}
    spec = RobotSpec.from_dict(d)
    g = torch.Generator().manual_seed(0)
    feat = torch.zeros(64, 3, 4, dtype=torch.float64)
    feat[..., :2] = (torch.rand(64, 3, 2, generator=g, dtype=torch.float64) - 0.5) * 0.008
    feat[..., 2] = torch.tensor([s.length for s in spec.segments], dtype=torch.float64)
    decoder = ClarkeDecoder(spec)
    q = decoder(feat)
    x = decoder(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - q
    enc = SlackAwareEncoder(spec, compliance=1e-14)
    with torch.no_grad():
        got = enc(x)
    assert torch.allclose(got, feat, atol=1e-9)
    assert torch.allclose(got, ClarkeEncoder(spec)(q), atol=1e-9)


def test_slack_encoder_single_pull_bends_towards_the_tendon_with_equal_curvature(spec):
    enc = SlackAwareEncoder(spec, compliance=1e-14)
    x = torch.full((9,), -0.01, dtype=torch.float64)
    x[6] = 0.002                                                   # segment 3, joint 0 (ψ = 0)
    with torch.no_grad():
        rho = enc(x)[:, :2]
    lengths = torch.tensor([s.length for s in spec.segments], dtype=torch.float64)
    assert torch.allclose(rho[:, 1], torch.zeros(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(rho[:, 0].sum(), torch.tensor(0.002, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(rho[:, 0] / lengths, (rho[0, 0] / lengths[0]).expand(3), rtol=1e-8)
    with torch.no_grad():
        slack = enc(torch.full((9,), -0.01, dtype=torch.float64))
        assert torch.equal(slack[:, :2], torch.zeros(3, 2, dtype=torch.float64))


def test_slack_encoder_gradients_match_finite_differences(spec):
    enc = SlackAwareEncoder(spec, compliance=2e-6, pretension=1e-4)
    x = torch.tensor([[2e-3, -1e-3, -1e-3, 1e-3, -3e-3, 0.0, 2e-3, -9e-3, 1e-3]], dtype=torch.float64)
    names = ["log_radius_scale", "rotation", "log_compliance", "pretension"]
    inputs = tuple(enc.get_parameter(n).detach().clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(
        lambda *p: torch.func.functional_call(enc, dict(zip(names, p, strict=True)), (x,))[..., :2], inputs,
        eps=1e-7, atol=1e-7)


def test_slack_encoder_balances_forces_so_straight_tendons_cause_no_torsion(spec):
    """At the solution, each segment's bending energy gradient equals the force of the taut
    tendons through it (KKT stationarity of E), slack tendons carry nothing, and so each ρ⁽ᵏ⁾ is
    parallel to the total tendon force through segment k — the moment of straight-routed tendons
    about the backbone, cross(ρ⁽ᵏ⁾, F), vanishes (docs/hardware.md: the model predicts no twist).
    The tendon directions are rebuilt here from the spec's joint angles, not from the encoder."""
    enc = SlackAwareEncoder(spec, compliance=2e-6, pretension=5e-5)
    with torch.no_grad():
        enc.rotation.copy_(torch.tensor([0.1, -0.2, 0.3]))
        enc.log_radius_scale.copy_(torch.tensor([0.05, -0.1, 0.0]))
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(200, 9, generator=g, dtype=torch.float64) - 0.6) * 8e-3   # mixes taut and slack tendons
    x[:50, 3:] = -0.01                                                        # parked slack, as in the pulls
    with torch.no_grad():
        rho = enc.clarke(x)                                                   # (n, 3, 2) at the effective radii
        gmap = enc.displacement_map()
        stretch = x + enc.pretension - rho.flatten(-2) @ gmap.mT
        tension = stretch.clamp_min(0) / enc.path_length                      # slack tendons: 0
        d = enc.effective_radius()
        bend_w = enc.log_compliance.exp() / (enc.lengths * d**2)
    lhs = bend_w[:, None] * rho
    rhs = (tension @ gmap).unflatten(-1, (3, 2))
    assert torch.allclose(lhs, rhs, atol=1e-12 * float(rhs.abs().max()))     # stationarity
    assert (stretch > 0).any() and (stretch < 0).any()
    psi = torch.tensor([a for s in spec.segments for a in s.joint_angles], dtype=torch.float64)
    segment = torch.arange(3).repeat_interleave(3)
    psi = psi + enc.rotation.detach()[segment]
    force = torch.zeros(200, 3, 2, dtype=torch.float64)
    force.index_add_(1, segment, tension.unsqueeze(-1) * torch.stack([psi.cos(), psi.sin()], -1))
    through = force.flip(1).cumsum(1).flip(1)                                 # Σ over segments j ≥ k
    torque = rho[..., 0] * through[..., 1] - rho[..., 1] * through[..., 0]
    scale = rho.norm(dim=-1) * through.norm(dim=-1)
    assert float(scale.max()) > 0
    assert float((torque.abs() / scale.clamp_min(1e-30)).max()) < 1e-9
    # an explicit force map equal to G gives the same solution; a reduced one, its own balance
    flat = x + enc.pretension
    same = solve_tendon_qp(flat, gmap, bend_w.repeat_interleave(2), 1 / enc.path_length,
                           force_map=gmap.expand(200, -1, -1))
    tol = roundoff_tol(torch.float64, float(rho.abs().max()), ulps=1024)
    assert torch.allclose(same, rho.flatten(-2), rtol=0, atol=tol)
    reduced = gmap * torch.linspace(0.6, 1.0, 9, dtype=torch.float64)[:, None]
    rho_f = solve_tendon_qp(flat, gmap, bend_w.repeat_interleave(2), 1 / enc.path_length,
                            force_map=reduced.expand(200, -1, -1))
    tension_f = (flat - rho_f @ gmap.mT).clamp_min(0) / enc.path_length
    assert torch.allclose(bend_w.repeat_interleave(2) * rho_f, tension_f @ reduced, atol=1e-12 * float(rhs.abs().max()))
    assert not torch.allclose(rho_f, rho.flatten(-2), atol=1e-6)
    # an external load (e.g. gravity) enters the same balance: bend_w·ρ = Gᵀ·tension + load
    assert torch.allclose(enc.bend_weights(), bend_w.repeat_interleave(2), rtol=1e-14)
    load = (torch.rand(200, 6, generator=g, dtype=torch.float64) - 0.5) * 2e-3
    rho_l = solve_tendon_qp(flat, gmap, enc.bend_weights(), 1 / enc.path_length, load=load)
    tension_l = (flat - rho_l @ gmap.mT).clamp_min(0) / enc.path_length
    assert torch.allclose(bend_w.repeat_interleave(2) * rho_l, tension_l @ gmap + load,
                          atol=1e-12 * float(rhs.abs().max()))
    assert not torch.allclose(rho_l, rho.flatten(-2), atol=1e-6)


# ---------------------------------------------------------------------------------- calibration


def label_truth(rec) -> dict[str, tuple[int, int]]:
    """servo id → (segment, joint) from labels like rep1_tendon4_id2_pull (the independent answer)."""
    truth = {}
    for label in rec.labels:
        m = re.search(r"tendon(\d+)_id([^_]+)_", label)
        if m:
            k = int(m.group(1))
            truth[m.group(2)] = (k // 3, k % 3)
    return truth


# The calibration ends in least-squares fits whose last digits follow the CPU's float kernels (one
# ulp of an angle on another CPU was seen); sqrt(eps) ≈ 1.5e-8 (rad or m) is the precision such a
# fitted value can be asked for, and 1e4 times finer than any physical meaning of these numbers.
CALIBRATION_TOL = float(torch.finfo(torch.float64).eps) ** 0.5


def assert_matches_committed_calibration(cal_spec: RobotSpec, smap: ServoMap, calibrated: Path) -> None:
    """The committed calibrated YAML and servo map are this result: the same structure and servo ids,
    floats equal up to the rounding of another CPU's BLAS/LAPACK kernels (angles [rad], lengths [m])."""
    assert_tree_close(cal_spec.to_dict(), RobotSpec.from_yaml(calibrated).to_dict(), atol=CALIBRATION_TOL)
    committed = ServoMap.from_yaml(calibrated.parent / "servo_maps" / calibrated.name)
    assert_tree_close([dataclasses.asdict(a) for a in smap.servos], [dataclasses.asdict(a) for a in committed.servos],
                      atol=CALIBRATION_TOL)
    assert smap.slack_level == pytest.approx(committed.slack_level, rel=0, abs=CALIBRATION_TOL)


def test_calibration_recovers_the_servo_map_of_ftdcr_v4(spec, pulls):
    truth = label_truth(pulls)
    assert len(truth) == 9
    cal_spec, smap, report = calibrate(pulls, spec)
    got = {a.servo: (a.segment, a.joint) for a in smap.servos}
    assert got == truth
    assert all(a.sign == 1 for a in smap.servos)
    assert report["slack_level_mm"] == pytest.approx(-9.99, abs=0.02)
    for seg, expected in zip(report["segments"], (-174.0, -145.0, -115.0), strict=True):
        assert seg["offset_deg"] == pytest.approx(expected, abs=3.0)
        assert seg["angle_rms_deg"] < 8.0
    assert_matches_committed_calibration(cal_spec, smap, CALIBRATED)


def test_calibration_ignores_column_order_and_ids(spec, pulls):
    perm = [5, 0, 8, 2, 7, 1, 4, 6, 3]
    renamed = tuple(f"m{pulls.servo_ids[p]}" for p in perm)
    shuffled = type(pulls)(renamed, pulls.servo[:, perm], pulls.tip, pulls.labels, pulls.timestamp, "shuffled")
    _, smap, _ = calibrate(shuffled, spec)
    got = {a.servo[1:]: (a.segment, a.joint) for a in smap.servos}
    truth = label_truth(pulls)
    for sid, (seg, _joint) in truth.items():          # same segments; joints up to a cyclic relabelling
        assert got[sid][0] == seg
    for seg in range(3):
        ids = [s for s in truth if truth[s][0] == seg]
        shift = {(got[s][1] - truth[s][1]) % 3 for s in ids}
        assert len(shift) == 1


# -------------------------------------------------------------------------------------- metric


def test_offset_removed_rmse_hand_computed():
    meas = torch.zeros(2, 3, dtype=torch.float64)
    pred = torch.tensor([[1.0, 0, 0], [3.0, 0, 0]], dtype=torch.float64)   # mean offset (2,0,0), residuals ±1
    assert float(offset_removed_rmse(pred, meas)) == pytest.approx(1.0)
    assert float(offset_removed_rmse(meas + torch.tensor([5.0, -2, 7]), meas)) == pytest.approx(0.0, abs=1e-12)
    pred = torch.tensor([[3e-3, 4e-3, 0], [0, 0, 0]], dtype=torch.float64)  # errors 5 mm and 0 mm
    m = tip_metrics(pred, meas)
    assert m["rmse_mm"] == pytest.approx(2.5) and m["mean_mm"] == pytest.approx(2.5)
    assert m["offset_mm"] == pytest.approx(2.5) and m["p95_mm"] == pytest.approx(0.95 * 5.0)
    with pytest.raises(ValueError, match="equal shapes"):
        offset_removed_rmse(pred, meas[:1])


def test_play_operator_lags_by_the_width():
    v = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [1.5, 0.0]], dtype=torch.float64)
    out = play_operator(v, 0.25)
    assert torch.allclose(out[:, 0], torch.tensor([0.0, 0.75, 1.75, 1.75], dtype=torch.float64))
    assert torch.equal(play_operator(v, torch.full((4,), 0.25, dtype=torch.float64)), out)
    per_row = play_operator(v, torch.tensor([0.0, 0.5, 0.1, 0.2], dtype=torch.float64))
    assert torch.allclose(per_row[:, 0], torch.tensor([0.0, 0.5, 1.9, 1.7], dtype=torch.float64))
    x = torch.tensor([[0.0], [1.0], [0.6], [-1.0]], dtype=torch.float64)      # scalar play = clamp
    assert torch.allclose(play_operator(x, 0.3)[:, 0], torch.tensor([0.0, 0.7, 0.7, -0.7], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"broadcastable to \(4,\), got shape \(3,\)"):
        play_operator(v, torch.ones(3, dtype=torch.float64))                  # widths for 3 rows, 4 given
    with pytest.raises(ValueError, match="widths >= 0"):
        play_operator(v, -0.1)


# ------------------------------------------------------ a second (synthetic) robot, same command

TRUE_OFFSETS = (0.4, -1.1)


def _second_robot(tmp_path: Path) -> tuple[Path, RobotSpec]:
    nominal = {"name": "synthetic-2seg", "routing": "coupled", "segments": [
        {"type": "0", "length": 0.08, "radius": 0.005, "joints": 4, "offset": 0.0, "limits": {"bend": 0.8}},
        {"type": "0", "length": 0.07, "radius": 0.005, "joints": 4, "offset": 0.0, "limits": {"bend": 0.8}}]}
    path = tmp_path / "synthetic_2seg.yaml"
    RobotSpec.from_dict(nominal).to_yaml(path)
    true = {**nominal, "segments": [s | {"offset": o} for s, o in zip(nominal["segments"], TRUE_OFFSETS, strict=True)]}
    return path, RobotSpec.from_dict(true)


def _write_recording(path: Path, ids, cols, model, spec, x: torch.Tensor, labels) -> None:
    with torch.no_grad():
        tip = model(x) + 1e-4 * torch.randn(x.shape[0], 3, generator=torch.Generator().manual_seed(1),
                                            dtype=torch.float64)
    servo = x[:, cols]                                           # column c shows joint cols[c]
    rows = [[1000.0 + 0.5 * k, labels[k]] + [f"{v * 1e3:.5f}" for v in servo[k].tolist()]
            + [f"{v * 1e3:.5f}" for v in tip[k].tolist()] for k in range(x.shape[0])]
    write_csv(path, ["timestamp", "pattern_label"] + [f"servo_{i}_mm" for i in ids] + ["tip_x", "tip_y", "tip_z"], rows)


def test_second_robot_runs_through_the_same_command(tmp_path):
    from dacr_learn.hardware.study.cli import main

    robot_yaml, true_spec = _second_robot(tmp_path)
    ids = ["B7", "A2", "C1", "A9", "B3", "C5", "A4", "B1"]
    cols = [3, 6, 0, 5, 1, 7, 2, 4]                               # joint shown by each column
    model = CalibratedCC(true_spec, compliance=1e-7)
    data = tmp_path / "data"
    data.mkdir()
    ramp = torch.cat([torch.linspace(-2e-3, 3e-3, 8), torch.linspace(3e-3, -2e-3, 8)[1:]]).double()
    pulls = torch.full((8 * len(ramp), 8), -8e-3, dtype=torch.float64)
    for c in range(8):
        pulls[c * len(ramp):(c + 1) * len(ramp), cols[c]] = ramp
    _write_recording(data / "tendon_pull.csv", ids, cols, model, true_spec, pulls, ["pull"] * len(pulls))
    g = torch.Generator().manual_seed(2)
    for name, n in (("train.csv", 300), ("val.csv", 120)):
        feat = torch.zeros(n, 2, 4, dtype=torch.float64)
        feat[..., :2] = (torch.rand(n, 2, 2, generator=g, dtype=torch.float64) - 0.5) * 0.006
        feat[..., 2] = torch.tensor([0.08, 0.07], dtype=torch.float64)
        dec = ClarkeDecoder(true_spec)
        x = dec(torch.cat([torch.zeros_like(feat[..., :2]), feat[..., 2:]], -1)) - dec(feat)
        _write_recording(data / name, ids, cols, model, true_spec, x, ["random"] * n)
    out = tmp_path / "run"
    report = main(["--data", str(data), "--robot", str(robot_yaml), "--out", str(out),
                   "--models", "linear_raw", "cc", "--seeds", "0", "--no-visuals"])
    smap = ServoMap.from_yaml(out / "servo_maps" / "calibrated_robot.yaml")
    cal = RobotSpec.from_yaml(out / "calibrated_robot.yaml")
    # Symmetric joints are only defined up to a cyclic relabelling: compare segment and angle.
    for a in smap.servos:
        true_joint = cols[ids.index(a.servo)]
        true_seg, true_i = divmod(true_joint, 4)
        assert a.segment == true_seg
        true_angle = true_spec.segments[true_seg].joint_angles[true_i]
        got_angle = cal.segments[a.segment].joint_angles[a.joint]
        assert math.remainder(got_angle - true_angle, 2 * math.pi) == pytest.approx(0.0, abs=math.radians(3))
    results = json.loads((out / "results.json").read_text())
    assert results["models"]["cc"]["val"]["rmse_mm"]["mean"] < 0.5
    assert report["best_clarke_model"] == "cc"


def test_cli_on_ftdcr_v4_writes_results_and_visuals(tmp_path):
    from dacr_learn.hardware.study.cli import main

    out = tmp_path / "run"
    report = main(["--data", str(DATA), "--robot", str(CALIBRATED), "--out", str(out),
                   "--models", "linear_raw", "cc", "--seeds", "0", "--no-proxies"])
    results = json.loads((out / "results.json").read_text())
    assert set(results["models"]) == {"linear_raw", "cc"} and results["default_model"] is None
    # README reference: linear least squares reaches 41 mm on val.csv
    assert results["models"]["linear_raw"]["val"]["rmse_mm"]["mean"] == pytest.approx(41.0, abs=1.0)
    assert results["models"]["cc"]["val"]["rmse_mm"]["mean"] < 9.0
    assert report["rows"] == {"train": 1620, "val": 443}
    assert (out / "val_tip_paths.png").stat().st_size > 10_000
    assert (out / "val_tip_paths.rrd").stat().st_size > 10_000
