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

from .scene import Scene

__all__ = ["MeshEdges", "candidate_edges", "mesh_edges"]


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


def mesh_edges(sc: Scene, eps: float) -> MeshEdges:
    """Group the facets' edges by their end points (rounded to ``eps`` metres). Not differentiated.

    Args:
        sc: The scene.
        eps: Length below which two end points are one (and an edge is degenerate), in metres.

    Returns:
        The :class:`MeshEdges` of the scene, on the CPU.
    """
    c = sc.corners.detach().double().cpu()
    F = c.shape[0]
    a, b = c.reshape(-1, 3), torch.roll(c, -1, dims=1).reshape(-1, 3)
    flat_id = torch.arange(4 * F)
    real = (b - a).norm(dim=-1) > eps
    flat_id, a, b = flat_id[real], a[real], b[real]
    ka, kb = torch.round(a / eps).long(), torch.round(b / eps).long()
    lead = (ka != kb).int().argmax(-1)  # order the two ends lexicographically
    swap = (ka.gather(1, lead[:, None]) > kb.gather(1, lead[:, None]))[:, 0]
    key = torch.cat([torch.where(swap[:, None], kb, ka), torch.where(swap[:, None], ka, kb)], 1)
    _, group, count = torch.unique(key, dim=0, return_inverse=True, return_counts=True)
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
