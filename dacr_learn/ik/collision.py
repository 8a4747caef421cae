"""Collision-free IK: the clearance of a model's body (and an arm's links) to a scene, for the solver.

Two paths, like the tip's:

- the independent check (:meth:`Avoidance.clearance_of_joints`): from joint vectors alone (encoder → the
  model's body at :data:`CHECK_POINTS` points per segment), the signed clearance of the swept body (robot and arm
  links) to every obstacle, and of the robot's body to the arm's links away from the mount (docs/body.md), as a
  rigorous lower bound (:mod:`dacr_learn.scene.clearance`); a solution succeeds when it is ≥ the clearance D;
- in the solver's working batch (:mod:`.pool`, the default): the converged starts are decided together by that same
  check of their joints (:meth:`Avoidance.accept`), and the value of an accepted start is its slot's verdict
  (:meth:`Avoidance.verdict`); a rejected start's slot restarts, its new starts mostly near a collision-free
  solution of the same target (:meth:`Avoidance.restarts`);
- with grouped restarts (``IKOptions(pool=0)``): a start whose tip has converged is checked at
  :data:`SOLVER_POINTS` points per segment (:meth:`Avoidance.triage`: only the side of D matters, so the stages
  that cannot change it are skipped), and restarts the same way; with ``hinge=True`` a start short by less than
  :data:`HINGE_WITHIN` is instead pushed clear by hinge residuals
  max(0, D + δ − d)/L of the :data:`PAIRS` worst (ball, obstacle) pairs (:meth:`Avoidance.residual`), d the
  signed distance of a body point's ball, with their Jacobian by forward differences (one batched evaluation of
  the body at the D perturbed variable vectors: any model with a body, meshes included); δ (a tenth of the
  longest chord between body points) makes the hinge push the points far enough for the chord bound to pass.

Clearances are evaluated in blocks of :data:`CHUNK` rows (their (rows, points, obstacles) arrays stay in cache).
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..scene import Scene, capsule_chain, capsule_pair, chain_clearance, join, swept_body, swept_clearance
from ..scene.shapes import capsule_distance
from .adapters import SolverModel

SOLVER_POINTS = 8     # body points per segment inside the refinement
CHECK_POINTS = 8      # body points per segment of the independent check
PAIRS = 4             # hinge residuals per start: its worst (ball, obstacle) pairs
LINK_SPACING = 0.05   # [m] longest chord along an arm link's capsule axis
HINGE_WITHIN = 0.001  # [m] with ``hinge=True``: a converged start short of the clearance by less than this is pushed
                      # clear, else restarted
STEP = 1e-7           # forward-difference step, in units of each variable's scale
RESTART_NEAR = 0.75   # fraction of new starts drawn near a collision-free solution of the same target (if any)
RESTART_SPREAD = 0.1  # their offset from it: uniform in ± this many units of each variable's scale
CHUNK = 512           # rows per block of a clearance evaluation (its (rows, points, obstacles) arrays stay in cache)


class Avoidance:
    """Clearance of ``model``'s body to ``scene`` at least ``clearance`` [m] (module docstring); the ``extra``
    condition of :class:`~.refine.Refinement` (``rows``, :meth:`triage`, :meth:`residual`). ``hinge``: push starts
    that miss the clearance by less than :data:`HINGE_WITHIN` clear with hinge residuals (``rows`` =
    :data:`PAIRS`); without it (the default, faster on both shipped scenes) every start that misses restarts and
    the LM system keeps its size (``rows`` = 0)."""

    def __init__(self, model: SolverModel, scene: Scene, clearance: float, hinge: bool = False):
        if not clearance >= 0 or clearance == float("inf"):
            raise ValueError(f"clearance: expected a finite distance >= 0 [m], got {clearance}")
        self.model, self.scene, self.clearance = model, scene, float(clearance)
        self.rows, self.within = (PAIRS, HINGE_WITHIN) if hinge else (0, 0.0)
        self._verdicts: dict[bytes, float] = {}        # variable vector → its independent check (accept, verdict)
        model.body(model.rest.to(torch.float64).unsqueeze(0), SOLVER_POINTS)     # ValueError without a body

    def _balls(self, x: Tensor, points_per_segment: int):
        """The body (:class:`~dacr_learn.body.BodyPoints`), the arm's link capsules or None, and the link capsules'
        chain with its point radii (or None) at variables x (B, D)."""
        both = getattr(self.model, "body_and_links", None)            # one pass of an arm's kinematics
        body, links = (both(x, points_per_segment) if both is not None else
                       (self.model.body(x, points_per_segment), self.model.links(x)))
        chain = None if links is None else capsule_chain(*links[:3], LINK_SPACING)
        return body, links, chain

    def _bound(self, x: Tensor, points_per_segment: int, decide: float | None = None) -> Tensor:
        """Clearance bound (B,) [m] at variables x (B, D): the swept body, and an arm's link chain, to every obstacle,
        and the body to the links away from the mount, in one :func:`~dacr_learn.scene.swept_clearance`; ``decide``:
        as there."""
        body, links, chain = self._balls(x, points_per_segment)
        swept = swept_body(body)
        if links is None:
            return chain_clearance(self.scene, swept, None, decide)
        a, b, radius, near = links
        a, b, radius = a[:, ~near], b[:, ~near], radius[~near]
        whole = join(swept, chain[0])
        o, scene, links_pair = self.scene.num_obstacles, self.scene, capsule_pair(a, b, radius)
        d_scene = self.scene.distances(whole.points)[0]                               # (B, P + Q, O)
        pts, n = body.points, x.shape[0]
        # (row, far link) pairs whose link lies beyond the body's reach from its base by more than the clearance some
        # point already has (an upper bound of the result) skip the body-to-link distances: they cannot hold the
        # minimum (each such link is ≥ that upper bound from every body point, by the triangle inequality)
        upper = ((d_scene.amin(-1) - torch.cat([body.radius, chain[1]])).amin(-1) if o
                 else pts.new_full((n,), float("inf")))
        reach = (torch.linalg.vector_norm(pts - pts[:, :1], dim=-1).amax(-1) + swept.sag.amax(-1)
                 + body.radius.max())
        d_base = capsule_distance(pts[:, :1], a, b, radius, grad=False)[0]                 # (B, C)
        rows, cap = ((d_base - reach.unsqueeze(-1)) < upper.unsqueeze(-1)).nonzero().unbind(-1)
        d_self = pts.new_full((n, whole.points.shape[1], radius.numel()), float("inf"))     # links: not to themselves
        if rows.numel():
            d_self[rows, :pts.shape[1], cap] = capsule_distance(pts[rows], a[rows, cap].unsqueeze(1),
                                                                b[rows, cap].unsqueeze(1), radius[cap].unsqueeze(1),
                                                                grad=False)[0]              # (K, P)

        def pair(rows: Tensor, points: Tensor, field: Tensor) -> tuple[Tensor, Tensor]:
            scene_field = field < o
            if bool(scene_field.all()):                                  # obstacles only (or links only): no split
                return scene.pair_distances(points, field)
            if not bool(scene_field.any()):
                return links_pair(rows, points, field - o)
            d, g = points.new_empty(field.shape), torch.empty_like(points)
            i, j = scene_field.nonzero().squeeze(-1), (~scene_field).nonzero().squeeze(-1)
            if i.numel():
                d[i], g[i] = scene.pair_distances(points[i], field[i])
            if j.numel():
                d[j], g[j] = links_pair(rows[j], points[j], field[j] - o)
            return d, g

        convex = torch.cat([self.scene.convex, torch.ones(radius.numel(), dtype=torch.bool)])
        return swept_clearance(whole, torch.cat([d_scene, d_self], -1), pair, convex,
                               decide)

    def _evaluate(self, x: Tensor, points_per_segment: int):
        """(clearance bound (B,), ball distances (B, E) [m], longest body chord (B,)) at variables x (B, D); the
        E (ball, obstacle) pairs: body points × obstacles, link points × obstacles, body points × far links (the
        hinge residuals' candidates)."""
        body, links, chain = self._balls(x, points_per_segment)
        d_body = self.scene.distances(body.points)[0]                               # (B, P, O)
        parts = [(d_body - body.radius.unsqueeze(-1)).flatten(1)]
        if links is not None:
            a, b, radius, near = links
            d_links = self.scene.distances(chain[0].points)[0]
            d_self = capsule_distance(body.points.unsqueeze(2), a[:, ~near].unsqueeze(1),
                                      b[:, ~near].unsqueeze(1), radius[~near], grad=False)[0]
            parts += [(d_links - chain[1].unsqueeze(-1)).flatten(1),
                      (d_self - body.radius.unsqueeze(-1)).flatten(1)]
        longest = torch.linalg.vector_norm(body.points[:, 1:] - body.points[:, :-1], dim=-1).amax(-1)
        return self._bound(x, points_per_segment), torch.cat(parts, 1), longest

    def _pair_distances(self, x: Tensor, pick: Tensor) -> Tensor:
        """The distances (B, k) [m] of the pairs ``pick`` (B, k) (indices into :meth:`_evaluate`'s E) at x (B, D)."""
        body, links, chain = self._balls(x, SOLVER_POINTS)
        o, p = self.scene.num_obstacles, body.points.shape[1]
        rows = torch.arange(x.shape[0]).unsqueeze(-1).expand_as(pick)
        in_body = pick < p * o
        point, obstacle = torch.where(in_body, pick, 0).div(o, rounding_mode="floor"), torch.where(in_body, pick, 0) % o
        d_scene, _ = self.scene.pair_distances(body.points[rows, point], obstacle)
        out = torch.where(in_body, d_scene - body.radius[point], 0.0)
        if links is None:
            return out
        a, b, radius, near = links
        q = chain[0].points.shape[1]
        in_links = ~in_body & (pick < (p + q) * o)
        j = torch.where(in_links, pick - p * o, 0)
        d_link, _ = self.scene.pair_distances(chain[0].points[rows, j.div(o, rounding_mode="floor")], j % o)
        out = torch.where(in_links, d_link - chain[1][j.div(o, rounding_mode="floor")], out)
        c = int((~near).sum())
        j = torch.where(~in_body & ~in_links, pick - (p + q) * o, 0)
        pt, cap = j.div(max(c, 1), rounding_mode="floor"), j % max(c, 1)
        far = (~near).nonzero().squeeze(-1)[cap] if c else cap
        d_self, _ = capsule_distance(body.points[rows, pt], a[rows, far], b[rows, far], radius[far], grad=False)
        return torch.where(~in_body & ~in_links, d_self - body.radius[pt], out)

    @torch.no_grad()
    def clearance_of(self, x: Tensor, points_per_segment: int = CHECK_POINTS, decide: float | None = None) -> Tensor:
        """Signed clearance lower bound (B,) [m] of variables x (B, D) (module docstring); in blocks of
        :data:`CHUNK` rows. ``decide``: only whether it is ≥ decide matters (a looser bound on the same side,
        :func:`~dacr_learn.scene.chain_clearance`)."""
        if x.shape[0] <= CHUNK:
            return self._bound(x, points_per_segment, decide)
        return torch.cat([self._bound(part, points_per_segment, decide) for part in x.split(CHUNK)])

    def triage(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(B,) bool each: the clearance bound of variables x (B, D) at :data:`SOLVER_POINTS` is ≥ D; it is below
        but within :data:`HINGE_WITHIN` of D with ``hinge`` (the refinement then pushes the body clear)."""
        bound = self.clearance_of(x, SOLVER_POINTS, None if self.within else self.clearance)
        return bound >= self.clearance, bound >= self.clearance - self.within

    def accept(self, x: Tensor) -> Tensor:
        """(B,) bool: the independent check of the joints of variables x (B, D) is ≥ D (the decision on a converged
        start in the working batch of :mod:`.pool`); each value is kept for :meth:`verdict`."""
        value = self.clearance_of_joints(self.model.joints(x))
        self._verdicts.update(zip((row.tobytes() for row in x.contiguous().numpy()), value.tolist(), strict=True))
        return value >= self.clearance

    def verdict(self, x: Tensor) -> Tensor:
        """The independent check (:meth:`clearance_of_joints`) of the joints of variables x (B, D) [m]: the value
        :meth:`accept` computed for the same variable vector, else computed now."""
        known = [self._verdicts.get(row.tobytes()) for row in x.contiguous().numpy()]
        out = torch.tensor([float("nan") if v is None else v for v in known], dtype=torch.float64)
        missing = out.isnan().nonzero().squeeze(-1)
        if missing.numel():
            out[missing] = self.clearance_of_joints(self.model.joints(x[missing]))
        return out

    def restarts(self, uniform: Tensor, x: Tensor, solved: Tensor, gen: torch.Generator,
                 share: float | None = None) -> Tensor:
        """New starts (R, D) of slots whose start stalled: ``uniform`` samples (R, D) of the admissible set, each
        replaced with probability ``share`` (default :data:`RESTART_NEAR`) by a solution of the same target (rows
        ``solved`` (R, K) into x (M, D), −1 where a slot is unsolved; one picked at random) moved by up to
        :data:`RESTART_SPREAD` scales per variable and projected onto the limits. Collision-free solutions lie on
        connected manifolds of a redundant robot, so a start near one converges clear far more often than a uniform
        one (a robot on an arm behind a port almost never clears from a uniform start; there about 98 % of the starts
        near a solution converge clear, against about 57 % of the pose bank's seeds)."""
        has = solved >= 0
        share = RESTART_NEAR if share is None else share
        near = has.any(-1) & (torch.rand(uniform.shape[0], generator=gen, dtype=uniform.dtype) < share)
        if not bool(near.any()):
            return uniform
        idx = near.nonzero().squeeze(-1)
        pick = torch.multinomial(has[idx].to(uniform.dtype), 1, generator=gen).squeeze(-1)
        centre = x[solved[idx, pick]]
        lim = self.model.limits
        offset = (2 * torch.rand(centre.shape, generator=gen, dtype=centre.dtype) - 1) * RESTART_SPREAD
        out = uniform.clone()
        out[idx] = lim.project(centre + offset * lim.scale.to(centre))
        return out

    def clearance_of_joints(self, q: Tensor) -> Tensor:
        """The independent check: clearance (B,) [m] of joint vectors q (B, N) alone (:data:`CHECK_POINTS`)."""
        return self.clearance_of(self.model.variables(q.to(torch.float64)), CHECK_POINTS)

    @torch.no_grad()
    def residual(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Hinge residuals (M, PAIRS) [units of L], their Jacobian (M, PAIRS, D) and whether each start's
        clearance bound is ≥ D (M,) bool, at variables x (M, D)."""
        m, dim = x.shape
        clear, d, longest = self._evaluate(x, SOLVER_POINTS)
        target = self.clearance + 0.1 * longest.unsqueeze(-1)
        violation = target - d
        r, jac = x.new_zeros(m, PAIRS), x.new_zeros(m, PAIRS, dim)
        active = (violation.amax(-1) > 0).nonzero().squeeze(-1)
        if active.numel() == 0:
            return r, jac, clear >= self.clearance
        k = min(PAIRS, d.shape[1])
        pick = violation[active].topk(k, dim=-1).indices                              # (A, k)
        step = STEP * self.model.limits.scale.to(x)                                  # (D,)
        xa = x[active]
        shifted = (xa.unsqueeze(1) + torch.diag(step)).reshape(-1, dim)              # (A·D, D)
        d_shift = self._pair_distances(shifted, pick.repeat_interleave(dim, 0)).view(active.numel(), dim, k)
        d_pick = d[active].gather(1, pick)
        slope = (d_shift - d_pick.unsqueeze(1)) / step.view(1, -1, 1)
        hinge = (target[active] - d_pick).clamp_min(0.0)
        length = self.model.length
        r[active, :k] = hinge / length
        jac[active, :k] = -slope.transpose(1, 2) * (hinge > 0).to(x.dtype).unsqueeze(-1) / length
        return r, jac, clear >= self.clearance


def add_scene_arguments(parser) -> None:
    """The command-line options ``--scene S.yaml --clearance D`` (an argparse parser)."""
    parser.add_argument("--scene", help="scene YAML (obstacles, docs/body.md) in the robot's base frame (the arm's "
                        "with --arm): success also needs the body at least --clearance from every obstacle")
    parser.add_argument("--clearance", type=float, default=None, metavar="D",
                        help="with --scene: the clearance [m] every solution keeps from the obstacles (default 0)")


def scene_options(args) -> dict:
    """``solve_ik`` keywords (scene, clearance) of parsed ``--scene/--clearance`` options; {} without a scene."""
    from ..scene import load_scene
    if args.scene is None:
        if args.clearance is not None:
            raise ValueError("--clearance goes with --scene S.yaml (the obstacles to keep clear of); "
                             "--scene is missing")
        return {}
    clearance = 0.0 if args.clearance is None else args.clearance
    if not clearance >= 0 or clearance == float("inf"):
        raise ValueError(f"--clearance: expected a finite distance >= 0 [m], got {args.clearance}")
    return {"scene": load_scene(args.scene), "clearance": clearance}
