"""Calibrated Cosserat-rod model of a tendon robot: joint displacements → tip position (docs/hardware.md, "The
Cosserat-rod model of the robot", describes the model and its fit).

    x (n, N) [m] ──rest lengths ℓ = L₀ − x − p──▶ solve_displacements ──▶ tip pose (base frame)
    tip = R_base · (p_tip + R_tip · d_marker) + t_base      (motion-capture frame, metres)

The mechanics of :mod:`dacr_learn.cosserat`, started from the calibrated CC model (:class:`~.ccmodel.CalibratedCC`,
whose parameters mean the same here), plus the robot's weight per length g = w·u [N/m] (w ∈ [0, :data:`WEIGHT_MAX`])
and the backbone's axial stiffness. Fitted by Levenberg–Marquardt (:meth:`CalibratedCosserat.fit`); gradient-free:
scored and used to generate data, not exported.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..body import BodyPoints
from ..cosserat.displacement import DisplacementSolution, solve_displacements
from ..robot import RobotSpec
from .ccmodel import CalibratedCC

BENDING_STIFFNESS = 6.0e10 * math.pi * 0.0005**4 / 4   # EI [N·m²] of a 1 mm NiTi wire: the scale of the tensions
POISSON_RATIO = 0.33
AXIAL_RADIUS = 5e-5      # [m] initial r_a: EA = 4·EI/r_a² (a 1 mm wire: 0.5 mm). Small: the start is the CC model
STEPS_PER_SEGMENT = 4     # RK4 steps per segment: tips within 3 µm of 32 steps on v4 / v6 training commands
FIT_ROWS = 240            # training rows the mechanics are fitted on (a seeded subset; half the solves of 480)
FIT_ITERATIONS = 6
SOLVE_TOL = 1e-8          # [m] tendon-length violation accepted: far below the finite differences of the fit
FIT_STALL = 1e-3          # stop when an iteration lowers the RMS by less than this fraction
# physics parameters, re-solved for their finite differences: name → the unit of an LM step in it
PHYSICS_SCALES = {"gravity": 0.3, "log_radius_scale": 0.05, "log_compliance": 0.5, "log_axial_radius": 0.3,
                  "pretension": 1e-4, "pretension_strain": 1e-4}
AXIAL_STARTS = (5e-5, 1e-3)   # [m] axial radii the fit starts from: near the CC model, and a compressible rod
# [N/m] bound of the fitted weight per length ‖g‖: a robot of this size weighs well under it; unbounded, the v6 fit
# ran to 1.6 N/m upwards and beyond, into ever more nonlinear (and slower) solves
WEIGHT_MAX = 0.5
AXIAL_RADIUS_RANGE = (1e-5, 2e-3)   # [m]: from an inextensible backbone (the CC limit) to a 4 mm wire
FD_FRACTION = 0.2         # finite-difference step of a physics parameter, in units of its scale
# physics parameters that leave the robot description as it is (they change the rest lengths, the gravity or the
# tendons' spring lengths): their finite differences are solved together, in one batch (_solve_trials)
SHARED_SPEC = ("gravity", "log_compliance", "pretension", "pretension_strain")
MAX_STEP = 3.0            # largest LM step per parameter, in units of its scale (a trust region)
FRAME_SCALE = 1e-3        # [rad] or [m]: the step unit of the tilt and marker parameters


@dataclass
class WarmStart:
    """Per-row tensions (n, T) [N] and chord matrices (n, T, T) of the last solve, for the next nearby one."""

    tension: Tensor
    compliance: Tensor


class CalibratedCosserat:
    """Joint displacements (..., N) [m] → tip position (..., 3) [m] in the motion-capture frame, by the
    Cosserat rod of the calibrated robot. Build from a fitted :class:`CalibratedCC` (copied, not changed)."""

    def __init__(self, cc: CalibratedCC, weight: float = 0.0, axial_radius: float = AXIAL_RADIUS,
                 steps_per_segment: int = STEPS_PER_SEGMENT, direction: tuple[float, float, float] = (0.0, 0.0, -1.0)):
        """``weight`` w ≥ 0 [N/m] acts along ``direction`` (a vector of the motion-capture frame, normalised)."""
        self.cc = copy.deepcopy(cc)
        self.cc.requires_grad_(False)
        u = torch.as_tensor(direction, dtype=torch.float64)
        if not (weight >= 0) or u.shape != (3,) or not bool(u.norm() > 0):
            raise ValueError(f"weight, direction: expected a weight >= 0 [N/m] and a non-zero 3-vector, got {weight!r} "
                             f"and {tuple(direction)!r}")
        self.gravity_vector = float(weight) * u / u.norm()      # g = w·u [N/m], motion-capture frame
        self.log_axial_radius = math.log(axial_radius)
        self.steps = int(steps_per_segment)
        enc = self.cc.encoder
        self.spec0 = cc.spec
        self.path_length = enc.path_length.detach().clone()

    # -- the mechanics ---------------------------------------------------------------------------------------
    def physics(self) -> dict[str, Tensor]:
        """Current values of the re-solved parameters (float64 tensors)."""
        enc = self.cc.encoder
        out = {"gravity": self.gravity_vector.clone(),
               "log_axial_radius": torch.tensor(self.log_axial_radius, dtype=torch.float64),
               "log_radius_scale": enc.log_radius_scale.detach().clone(),
               "log_compliance": enc.log_compliance.detach().clone(), "pretension": enc.pretension.detach().clone()}
        if enc.strain:
            out["pretension_strain"] = enc.pretension_strain.detach().clone()
        return out

    def set_physics(self, values: dict[str, Tensor]) -> None:
        enc = self.cc.encoder
        with torch.no_grad():
            for name, value in values.items():
                if name == "gravity":
                    g = torch.as_tensor(value, dtype=torch.float64).clone()
                    self.gravity_vector = g * min(1.0, WEIGHT_MAX / max(float(g.norm()), 1e-300))
                elif name == "log_axial_radius":
                    self.log_axial_radius = min(max(float(value), math.log(AXIAL_RADIUS_RANGE[0])),
                                                math.log(AXIAL_RADIUS_RANGE[1]))
                else:
                    getattr(enc, name).copy_(value)

    def robot(self) -> RobotSpec:
        """The robot for the solver: effective radii, rotated joint angles, the nominal rod with the fitted
        tendon compliance, and a density giving 1 kg/m (the weight per length enters as the gravity)."""
        enc = self.cc.encoder
        d = self.spec0.to_dict()
        radii = enc.effective_radius().tolist()
        for k, seg in enumerate(d["segments"]):
            if "joint_angles" in seg:
                seg["joint_angles"] = [a + float(enc.rotation[k]) for a in seg["joint_angles"]]
                seg["joint_radii"] = [radii[k]] * len(seg["joint_angles"])
            else:
                seg["offset"] = seg.get("offset", 0.0) + float(enc.rotation[k])
                seg["radius"] = radii[k]
        radius = math.exp(self.log_axial_radius)                # a solid rod of this radius with EI fixed
        area, ei = math.pi * radius**2, BENDING_STIFFNESS
        compliance = float(enc.log_compliance.exp())            # EI / (E_t A_t) [m²]
        d["mechanics"] = {"youngs_modulus": 4 * ei / (math.pi * radius**4), "poisson_ratio": POISSON_RATIO,
                          "outer_radius": radius, "density": 1.0 / area, "tendon_compliance": compliance / ei}
        return RobotSpec.from_dict(d)

    @property
    def weight(self) -> float:
        """The weight per length w = ‖g‖ ≥ 0 [N/m]."""
        return float(self.gravity_vector.norm())

    def direction(self) -> Tensor:
        """The direction u (3,) of the weight in the motion-capture frame (−e_z while w = 0)."""
        w = self.gravity_vector.norm()
        return self.gravity_vector / w if w > 0 else torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)

    def gravity(self) -> Tensor:
        """Gravity vector (3,) in the robot base frame whose product with 1 kg/m is the weight per length:
        g of the motion-capture frame, rotated into the tilted base."""
        return self.cc.base_rotation().detach().to(torch.float64).T @ self.gravity_vector

    def rest_lengths(self, x: Tensor) -> Tensor:
        """Unstretched tendon lengths ℓ = L₀ − x − p (n, N) [m] of displacements x (n, N) [m]."""
        p = self.cc.encoder.tendon_pretension().detach()
        return self.path_length - x.to(torch.float64) - p

    def solve(self, x: Tensor, warm: WarmStart | None = None) -> DisplacementSolution:
        """The statics of displacements x (n, N) [m] (base frame; NaN rows where the solve failed)."""
        kw = {} if warm is None else {"tension_guess": warm.tension, "compliance_guess": warm.compliance}
        return solve_displacements(self.robot(), self.rest_lengths(x), gravity=self.gravity(),
                                   spring_lengths=self.path_length, passing="segment",
                                   steps_per_segment=self.steps, tol=SOLVE_TOL, on_failure="flag", **kw)

    def tip_poses(self, x: Tensor, warm: WarmStart | None = None) -> tuple[Tensor, WarmStart]:
        """Tip poses (n, 4, 4) [m] in the base frame of displacements x (n, N) [m], and the new warm start."""
        sol = self.solve(x, warm)
        return sol.tip, WarmStart(sol.tension, sol.compliance)

    def body(self, x: Tensor, points_per_segment: int | None = None) -> BodyPoints:
        """The rod's body of displacements x (n, N) [m]: its nodes (:meth:`~dacr_learn.cosserat.statics.
        CosseratSolution.body`; K must divide ``steps_per_segment``, None: all of them) in the motion-capture
        frame; NaN rows where the solve failed."""
        body = self.solve(x).statics.body(self.spec0, points_per_segment)
        with torch.no_grad():
            return body._replace(points=self.cc.to_world(body.points))

    def world_tip(self, pose: Tensor) -> Tensor:
        """Tip poses (n, 4, 4) in the base frame → marker positions (n, 3) [m], motion-capture frame."""
        with torch.no_grad():
            return self.cc.to_world(self.cc.marker_point(pose))

    def __call__(self, x: Tensor) -> Tensor:
        """Tip positions (n, 3) [m]; NaN rows where the solve failed."""
        return self.world_tip(self.tip_poses(x)[0])

    def report(self) -> dict:
        out = self.cc.report()
        out["weight_per_length_N_per_m"] = round(self.weight, 5)
        u = self.direction()
        axis = self.cc.base_rotation().detach().to(torch.float64)[:, 2]       # the robot's base axis, mocap frame
        out["gravity_direction_mocap"] = [round(float(v), 4) for v in u]
        # polar angle from mocap −z and azimuth in the mocap xy plane; angle between the weight and the base axis
        out["gravity_from_mocap_down_deg"] = round(math.degrees(math.acos(max(-1.0, min(1.0, -float(u[2]))))), 2)
        out["gravity_azimuth_deg"] = round(math.degrees(math.atan2(float(u[1]), float(u[0]))), 2)
        out["gravity_to_base_axis_deg"] = round(math.degrees(math.acos(max(-1.0, min(1.0, float(u @ axis))))), 2)
        out["axial_over_bending_stiffness_per_mm2"] = round(4 / math.exp(2 * self.log_axial_radius) * 1e-6, 4)
        return out

    # -- fitting ---------------------------------------------------------------------------------------------
    def fit(self, x: Tensor, tip: Tensor, rows: int = FIT_ROWS, iterations: int = FIT_ITERATIONS,
            seed: int = 0, free_frame: bool = True, starts: tuple[float, ...] = AXIAL_STARTS, log=None) -> dict:
        """Levenberg–Marquardt on (x (n, N), tip (n, 3)) [m] over a seeded subset of ``rows`` rows, from each backbone
        axial radius in ``starts`` [m], keeping the start of lowest RMS. Returns the RMS before and after [m], each
        start's RMS, the iterations and the time. ``free_frame=False`` keeps the CC model's base pose and marker."""
        begin = time.perf_counter()
        if x.shape[0] > rows:
            pick = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(seed))[:rows]
            x, tip = x[pick], tip[pick]
        x, tip = x.to(torch.float64), tip.to(torch.float64)
        initial = (copy.deepcopy(self.cc), self.gravity_vector.clone(), self.log_axial_radius)
        best, per_start, before = None, {}, None
        for radius in starts:
            self.cc, self.gravity_vector = copy.deepcopy(initial[0]), initial[1].clone()
            self.set_physics({"log_axial_radius": torch.tensor(math.log(radius))})
            info = self._levenberg_marquardt(x, tip, iterations, free_frame, log)
            before = info["rms_before_m"] if before is None else before
            per_start[f"{radius:g}"] = info["rms_m"]
            if best is None or info["rms_m"] < best[0]["rms_m"]:
                best = (info, copy.deepcopy(self.cc), self.gravity_vector.clone(), self.log_axial_radius)
        info, self.cc, self.gravity_vector, self.log_axial_radius = best
        return {**info, "rms_before_m": before, "rms_per_start_m": per_start, "seconds": time.perf_counter() - begin}

    def _levenberg_marquardt(self, x: Tensor, tip: Tensor, iterations: int, free_frame: bool, log) -> dict:
        start = time.perf_counter()
        frame = [self.cc.base_tilt, self.cc.marker_lateral if self.cc.lateral_marker else None, self.cc.tip_offset]
        frame = [p for p in frame if p is not None] if free_frame else []
        names = list(self.physics())
        lam = 1e-2

        def residual(poses: Tensor) -> Tensor:
            r = self.world_tip(poses) - tip
            return r - r.mean(0) if free_frame else r          # the translation is fitted in closed form

        poses, warm = self.tip_poses(x)
        r = residual(poses)
        rms0 = _rms(r)
        done = 0
        for _ in range(iterations):
            rms_prev = _rms(r)
            base = self.physics()
            batched, columns = [], []                           # physics: finite differences of warm solves
            for name in names:
                for j in range(base[name].numel()):
                    trial = {k: v.clone() for k, v in base.items()}
                    trial[name].view(-1)[j] += PHYSICS_SCALES[name] * FD_FRACTION
                    if name in SHARED_SPEC:                     # same robot: one solve for all of them, below
                        batched.append(len(columns))
                        columns.append(trial)
                        continue
                    self.set_physics(trial)
                    columns.append(self.tip_poses(x, warm)[0])
                    self.set_physics(base)
            for k, poses in zip(batched, self._solve_trials(x, warm, base, [columns[k] for k in batched]),
                                strict=True):
                columns[k] = poses
            jac = torch.stack([((residual(p1) - r) / FD_FRACTION).reshape(-1) for p1 in columns], -1)
            if frame:
                jac = torch.cat([jac, _frame_jacobian(self.cc, frame, poses, tip)], -1)
            if not torch.isfinite(jac).all():
                break
            g, hess = jac.T @ r.reshape(-1), jac.T @ jac
            improved = False
            frame_before = [p.detach().clone() for p in frame]
            for _ in range(6):
                step = -torch.linalg.solve(hess + lam * torch.diag(hess.diagonal().clamp(min=1e-12)), g)
                step = step * min(1.0, MAX_STEP / float(step.abs().max()))
                self._apply(names, base, frame_before, frame, step)
                p1, w1 = self.tip_poses(x, warm)
                r1 = residual(p1)
                if torch.isfinite(r1).all() and r1.pow(2).sum() < r.pow(2).sum():
                    poses, warm, r, improved = p1, w1, r1, True
                    lam = max(lam / 3, 1e-6)
                    break
                self._apply(names, base, frame_before, frame, torch.zeros_like(step))   # back to the start
                lam *= 5
            done += 1
            if log is not None:
                log(f"cosserat fit {done}: {_rms(r) * 1e3:.3f} mm, g = {self.gravity_vector.tolist()} N/m")
            if not improved or rms_prev - _rms(r) < FIT_STALL * rms_prev:
                break
        if free_frame:
            with torch.no_grad():
                self.cc.base_translation += -(self.world_tip(poses) - tip).mean(0)
        return {"rms_before_m": rms0, "rms_m": _rms(self.world_tip(poses) - tip), "iterations": done,
                "rows": int(x.shape[0]), "seconds": time.perf_counter() - start}

    def _solve_trials(self, x: Tensor, warm: WarmStart, base: dict[str, Tensor],
                      trials: list[dict[str, Tensor]]) -> list[Tensor]:
        """Tip poses (n, 4, 4) of displacements x (n, N) under each of ``trials`` (physics that differ from ``base``
        only in :data:`SHARED_SPEC` parameters), all in one solve of the robot at ``base``: per sample their rest
        lengths, gravities and spring lengths (a compliance c' as the lengths L·c'/c), warm-started at ``warm``."""
        if not trials:
            return []
        self.set_physics(base)
        spec, c0 = self.robot(), float(self.cc.encoder.log_compliance.exp())
        rest, gravity, spring = [], [], []
        n = x.shape[0]
        for trial in trials:
            self.set_physics(trial)
            rest.append(self.rest_lengths(x))
            gravity.append(self.gravity().expand(n, 3))
            spring.append((self.path_length * float(self.cc.encoder.log_compliance.exp()) / c0).expand(n, -1))
        self.set_physics(base)
        k = len(trials)
        sol = solve_displacements(spec, torch.cat(rest), gravity=torch.cat(gravity), spring_lengths=torch.cat(spring),
                                  passing="segment", steps_per_segment=self.steps, tol=SOLVE_TOL, on_failure="flag",
                                  tension_guess=warm.tension.repeat(k, 1),
                                  compliance_guess=warm.compliance.repeat(k, 1, 1))
        return list(sol.tip.split(n))

    def _apply(self, names, base, frame_base, frame, step: Tensor) -> None:
        """Set the physics to ``base`` and the frame parameters to ``frame_base`` plus the scaled LM ``step``."""
        values, k = {}, 0
        for name in names:
            n = base[name].numel()
            values[name] = base[name] + PHYSICS_SCALES[name] * step[k:k + n].reshape(base[name].shape)
            k += n
        self.set_physics(values)
        with torch.no_grad():
            for p, p0 in zip(frame, frame_base, strict=True):
                n = p.numel()
                p.copy_(p0 + FRAME_SCALE * step[k:k + n].reshape(p.shape))
                k += n


def _rms(r: Tensor) -> float:
    """Root-mean-square length of residual vectors r (n, 3) [m]."""
    return float(r.pow(2).sum(-1).mean().sqrt())


def _frame_jacobian(cc: CalibratedCC, frame: list[Tensor], poses: Tensor, tip: Tensor) -> Tensor:
    """∂(mean-removed residual)/∂(frame parameters / FRAME_SCALE) (3n, P) at fixed tip poses, by central
    differences (no solve: the frame parameters act after the mechanics; the residual is smooth in them)."""
    def res() -> Tensor:
        r = cc.to_world(cc.marker_point(poses)) - tip
        return r - r.mean(0)

    h, cols = 1e-6, []
    with torch.no_grad():
        for p in frame:
            flat = p.view(-1)
            for j in range(flat.numel()):
                flat[j] += h
                up = res()
                flat[j] -= 2 * h
                down = res()
                flat[j] += h
                cols.append(((up - down) / (2 * h) * FRAME_SCALE).reshape(-1))
    return torch.stack(cols, -1)
