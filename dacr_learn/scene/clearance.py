"""Clearance of swept bodies: a lower bound on the distance of a robot's (or an arm link's) envelope to obstacles.

A :class:`Swept` body is a chain of points (B, P, 3); the body between consecutive points is the chord joining
them, within ``sag`` of it (the backbone's arc, :func:`~dacr_learn.body.chord_sag`; 0 for a straight link),
swept by a ball of the chord's ``radius``. Its clearance to an obstacle is bounded below per chord from the
signed distance f and its gradient at the two ends, f(t) along the chord t ∈ [0, 1]:

- convex obstacles (sphere, capsule, box): f is convex along the chord, so it lies above its tangent lines, e.g.
  f_a + s_a·t and f_b + s_b·(t − 1) (s = ∇f·(b − a)); the bound is the minimum of their upper envelope on [0, 1],
  tightened by tangents where that envelope is lowest (:func:`cut_bound`);
- meshes: f is 1-Lipschitz: f(t) ≥ (f_a + f_b − c)/2 for a chord of length c;

minus the chord's radius and sag. The bound is exact at the chord's ends; for convex obstacles its gap is the
sag's (∝ chord², a check of denser points is tighter) plus what the cuts leave (shrinking fast with each cut).
Meshes get the (looser) Lipschitz bound. Only the chords and obstacles that can hold the minimum are refined
(:func:`swept_clearance`), so most of the cost is the distances at the points.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from ..body import BodyPoints, chord_sag
from .files import Scene
from .shapes import capsule_distance

PairDistance = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]


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
    [m] (short chords keep the bound tight; sag 0), and the radius (P,) of each of its points. The chords per
    capsule follow the first row's axis lengths (the same in every row for a rigid link; any count is a valid
    chain, it only sets how tight the bound is); the chords between two capsules are invalid (as :func:`join`)."""
    counts = tuple(max(1, int(n)) for n in torch.ceil(torch.linalg.vector_norm(a[0] - b[0], dim=-1) / spacing).tolist())
    capsule, t, chord_capsule, valid = _chain_layout(counts, a.device)
    pts = torch.lerp(a[:, capsule], b[:, capsule], t.to(a.dtype).unsqueeze(-1))
    chord_radius = torch.where(valid, radius[chord_capsule], radius.new_zeros(()))
    return Swept(pts, chord_radius, pts.new_zeros(a.shape[0], valid.numel()), valid), radius[capsule]


@functools.lru_cache(maxsize=64)
def _chain_layout(counts: tuple[int, ...], device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per point of a capsule chain with ``counts`` chords per capsule: its capsule (P,) and fraction t (P,) along
    the axis; per chord: its capsule (P − 1,) and whether it is valid (False between two capsules)."""
    capsule = torch.cat([torch.full((n + 1,), c) for c, n in enumerate(counts)])
    t = torch.cat([torch.linspace(0, 1, n + 1, dtype=torch.float64) for n in counts])
    valid = torch.cat([torch.cat([torch.ones(n, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)])
                       for n in counts])[:-1]
    return capsule.to(device), t.to(device), capsule[:-1].to(device), valid.to(device)


CUTS = 2   # tangent cuts per refined (chord, convex obstacle) pair, each at the minimum of the bound so far


def _envelope(fa: Tensor, fb: Tensor, sa: Tensor, sb: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`convex_bound` and where on [0, 1] the upper envelope of the two tangent lines is lowest."""
    denom = sa - sb
    t = ((fb - sb - fa) / torch.where(denom < 0, denom, -1.0)).clamp(0.0, 1.0)
    bound = torch.where(sa >= 0, fa, torch.where(sb <= 0, fb, fa + sa * t))
    return torch.minimum(bound, torch.minimum(fa, fb)), t


def convex_bound(fa: Tensor, fb: Tensor, sa: Tensor, sb: Tensor) -> Tensor:
    """Lower bound of a convex f on a chord t ∈ [0, 1] from its values fa, fb at the ends and its slopes sa, sb
    (∇f·(b − a)) there: the minimum of the upper envelope of the two tangent lines (module docstring)."""
    return _envelope(fa, fb, sa, sb)[0]


def cut_bound(pair: PairDistance, rows: Tensor, a: Tensor, b: Tensor, field: Tensor, cuts: int = CUTS) -> Tensor:
    """Lower bound (T,) [m] of convex distance fields along chords a → b (T, 3) of batch rows ``rows`` (T,), field
    indices ``field`` (T,): :func:`convex_bound` of the ends, then ``cuts`` times the field's tangent where that
    bound is lowest, t*: the minimum lies on the side of t* where the slope there points down, and the two tangents
    bounding that side give the next bound (a cutting-plane search; every bound is a lower bound, each tighter)."""
    ab, n = b - a, rows.shape[0]
    f2, g2 = pair(torch.cat([rows, rows]), torch.cat([a, b]), torch.cat([field, field]))   # both ends in one call
    fa, fb, ga, gb = f2[:n], f2[n:], g2[:n], g2[n:]
    sa, sb = (ga * ab).sum(-1), (gb * ab).sum(-1)                              # slopes per unit t
    bound, u = _envelope(fa, fb, sa, sb)
    lo, hi = torch.zeros_like(fa), torch.ones_like(fa)
    for _ in range(cuts):                 # where sa ≥ 0 or sb ≤ 0 the bound is an end's value, exact: kept as is
        t = lo + u * (hi - lo)
        f, g = pair(rows, a + t.unsqueeze(-1) * ab, field)
        s = (g * ab).sum(-1)
        inner = (sa < 0) & (sb > 0)
        left, right = inner & (s >= 0), inner & (s < 0)                   # the minimum lies in [lo, t*] / [t*, hi]
        lo, hi = torch.where(right, t, lo), torch.where(left, t, hi)
        fa, sa = torch.where(right, f, fa), torch.where(right, s, sa)
        fb, sb = torch.where(left, f, fb), torch.where(left, s, sb)
        width = hi - lo
        tighter, u = _envelope(fa, fb, sa * width, sb * width)
        bound = torch.maximum(bound, tighter)
    return bound


def swept_clearance(swept: Swept, distances: Tensor, pair: PairDistance, convex: Tensor,
                    decide: float | None = None, cuts: int = CUTS) -> Tensor:
    """Signed clearance lower bound (B,) [m] of a swept chain to F distance fields (obstacles, or capsules moving
    with each row), from their values at the chain's points ``distances`` (B, P, F) (+inf where a field does not
    apply to a point); ``pair(rows (T,), points (T, 3), field (T,))`` → (distance (T,), gradient (T, 3)) of one
    field each; ``convex`` (F,) bool: the fields that are convex along a line (else 1-Lipschitz only).

    In stages, each skipping what cannot decide the minimum: (1) every chord takes the Lipschitz bound of the
    nearest field at its two ends, (f_a + f_b − c)/2 − radius − sag with f the smallest distance at each point;
    (2) the chords whose bound lies below the row's upper bound of the result (the smallest min(f_a, f_b) − radius
    − sag; no other chord can hold the minimum) take it per field; (3) those (chord, convex field) pairs still below
    it take :func:`cut_bound` (``cuts`` tangent cuts). ``decide``: only whether the clearance is ≥ decide matters:
    rows whose stage-1 bound is ≥ decide, or whose upper bound is < decide, stop there (the result is still a lower
    bound, on the same side of ``decide`` as the full one)."""
    pts = swept.points
    b = pts.shape[0]
    if distances.shape[-1] == 0 or not bool(swept.valid.any()):
        return pts.new_full((b,), float("inf"))
    length = torch.linalg.vector_norm(pts[:, 1:] - pts[:, :-1], dim=-1)          # (B, P − 1)
    shrink = swept.radius + swept.sag
    near = distances.amin(-1)                                                     # (B, P)
    bound = (near[:, :-1] + near[:, 1:] - length) / 2 - shrink
    ends = torch.minimum(near[:, :-1], near[:, 1:]) - shrink
    if not bool(swept.valid.all()):
        bound = bound.masked_fill(~swept.valid, float("inf"))
        ends = ends.masked_fill(~swept.valid, float("inf"))
    reach = ends.amin(-1)                                                         # (B,) ≥ the result
    if decide is not None:
        low = bound.amin(-1)
        reach = torch.where((low >= decide) | (reach < decide), -float("inf"), reach.clamp_max(decide))
    rows, chord = (bound < reach.unsqueeze(-1)).nonzero().unbind(-1)
    if rows.numel() == 0:
        return bound.amin(-1)
    cap = shrink[rows, chord].unsqueeze(-1)
    each = (distances[rows, chord] + distances[rows, chord + 1] - length[rows, chord].unsqueeze(-1)) / 2 - cap
    sel, field = ((each < reach[rows].unsqueeze(-1)) & convex).nonzero().unbind(-1)
    if sel.numel():
        r, c = rows[sel], chord[sel]
        tight = cut_bound(pair, r, pts[r, c], pts[r, c + 1], field, cuts) - cap[sel, 0]
        each = each.index_put((sel, field), torch.maximum(each[sel, field], tight))
    return bound.index_put((rows, chord), each.amin(-1)).amin(-1)


def chain_clearance(scene: Scene, swept: Swept, distances: Tensor | None = None,
                    decide: float | None = None, cuts: int = CUTS) -> Tensor:
    """Signed clearance (B,) [m] of a swept chain to a scene (+inf for a scene without obstacles): the smallest lower
    bound over its valid chords and every obstacle (:func:`swept_clearance`: convex obstacles take tangent bounds,
    meshes the Lipschitz one). ``distances``: the scene's distances (B, P, O) of the chain's points, when already
    computed; ``decide``, ``cuts``: as in :func:`swept_clearance`."""
    pts = swept.points
    if scene.num_obstacles == 0:
        return pts.new_full((pts.shape[0],), float("inf"))
    d = scene.distances(pts)[0] if distances is None else distances
    return swept_clearance(swept, d, lambda rows, p, o: scene.pair_distances(p, o), scene.convex, decide, cuts)


def capsule_pair(a: Tensor, b: Tensor, radius: Tensor) -> PairDistance:
    """The ``pair`` of :func:`swept_clearance` for capsules moving with the rows: a, b (B, C, 3), radius (C,) [m]."""
    return lambda rows, p, c: capsule_distance(p, a[rows, c], b[rows, c], radius[c])


def capsule_clearance(swept: Swept, a: Tensor, b: Tensor, radius: Tensor, decide: float | None = None,
                      cuts: int = CUTS) -> Tensor:
    """Signed clearance (B,) [m] of a swept chain to capsules moving with it: a, b (B, C, 3), radius (C,) (e.g.
    an arm's links around the robot it carries); +inf without capsules. ``decide``, ``cuts``: as in
    :func:`swept_clearance`."""
    pts = swept.points
    if a.shape[1] == 0:
        return pts.new_full((pts.shape[0],), float("inf"))
    d = capsule_distance(pts.unsqueeze(2), a.unsqueeze(1), b.unsqueeze(1), radius, grad=False)[0]   # (B, P, C)
    return swept_clearance(swept, d, capsule_pair(a, b, radius), torch.ones(a.shape[1], dtype=torch.bool), decide,
                           cuts)
