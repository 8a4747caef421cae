"""One follow-the-leader step as a least-squares problem, batched over steps: residuals, LM, the tip polish.

At a step whose tip is at arc length s along the path, every backbone point at distance δ behind the tip (along
the body) is asked to lie on the path point at arc s − δ: on the path when s − δ ≥ 0 (inserted), else on the
straight entry line behind the path's start (:meth:`~.path.Path.at`), with the lower weight
``outside_weight`` (a ramp over :data:`RAMP` of the length). The tip itself weighs :data:`TIP_WEIGHT` times a
body point, and a small pull ``regularization`` towards reference variables (the previous step) fixes what the
body leaves free (e.g. the roll of a free base about the robot's axis). With a scene, a **clearance hinge**
max(0, D + m·L + δ − c)/L joins for every (sample, obstacle) pair (samples: the body points and
:data:`HINGE_SUBDIVISION` − 1 more along each chord; m = ``hinge_margin``), weighing :data:`HINGE_WEIGHT`
body points: c the sample's clearance (the scene's signed distance less the body's envelope radius there),
δ the chord's sag (:func:`dacr_learn.body.chord_sag`), so that the body between the samples keeps D too; its
Jacobian from the scene's distance gradients and the body's. On an arm, a **conditioning** residual
w·(1 − σ_min) (σ_min: the smallest singular value of the arm's tool Jacobian, linear rows per L, prismatic columns
times L), linearised at the previous step, spends what the body leaves free on staying away from the arm's
singularities (a free base's Euler angles turn up to 1/|cos pitch| times faster than the base near the gimbal
lock); its drift per step is bounded (≤ 0.06 rad per 1 % L where only the pull resists it). Residuals are in units
of the robot's length L; the variables are scaled by the limits' scale.

:func:`refine` runs Levenberg–Marquardt on these residuals with the limits inside the step (blocked limits held,
the trial point projected onto the admissible set, as in :mod:`dacr_learn.ik.refine`), solving the D × D normal
equations (the body gives many more rows than variables). :func:`polish` then puts the tip on the path point
exactly: minimum-norm Gauss–Newton steps on the tip residual alone (:func:`dacr_learn.ik.refine.limited_step`).
Float64.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..arm import Composite
from ..body import BodyPoints, chord_sag
from ..checks import F64
from ..deploy.qp_clearance import clearance_rows
from ..ik.adapters import SolverModel
from ..ik.refine import limited_step
from ..scene import Scene
from .body import FD_STEP, body_and_jacobian
from .path import Path

TIP_WEIGHT = 10.0      # the tip's weight relative to one body point (then polished to the tolerance)
RAMP = 0.25            # length of the weight ramp at the entry point, relative to L
HINGE_WEIGHT = 10.0    # a clearance hinge's weight relative to one body point's (as the tip's)
HINGE_SUBDIVISION = 4  # hinge samples per chord between body points (the check's spacing for 8 points per segment)


@dataclass(frozen=True)
class StepOptions:
    """outside_weight: weight of body points not yet inserted (on the entry line); regularization: pull towards
    the reference variables, per scaled unit, in units of L; damping: initial λ (relative to the mean diagonal of
    the Gauss–Newton matrix: small, so that LM converges along the weak directions the pull alone fixes instead
    of lagging behind and catching up in one step); points_per_segment: backbone points per segment in the
    residuals (the figures use :data:`~.body.POINTS_PER_SEGMENT`); conditioning: the weight w of the arm's
    conditioning residual (0: none); hinge_weight, hinge_margin: a clearance hinge's weight relative to one body
    point's, and the margin it keeps beyond D and the chord sag, relative to L."""

    outside_weight: float = 0.1
    regularization: float = 1e-4
    damping: float = 1e-12
    points_per_segment: int = 8
    conditioning: float = 5e-6
    hinge_weight: float = HINGE_WEIGHT
    hinge_margin: float = 1e-4


class Problem:
    """The FTL step problem of ``model`` along ``path`` (module docstring); L = ``length`` [m]; ``scene``: the
    obstacles to keep ``clearance`` [m] from (or None)."""

    def __init__(self, model: SolverModel, path: Path, length: float, options: StepOptions,
                 scene: Scene | None = None, clearance: float = 0.0):
        self.model, self.path, self.length, self.opts = model, path, length, options
        self.scene, self.clearance = scene, clearance
        self.lim = model.limits.to(F64)
        self.scale = self.lim.scale.to(F64)
        self.conditioned = isinstance(model, Composite) and options.conditioning > 0
        if self.conditioned:                   # the arm's columns in the continuity bound's units (L, rad)
            self.arm_columns = torch.tensor([length if k == "prismatic" else 1.0 for k in model.arm.joint_types],
                                            dtype=F64)
        if scene is not None:                  # the envelope radius (P,) at the body points (the body API's)
            rest = self.lim.project(model.rest.to(F64)[None])
            self.radius = model.body(rest, options.points_per_segment).radius.to(F64)

    def residual(self, x: Tensor, s: Tensor, ref: Tensor, reg: float | None = None,
                 cond: tuple[Tensor, Tensor] | None = None, hinge: float = 1.0,
                 lift: float = 0.0) -> tuple[Tensor, Tensor]:
        """r (B, R) and ∂r/∂x (B, R, D) at variables x (B, D), tip arc lengths s (B,) [m], references ref (B, D);
        ``reg``: the pull towards ref (default ``regularization``); ``cond``: the arm's conditioning residual and
        its Jacobian at ref ((B, 1), (B, 1, D): :meth:`conditioning`), linearised there (default: evaluated);
        ``hinge``: a factor on the hinges' weight; ``lift`` [m]: added to their target."""
        b, d = x.shape
        body, jac, jac_arc = body_and_jacobian(self.model, x, self.opts.points_per_segment)
        p = body.points.shape[1]
        along = s[:, None] - (body.arc[:, -1:] - body.arc)                              # (B, P) path arcs
        target = self.path.at(along)
        # the targets slide along the path with the arc lengths (an extensible robot): ∂target = t·∂along
        d_along = jac_arc - jac_arc[:, -1:]                                              # (B, P, D)
        jac_points = jac
        jac = jac - self.path.tangent(along).unsqueeze(-1) * d_along.unsqueeze(-2)
        ramp = RAMP * self.length
        w = self.opts.outside_weight + (1 - self.opts.outside_weight) * ((along + ramp) / ramp).clamp(0.0, 1.0)
        w = w.clone()
        w[:, -1] = TIP_WEIGHT
        w = w / (self.length * p ** 0.5)
        r_body = (w[..., None] * (body.points - target)).reshape(b, 3 * p)
        j_body = (w[..., None, None] * jac).reshape(b, 3 * p, d)
        reg = self.opts.regularization if reg is None else reg
        r_reg = reg * (x - ref) / self.scale
        j_reg = torch.diag(reg / self.scale).expand(b, d, d)
        rows, jacs = [r_body, r_reg], [j_body, j_reg]
        if self.conditioned:
            r_cond, j_cond = self.conditioning(ref) if cond is None else cond
            rows.append(r_cond + (j_cond @ (x - ref).unsqueeze(-1)).squeeze(-1))
            jacs.append(j_cond)
        if self.scene is not None:
            r_hinge, j_hinge = self._hinges(body.points, jac_points, lift)
            r_hinge, j_hinge = hinge * r_hinge, hinge * j_hinge
            rows.append(r_hinge)
            jacs.append(j_hinge)
        self.tip_rows = slice(3 * p - 3, 3 * p)
        return torch.cat(rows, dim=1), torch.cat(jacs, dim=1)

    def conditioning(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The arm's conditioning residual (B, 1) = w/σ_min of its tool Jacobian in the continuity bound's units
        (linear rows per L, prismatic columns times L), and its Jacobian (B, 1, D) by central differences."""
        b, d = x.shape
        n = self.model.num_arm
        h = FD_STEP * self.scale[:n]
        shift = torch.diag(h)
        q = x[:, :n]
        probe = torch.cat([q[:, None], q[:, None] + shift, q[:, None] - shift], dim=1).reshape(-1, n)
        jac = self.model.arm.chain.jacobian_tensor(probe)                                 # (B(2n+1), 6, n)
        jac = jac * self.arm_columns
        jac = torch.cat([jac[:, :3] / self.length, jac[:, 3:]], dim=1)
        inv = (1.0 - torch.linalg.svdvals(jac)[:, -1]).reshape(b, 1 + 2 * n)
        r = self.opts.conditioning * inv[:, :1]
        j = torch.zeros(b, 1, d, dtype=F64)
        j[:, 0, :n] = self.opts.conditioning * (inv[:, 1:1 + n] - inv[:, 1 + n:]) / (2 * h)
        return r, j

    def _hinges(self, points: Tensor, jac: Tensor, lift: float = 0.0) -> tuple[Tensor, Tensor]:
        """The clearance hinges (B, Q·O) of body points (B, P, 3) with Jacobian jac (B, P, 3, D), and theirs: at
        the points and :data:`HINGE_SUBDIVISION` − 1 more along each chord between them (Q of them), each with the
        chord's sag as margin (the backbone lies within it of the chord), so that an obstacle poking between two
        body points is seen."""
        p = points.shape[1]
        if self.radius.shape[0] != p:
            raise ValueError(f"{type(self.model).__name__}: the body API gives {self.radius.shape[0]} points, the "
                             f"planner's body {p}; expected the same layout")
        k = HINGE_SUBDIVISION
        t = torch.arange(k, dtype=F64) / k                                              # (k,)
        a, b = points[:, :-1, None], points[:, 1:, None]                               # (B, P − 1, 1, 3)
        sub = torch.cat([(a + t[:, None] * (b - a)).flatten(1, 2), points[:, -1:]], 1)  # (B, Q, 3)
        ja, jb = jac[:, :-1, None], jac[:, 1:, None]                                   # (B, P − 1, 1, 3, D)
        jsub = torch.cat([(ja + t[:, None, None] * (jb - ja)).flatten(1, 2), jac[:, -1:]], 1)
        radius = torch.maximum(self.radius[:-1], self.radius[1:]).repeat_interleave(k)
        radius = torch.cat([radius, self.radius[-1:]])                                 # (Q,)
        clear, jd = clearance_rows(self.scene, BodyPoints(sub, radius.new_zeros(radius.shape), radius), jsub)
        sag = chord_sag(points)                                                        # (B, P − 1)
        pad = torch.zeros_like(sag[:, :1])
        ends = torch.maximum(torch.cat([pad, sag], 1), torch.cat([sag, pad], 1))       # (B, P): at the points
        margin = sag[:, :, None].expand(-1, -1, k).clone()
        margin[:, :, 0] = ends[:, :-1]
        margin = torch.cat([margin.flatten(1), ends[:, -1:]], 1)                      # (B, Q)
        short = (self.clearance + lift + self.opts.hinge_margin * self.length + margin).repeat_interleave(
            self.scene.num_obstacles, 1) - clear
        w = self.opts.hinge_weight / (self.length * p ** 0.5)
        return w * short.clamp_min(0.0), -w * (short > 0).to(F64).unsqueeze(-1) * jd

    def refine(self, x: Tensor, s: Tensor, ref: Tensor, iterations: int, tol: float = 1e-10,
               reg: float | None = None, steer: float = 1.0, hinge: float = 1.0,
               lift: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
        """LM on the step residuals from x (B, D): at most ``iterations`` steps; a row stops when its cost
        falls by less than ``tol`` (relative) or its λ exceeds 1e6; ``reg`` overrides the pull's weight. Returns
        (x, cost (B,), the tip's distance to its path point (B,) [m], from the body's last point)."""
        x = self.lim.project(x.to(F64))
        cond = tuple(steer * c for c in self.conditioning(ref)) if self.conditioned else (x[:, :0], x[:, None, :0])
        r, jac = self.residual(x, s, ref, reg, cond, hinge, lift)
        cost = (r * r).sum(-1)
        lam = torch.full_like(cost, self.opts.damping)
        live = torch.ones_like(cost, dtype=torch.bool)
        for _ in range(iterations):
            rows = live.nonzero().squeeze(-1)
            if rows.numel() == 0:
                break
            xt = self._step(x[rows], r[rows], jac[rows], lam[rows])
            rt, jt = self.residual(xt, s[rows], ref[rows], reg, (cond[0][rows], cond[1][rows]), hinge, lift)
            ct = (rt * rt).sum(-1)
            better = ct < cost[rows]
            gain = (cost[rows] - ct) / cost[rows].clamp_min(1e-300)
            acc = rows[better]
            x[acc], r[acc], jac[acc], cost[acc] = xt[better], rt[better], jt[better], ct[better]
            lam[rows] = torch.where(better, (lam[rows] / 10).clamp_min(1e-15), lam[rows] * 10)
            live[rows] = ~((better & (gain < tol)) | (lam[rows] > 1e6))
        p = self.tip_rows.stop // 3
        tip = torch.linalg.vector_norm(r[:, self.tip_rows], dim=-1) * self.length * p ** 0.5 / TIP_WEIGHT
        return x, cost, tip

    def _step(self, x: Tensor, r: Tensor, jac: Tensor, lam: Tensor) -> Tensor:
        """The trial point: δz minimises ‖r + J̃P·δz‖² + λ·μ‖δz‖² (normal equations, D × D; μ the mean diagonal of
        (J̃P)ᵀJ̃P, so λ is relative) in scaled variables
        z = x/scale with the blocking limits held (projector P), then projected onto the admissible set."""
        jz = jac * self.scale
        grad = (jz.mT @ r.unsqueeze(-1)).squeeze(-1)
        box, normals = self.lim.blocked(x, grad)
        a = jz @ self.lim.free_directions(box, normals)
        d = x.shape[1]
        h = a.mT @ a
        level = h.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-300)                # λ relative to ‖J̃‖²/D
        h = h + (lam * level)[:, None, None] * torch.eye(d, dtype=F64)
        dz = -torch.linalg.solve(h, (a.mT @ r.unsqueeze(-1))).squeeze(-1)
        return self.lim.project(x + dz * self.scale)

    def tip_error(self, x: Tensor, s: Tensor) -> Tensor:
        """Tip distance (B,) [m] to the path point at s (the model's tip, not the body)."""
        pos = self.model.tip_and_jacobian(x)[0]
        return torch.linalg.vector_norm(pos - self.path.at(s), dim=-1)

    def polish(self, x: Tensor, s: Tensor, tol: float, iterations: int = 20) -> tuple[Tensor, Tensor]:
        """Tip onto the path point at s (B,): minimum-norm steps on the tip residual alone, inside the limits,
        until the tip error is below ``tol`` [m] (or ``iterations``). Returns x and its tip error (B,) [m]."""
        target = self.path.at(s)
        for _ in range(iterations):
            pos, _, jac = self.model.tip_and_jacobian(x)
            err = pos - target
            gap = torch.linalg.vector_norm(err, dim=-1)
            rows = (gap > tol).nonzero().squeeze(-1)
            if rows.numel() == 0:
                return x.detach(), gap.detach()
            lam = torch.full((rows.numel(),), 1e-14, dtype=F64)
            x = x.clone()
            x[rows] = limited_step(self.lim, x[rows], err[rows] / self.length, jac[rows, :3] / self.length, lam,
                                   only_held=True)
        return x.detach(), self.tip_error(x, s).detach()
