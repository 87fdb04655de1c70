"""Per-facet measures of corners ``[F, 4, 3]`` (a triangle repeating its last corner): areas, unit normals,
centroids, diameters. Differentiable; :class:`~.scene.Scene` keeps them while its corners are unchanged
(:mod:`.derived`)."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["facet_areas", "facet_centroids", "facet_diameters", "facet_normals"]


def facet_normals(c: Tensor) -> Tensor:
    """Unit normals ``[F, 3]``: the Newell-like robust normal of a (possibly collapsed) quad, the cross product of
    its diagonals."""
    n = torch.linalg.cross(c[:, 2] - c[:, 0], c[:, 3] - c[:, 1], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(c.dtype).tiny)


def facet_centroids(c: Tensor) -> Tensor:
    """Area centroids ``[F, 3]`` (m)."""
    a, b, cc, d = c.unbind(1)
    # split into triangles (a, b, c) and (a, c, d); a collapsed quad gives a zero second triangle
    a1 = 0.5 * torch.linalg.cross(b - a, cc - a, dim=-1).norm(dim=-1)
    a2 = 0.5 * torch.linalg.cross(cc - a, d - a, dim=-1).norm(dim=-1)
    g1 = (a + b + cc) / 3
    g2 = (a + cc + d) / 3
    return (a1[:, None] * g1 + a2[:, None] * g2) / (a1 + a2)[:, None]


def facet_areas(c: Tensor) -> Tensor:
    """Areas ``[F]`` (m²): half the norm of the cross product of the diagonals (exact for planar quads and
    triangles)."""
    return 0.5 * torch.linalg.cross(c[:, 2] - c[:, 0], c[:, 3] - c[:, 1], dim=-1).norm(dim=-1)


def facet_diameters(c: Tensor) -> Tensor:
    """Largest distance between two corners of each facet ``[F]`` (m)."""
    return (c[:, :, None, :] - c[:, None, :, :]).norm(dim=-1).flatten(1).max(dim=1).values
