"""Gaps between facets: the least distance between two convex planar facets, and the pairs whose gap is small
against their size (near-field pairs that do not touch: a wall hung a few centimetres above a floor).

Where two facets touch (a concave edge, a block on a floor), the planners resolve the light along the contact
(:mod:`.contacts`). Where they nearly touch, each lights the other in a band about as wide as the gap, which a leaf
much larger than the gap cannot follow; the error then sits in the *other* facet's output (the floor under the wall
is off because the wall's radiosity near its foot is wrong), where a per-facet estimate does not look for it.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import ShapeError, ValueRangeError
from ._polygon import plane_eps
from .scene import Scene

__all__ = ["PAIR_CHUNK", "near_pairs", "polygon_gaps"]

#: Largest number of facet pairs whose gap is computed at once.
PAIR_CHUNK = 1 << 16


def _segment_distances(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    """Least distance between segments ``p1 q1`` and ``p2 q2`` (``[..., 3]`` each, any batch shape); either may be a
    point. The clamped closed form (Ericson, *Real-Time Collision Detection*, 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = (d1 * d1).sum(-1), (d2 * d2).sum(-1)
    b, c, f = (d1 * d2).sum(-1), (d1 * r).sum(-1), (d2 * r).sum(-1)
    tiny = torch.finfo(p1.dtype).tiny
    den = a * e - b * b
    s = torch.where(den > 1e-12 * a * e, ((b * f - c * e) / den.clamp_min(tiny)).clamp(0, 1), torch.zeros_like(a))
    s = torch.where(a > tiny, s, torch.zeros_like(s))
    t = torch.where(e > tiny, (b * s + f) / e.clamp_min(tiny), torch.zeros_like(s))
    # t outside [0, 1]: clamp it and recompute s for the clamped t
    t_c = t.clamp(0, 1)
    s = torch.where((t != t_c) & (a > tiny), ((b * t_c - c) / a.clamp_min(tiny)).clamp(0, 1), s)
    s = torch.where((e <= tiny) & (a > tiny), (-c / a.clamp_min(tiny)).clamp(0, 1), s)  # the second is a point
    return (p1 + s[..., None] * d1 - p2 - t_c[..., None] * d2).norm(dim=-1)


def _point_polygon_distances(x: Tensor, poly: Tensor, normal: Tensor, eps: float) -> Tensor:
    """Least distance from points ``x [P, K, 3]`` to convex planar polygons ``poly [P, 4, 3]`` (normals
    ``[P, 3]``): to the plane where the point's projection falls inside (``eps`` of margin), else to the nearest
    edge. Shape ``[P, K]``."""
    nxt = poly.roll(-1, dims=1)
    height = ((x - poly[:, None, 0]) * normal[:, None]).sum(-1)  # [P, K]
    y = x - height[..., None] * normal[:, None]
    side = (torch.linalg.cross((nxt - poly)[:, None], y[:, :, None] - poly[:, None], dim=-1)
            * normal[:, None, None]).sum(-1)  # [P, K, 4]; a repeated corner's edge gives 0
    inside = (side >= -eps * (nxt - poly).norm(dim=-1)[:, None]).all(-1)
    edge = _segment_distances(x[:, :, None], x[:, :, None], poly[:, None], nxt[:, None]).amin(-1)
    return torch.where(inside, height.abs(), edge)


def _crossing_distances(a: Tensor, b: Tensor, normal_b: Tensor, eps: float) -> Tensor:
    """Least distance ``[P]`` from where ``a``'s edges cross ``b``'s plane to facet ``b`` (0 where an edge of ``a``
    passes through ``b``); an edge that does not cross stands in with its first corner."""
    h = ((a - b[:, None, 0]) * normal_b[:, None]).sum(-1)  # [P, 4]
    hn, an = h.roll(-1, dims=1), a.roll(-1, dims=1)
    t = torch.where(h * hn < 0, h / (h - hn).where(h * hn < 0, torch.ones_like(h)), torch.zeros_like(h))
    return _point_polygon_distances(a + t[..., None] * (an - a), b, normal_b, eps).amin(-1)


def polygon_gaps(a: Tensor, b: Tensor, normal_a: Tensor, normal_b: Tensor, eps: float = 0.0) -> Tensor:
    """Least distance between pairs of convex planar facets (m).

    The least of: every corner of one to the other facet, every edge of one to every edge of the other, and where an
    edge of one crosses the other's plane, that point to the other facet (0 where the facets cross).

    Args:
        a, b: Corners of the pairs' facets (a triangle repeats its last corner). Shape ``[P, 4, 3]`` each.
        normal_a, normal_b: Their unit normals, by the right-hand rule of the corners' order (as
            :attr:`~.scene.Scene.normals`: the inside test depends on it). Shape ``[P, 3]`` each.
        eps: Margin of the inside test (m).

    Returns:
        Gaps ``[P]`` (0 where the facets touch or cross).

    Raises:
        ShapeError: ``a`` and ``b`` not ``[P, 4, 3]`` alike, or normals not ``[P, 3]``.

    Shape:
        - a, b: ``[P, 4, 3]``; normal_a, normal_b: ``[P, 3]``; output ``[P]``

    Example:
        >>> import torch
        >>> from torch_interreflect.geometry.gaps import polygon_gaps
        >>> floor = torch.tensor([[[0., 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]])
        >>> wall = torch.tensor([[[0.5, 0, 0.05], [0.5, 1, 0.05], [0.5, 1, 1], [0.5, 0, 1]]])
        >>> round(float(polygon_gaps(floor, wall, torch.tensor([[0., 0, 1]]), torch.tensor([[1., 0, 0]]))[0]), 6)
        0.05
    """
    if a.ndim != 3 or tuple(a.shape[1:]) != (4, 3) or a.shape != b.shape or normal_a.shape != (a.shape[0], 3) \
            or normal_b.shape != normal_a.shape:
        raise ShapeError(f"polygon_gaps needs corners [P, 4, 3] twice and normals [P, 3] twice; got {list(a.shape)}, "
                         f"{list(b.shape)}, {list(normal_a.shape)}, {list(normal_b.shape)}")
    corners = torch.minimum(_point_polygon_distances(a, b, normal_b, eps).amin(-1),
                            _point_polygon_distances(b, a, normal_a, eps).amin(-1))
    crossings = torch.minimum(_crossing_distances(a, b, normal_b, eps), _crossing_distances(b, a, normal_a, eps))
    ea, eb = a.roll(-1, dims=1), b.roll(-1, dims=1)
    edges = _segment_distances(a[:, :, None], ea[:, :, None], b[:, None], eb[:, None]).flatten(1).amin(-1)
    return torch.minimum(torch.minimum(corners, crossings), edges)


def near_pairs(scene: Scene, ratio: float) -> tuple[Tensor, Tensor, Tensor]:
    """Pairs of facets that face each other (each partly in front of the other) and do not touch, whose gap is
    below ``ratio`` times the larger of their diameters.

    Args:
        scene: The scene.
        ratio: Largest gap over the larger diameter of the pair.

    Returns:
        ``(i, j, gap)``: both orders of every pair (int64), and their gaps in metres (float64).

    Raises:
        ValueRangeError: ``ratio`` not a finite positive number.

    Shape:
        - output ``i, j, gap``: ``[P]`` each (``P`` even: both orders)

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.geometry.gaps import near_pairs
        >>> floor = [[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]]
        >>> wall = [[0.3, -2.0, 0.05], [0.3, 2.0, 0.05], [0.3, 2.0, 3.0], [0.3, -2.0, 3.0]]
        >>> i, j, gap = near_pairs(ti.Scene.from_polygons(torch.tensor([floor, wall])), 0.25)
        >>> i.tolist(), j.tolist(), [round(g, 4) for g in gap.tolist()]
        ([0, 1], [1, 0], [0.05, 0.05])
    """
    if not (isinstance(ratio, (int, float)) and math.isfinite(ratio) and ratio > 0):
        raise ValueRangeError(f"near_pairs needs a finite ratio > 0 (gap over the larger diameter); got {ratio!r}")
    sc = scene.to(torch.float64).to("cpu")
    corners, normals, diam, cent = (t.detach() for t in (sc.corners, sc.normals, sc.diameters, sc.centroids))
    eps = plane_eps(scene)
    i, j = _candidates(cent, diam, ratio)
    # facets facing the same way are never each in front of the other (their heights over each other's planes are
    # opposite): most candidates of a tiled plane, left before their corners are gathered
    other_way = (normals[i] * normals[j]).sum(-1) < 1.0 - 1e-9
    i, j = i[other_way], j[other_way]

    def heights(a: Tensor, b: Tensor) -> Tensor:  # of b's corners over a's plane [P, 4]
        return ((corners[b] - cent[a][:, None]) * normals[a][:, None]).sum(-1)

    h_ij, h_ji = heights(i, j), heights(j, i)
    # each partly in front of the other; the least height of one's corners over the other's plane bounds the gap
    low = torch.maximum(h_ij.amin(-1), h_ji.amin(-1))
    # a corner in the other's plane (a shared hinge; a block standing on the tile beside): the pair meets that plane
    # along a line, the concave corner of a contact, which the planners' estimates follow; not a gap
    on_plane = (h_ij.abs() <= eps).any(-1) | (h_ji.abs() <= eps).any(-1)
    keep = (h_ij > eps).any(-1) & (h_ji > eps).any(-1) & ~on_plane & (low < ratio * torch.maximum(diam[i], diam[j]))
    i, j = i[keep], j[keep]
    gaps = torch.cat([polygon_gaps(corners[i[s:s + PAIR_CHUNK]], corners[j[s:s + PAIR_CHUNK]],
                                   normals[i[s:s + PAIR_CHUNK]], normals[j[s:s + PAIR_CHUNK]], eps)
                      for s in range(0, i.numel(), PAIR_CHUNK)]) if i.numel() else torch.zeros(0, dtype=torch.float64)
    near = (gaps > eps) & (gaps < ratio * torch.maximum(diam[i], diam[j]))
    i, j, gaps = i[near], j[near], gaps[near]
    return torch.cat([i, j]), torch.cat([j, i]), torch.cat([gaps, gaps])


def _candidates(cent: Tensor, diam: Tensor, ratio: float) -> tuple[Tensor, Tensor]:
    """Pairs ``i < j`` whose centroids' distance less both diameters (each bounds a corner's distance from its
    centroid) is below ``ratio`` times the larger diameter, built in row blocks of about :data:`PAIR_CHUNK` pairs
    (memory ``O(F)`` per row, not ``O(F²)``)."""
    F = cent.shape[0]
    rows = max(1, PAIR_CHUNK // max(1, F))
    found_i, found_j = [], []
    for s0 in range(0, F, rows):
        r = torch.arange(s0, min(F, s0 + rows))
        dist = torch.cdist(cent[r], cent, compute_mode="donot_use_mm_for_euclid_dist")
        bound = dist - diam[r, None] - diam[None] - ratio * torch.maximum(diam[r, None], diam)
        a, b = torch.nonzero((bound < 0) & (torch.arange(F)[None] > r[:, None]), as_tuple=True)
        found_i.append(r[a])
        found_j.append(b)
    empty = torch.zeros(0, dtype=torch.int64)
    return (torch.cat(found_i), torch.cat(found_j)) if found_i else (empty, empty)
