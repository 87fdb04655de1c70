"""The edges of a scene's facets: which facets share each edge, and whether they share a plane.

Shadow boundaries (:mod:`~torch_interreflect.formfactors.visibility_grad`, the sun's shadows) and image
discontinuities (:mod:`~torch_interreflect.camera.image_grad`) move with these edges. Edges are matched by their end
points rounded to a length ``eps``; the degenerate edge of a triangle (stored as a quad with a repeated corner) is
left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._unique import unique_rows
from ._polygon import pieces_between
from .scene import Scene

__all__ = ["EdgePieces", "MeshEdges", "candidate_edges", "edge_pieces", "mesh_edges"]


@dataclass(frozen=True)
class MeshEdges:
    """One row per geometric edge.

    Attributes:
        facet: The facet that stands for the edge (the lowest ``4 · facet + corner``). ``[E]`` int64.
        corner: The edge runs from corner ``corner`` to corner ``corner + 1`` (mod 4) of ``facet``. ``[E]`` int64.
        partner: The other facet of an edge of exactly two facets, else ``-1``. ``[E]`` int64.
        share: How many facets have the edge. ``[E]`` int64.
        coplanar: ``True`` for an edge of two facets with the same plane (same normal and offset). ``[E]`` bool.
    """

    facet: Tensor
    corner: Tensor
    partner: Tensor
    share: Tensor
    coplanar: Tensor


def _facet_edges(sc: Scene, eps: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(corners [F, 4, 3], flat id [E], start [E, 3], end [E, 3])`` of every edge longer than ``eps`` (float64,
    CPU; ``flat id = 4 · facet + corner``, the edge from that corner to the next)."""
    c = sc.corners.detach().double().cpu()
    a, b = c.reshape(-1, 3), torch.roll(c, -1, dims=1).reshape(-1, 3)
    real = (b - a).norm(dim=-1) > eps
    return c, torch.arange(4 * c.shape[0])[real], a[real], b[real]


def _end_key(a: Tensor, b: Tensor, eps: float) -> Tensor:
    """A key ``[E, 6]`` (int64) of each segment's two end points rounded to ``eps``, the same for either direction."""
    ka, kb = torch.round(a / eps).long(), torch.round(b / eps).long()
    lead = (ka != kb).int().argmax(-1)  # order the two ends lexicographically
    swap = (ka.gather(1, lead[:, None]) > kb.gather(1, lead[:, None]))[:, 0]
    return torch.cat([torch.where(swap[:, None], kb, ka), torch.where(swap[:, None], ka, kb)], 1)


def mesh_edges(sc: Scene, eps: float) -> MeshEdges:
    """Group the facets' edges by their end points (rounded to ``eps`` metres). Not differentiated.

    Args:
        sc: The scene.
        eps: Length below which two end points are one (and an edge is degenerate), in metres.

    Returns:
        The :class:`MeshEdges` of the scene, on the CPU.
    """
    c, flat_id, a, b = _facet_edges(sc, eps)
    _, group, count = unique_rows(_end_key(a, b, eps))
    order = torch.argsort(group, stable=True)  # within a group: ascending flat index
    _, first = np.unique(group[order].numpy(), return_index=True)
    first_t = torch.as_tensor(first)
    lead_id = flat_id[order[first_t]]
    share = count
    partner = torch.full_like(share, -1)
    coplanar = torch.zeros_like(share, dtype=torch.bool)
    two = torch.nonzero(share == 2).reshape(-1)
    if two.numel():
        second = flat_id[order[first_t[two] + 1]]
        fi, fj = lead_id[two] // 4, second // 4
        partner[two] = fj
        n = sc.normals.detach().double().cpu()
        pos_i = (n[fi] * c[fi, lead_id[two] % 4]).sum(-1)  # each plane's offset at its own edge's start
        pos_j = (n[fj] * c[fj, second % 4]).sum(-1)
        coplanar[two] = ((n[fi] * n[fj]).sum(-1) > 1 - 1e-9) & ((pos_i - pos_j).abs() <= eps)
    return MeshEdges(lead_id // 4, lead_id % 4, partner, share, coplanar)


def candidate_edges(sc: Scene, eps: float) -> tuple[Tensor, Tensor]:
    """Edges that can cast a shadow boundary: ``(facet [E], corner [E])``, the edge from corner ``k`` to corner
    ``k + 1`` (mod 4) of ``facet``. Boundary edges (one facet), edges of more than two facets and creases (two
    facets with different planes) of :func:`mesh_edges`; edges between coplanar facets, and the degenerate edge of
    a triangle, are left out."""
    e = mesh_edges(sc, eps)
    keep = (e.share != 2) | ~e.coplanar
    return e.facet[keep], e.corner[keep]


@dataclass(frozen=True)
class EdgePieces:
    """The facets' edges cut where another facet's corner lies on them, one row per geometric piece.

    A piece runs over ``[t0, t1]`` of the edge from corner ``corner`` to corner ``corner + 1`` (mod 4) of ``facet``
    (the lowest ``4 · facet + corner`` among the facets that have it), and ``facets`` lists every facet that has it
    (``-1`` padded). Where a facet borders two smaller ones (a T-junction, as refinement and contact splits leave),
    its edge is cut at their shared corner, so each piece is listed once with the facets on both of its sides.

    Attributes:
        facet, corner: ``[E]`` int64. t0, t1: ``[E]`` float64 in ``[0, 1]``. facets: ``[E, M]`` int64.
    """

    facet: Tensor
    corner: Tensor
    t0: Tensor
    t1: Tensor
    facets: Tensor


def edge_pieces(sc: Scene, eps: float, chunk: int = 1 << 22) -> EdgePieces:
    """Cut every edge at the corners of other facets that lie on it (within ``eps`` metres), then group the pieces
    by their end points (:class:`EdgePieces`). Not differentiated; ``chunk`` bounds the (edge, corner) tests at
    once."""
    c, flat_id, a, b = _facet_edges(sc, eps)
    verts = unique_rows(torch.round(c.reshape(-1, 3) / eps))[0] * eps  # the corners, each once
    d = b - a
    length2 = (d * d).sum(-1)
    cuts_e, cuts_t = [], []
    per = max(1, chunk // max(1, verts.shape[0]))
    for s in range(0, a.shape[0], per):
        aa, dd, ll = a[s : s + per, None], d[s : s + per, None], length2[s : s + per, None]
        t = ((verts[None] - aa) * dd).sum(-1) / ll  # [e, V]
        off = (aa + t[..., None] * dd - verts[None]).norm(dim=-1)
        inner = (off <= eps) & (t * ll.sqrt() > eps) & ((1 - t) * ll.sqrt() > eps)
        e, v = torch.nonzero(inner, as_tuple=True)
        cuts_e.append(e + s)
        cuts_t.append(t[e, v])
    ce, ct = torch.cat(cuts_e), torch.cat(cuts_t)
    n = a.shape[0]
    # every edge's break points: 0, its cuts, 1
    pe = torch.cat([torch.arange(n), ce, torch.arange(n)])
    pt = torch.cat([torch.zeros(n, dtype=torch.float64), ct, torch.ones(n, dtype=torch.float64)])
    edge, t0, t1 = pieces_between(pe, pt)
    p0 = a[edge] + t0[:, None] * d[edge]
    p1 = a[edge] + t1[:, None] * d[edge]
    _, group, count = unique_rows(_end_key(p0, p1, eps))
    member = flat_id[edge]
    order = torch.argsort(member, stable=True)
    order = order[torch.argsort(group[order], stable=True)]  # by group, then by 4 · facet + corner
    g_sorted = group[order]
    first = torch.ones_like(g_sorted, dtype=torch.bool)
    first[1:] = g_sorted[1:] != g_sorted[:-1]
    start = torch.nonzero(first).reshape(-1)
    rank = torch.arange(g_sorted.numel()) - start[torch.cumsum(first.long(), 0) - 1]
    M = int(count.max()) if count.numel() else 1
    facets = torch.full((count.numel(), M), -1, dtype=torch.int64)
    facets[g_sorted, rank] = member[order] // 4
    lead_row = order[first]  # the piece standing for its group
    return EdgePieces(member[lead_row] // 4, member[lead_row] % 4, t0[lead_row], t1[lead_row], facets)
