"""Clearance of swept bodies: a lower bound on the distance of a robot's (or an arm link's) envelope to obstacles.

A :class:`Swept` body is a chain of points (B, P, 3); the body between consecutive points is the chord joining
them, within ``sag`` of it (the backbone's arc, :func:`~dacr_learn.body.chord_sag`; 0 for a straight link),
swept by a ball of the chord's ``radius``. Its clearance to an obstacle is bounded below per chord from the
signed distance f and its gradient at the two ends, f(t) along the chord t ∈ [0, 1]:

- convex obstacles (sphere, capsule, box): f is convex along the chord, so it lies above both tangent lines
  f_a + s_a·t and f_b + s_b·(t − 1) (s = ∇f·(b − a)); the bound is the minimum of their upper envelope on [0, 1];
- meshes: f is 1-Lipschitz: f(t) ≥ (f_a + f_b − c)/2 for a chord of length c;

minus the chord's radius and sag. The bound is exact at the chord's ends and its gap shrinks with the square
of the chord length for convex obstacles, so a check of denser points is tighter, never looser. Meshes get the
(looser) Lipschitz bound.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ..body import BodyPoints, chord_sag
from .files import Scene


class Swept(NamedTuple):
    """A chain of swept chords: points (B, P, 3) [m]; radius (P − 1,) [m] of each chord; sag (B, P − 1) [m]
    (how far the body strays from the chord); valid (P − 1,) bool (False for the gap between two chains
    concatenated with :func:`join`)."""

    points: Tensor
    radius: Tensor
    sag: Tensor
    valid: Tensor


def swept_body(body: BodyPoints) -> Swept:
    """A robot body as a swept chain: chord i (points i, i + 1) takes the radius of point i + 1 (its segment's)
    and the sag bound of :func:`~dacr_learn.body.chord_sag`."""
    p = body.points
    return Swept(p, body.radius[1:], chord_sag(p), torch.ones(p.shape[1] - 1, dtype=torch.bool, device=p.device))


def join(*chains: Swept) -> Swept:
    """Several chains as one (the chords between them marked invalid)."""
    if len(chains) == 1:
        return chains[0]
    points, radius, sag, valid = [], [], [], []
    for i, c in enumerate(chains):
        points.append(c.points)
        radius.append(c.radius)
        sag.append(c.sag)
        valid.append(c.valid)
        if i + 1 < len(chains):                               # the gap chord to the next chain
            radius.append(c.radius.new_zeros(1))
            sag.append(c.sag.new_zeros(c.sag.shape[0], 1))
            valid.append(torch.zeros(1, dtype=torch.bool, device=c.valid.device))
    return Swept(torch.cat(points, 1), torch.cat(radius), torch.cat(sag, 1), torch.cat(valid))


def capsule_chain(a: Tensor, b: Tensor, radius: Tensor, spacing: float) -> tuple[Swept, Tensor]:
    """Capsules a, b (B, C, 3), radius (C,) [m] as one swept chain, each axis cut into chords of at most ``spacing``
    [m] (short chords keep the bound tight; sag 0), and the radius (P,) of each of its points."""
    chains, point_radius = [], []
    for c in range(a.shape[1]):
        n = max(1, int(torch.ceil(torch.linalg.vector_norm(a[0, c] - b[0, c]) / spacing)))
        t = torch.linspace(0, 1, n + 1, dtype=a.dtype, device=a.device).view(1, -1, 1)
        pts = a[:, c:c + 1] + t * (b[:, c:c + 1] - a[:, c:c + 1])
        chains.append(Swept(pts, radius[c].expand(n), pts.new_zeros(a.shape[0], n),
                            torch.ones(n, dtype=torch.bool, device=a.device)))
        point_radius.append(radius[c].expand(n + 1))
    return join(*chains), torch.cat(point_radius)


def convex_bound(fa: Tensor, fb: Tensor, sa: Tensor, sb: Tensor) -> Tensor:
    """Lower bound of a convex f on a chord t ∈ [0, 1] from its values fa, fb at the ends and its slopes sa, sb
    (∇f·(b − a)) there: the minimum of the upper envelope of the two tangent lines (module docstring)."""
    denom = sa - sb
    t = ((fb - sb - fa) / torch.where(denom < 0, denom, -1.0)).clamp(0.0, 1.0)
    bound = torch.where(sa >= 0, fa, torch.where(sb <= 0, fb, fa + sa * t))
    return torch.minimum(bound, torch.minimum(fa, fb))


def chain_clearance(scene: Scene, swept: Swept, distances: Tensor | None = None,
                    decide: float | None = None) -> Tensor:
    """Signed clearance (B,) [m] of a swept chain to a scene: the smallest lower bound over its valid chords and
    every obstacle (+inf for a scene without obstacles). Every (chord, obstacle) pair takes the Lipschitz bound;
    those whose Lipschitz bound lies below the smallest min(f_a, f_b) − radius − sag of the row (an upper bound of
    the result: no other pair can decide the minimum) also the convex one. ``distances``: the scene's distances
    (B, P, O) of the chain's points, when already computed. ``decide``: only whether the clearance is ≥ decide
    matters: a row whose Lipschitz bound is ≥ decide, or whose upper bound is < decide, skips the convex bound
    (the result is still a lower bound, on the same side of ``decide`` as the full one)."""
    pts = swept.points
    b = pts.shape[0]
    if scene.num_obstacles == 0 or not bool(swept.valid.any()):
        return pts.new_full((b,), float("inf"))
    d = scene.distances(pts)[0] if distances is None else distances             # (B, P, O)
    chord = pts[:, 1:] - pts[:, :-1]
    length = torch.linalg.vector_norm(chord, dim=-1)                            # (B, P − 1)
    shrink = (swept.radius + swept.sag).unsqueeze(-1)
    ends = torch.minimum(d[:, :-1], d[:, 1:])
    bound = (d[:, :-1] + d[:, 1:] - length.unsqueeze(-1)) / 2 - shrink          # Lipschitz, (B, P − 1, O)
    if not bool(swept.valid.all()):
        bound = bound.masked_fill(~swept.valid.view(1, -1, 1), float("inf"))
        ends = ends.masked_fill(~swept.valid.view(1, -1, 1), float("inf"))
    reach = (ends - shrink).flatten(1).amin(-1)                                 # (B,) ≥ the result
    if decide is not None:
        low = bound.flatten(1).amin(-1)
        reach = torch.where((low >= decide) | (reach < decide), -float("inf"), reach.clamp_max(decide))
    sel = ((bound < reach.view(-1, 1, 1)) & scene.convex.view(1, 1, -1)).nonzero()
    if sel.shape[0]:
        r, c, o = sel.unbind(-1)
        fa, ga = scene.pair_distances(pts[r, c], o)
        fb, gb = scene.pair_distances(pts[r, c + 1], o)
        tight = convex_bound(fa, fb, (ga * chord[r, c]).sum(-1), (gb * chord[r, c]).sum(-1)) - shrink[r, c, 0]
        bound = bound.index_put((r, c, o), torch.maximum(bound[r, c, o], tight))
    return bound.flatten(1).amin(-1)


def capsule_clearance(swept: Swept, a: Tensor, b: Tensor, radius: Tensor) -> Tensor:
    """Signed clearance (B,) [m] of a swept chain to capsules moving with it: a, b (B, C, 3), radius (C,) (e.g.
    an arm's links around the robot it carries); +inf without capsules."""
    from .shapes import capsule_distance
    pts = swept.points
    if a.shape[1] == 0 or not bool(swept.valid.any()):
        return pts.new_full((pts.shape[0],), float("inf"))
    d, g = capsule_distance(pts.unsqueeze(2), a.unsqueeze(1), b.unsqueeze(1), radius)     # (B, P, C), (B, P, C, 3)
    chord = (pts[:, 1:] - pts[:, :-1]).unsqueeze(-2)
    bound = convex_bound(d[:, :-1], d[:, 1:], (g[:, :-1] * chord).sum(-1), (g[:, 1:] * chord).sum(-1))
    bound = bound - (swept.radius + swept.sag).unsqueeze(-1)
    return bound[:, swept.valid].flatten(1).amin(-1)
