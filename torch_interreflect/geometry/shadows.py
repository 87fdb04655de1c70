"""Where a distant light's shadow edges can lie: mesh edges projected along the light onto facets.

A boundary or crease edge (:func:`~torch_interreflect.geometry.edges.candidate_edges`) in front of a facet casts,
along a light travelling in direction ``d``, a straight segment on the facet's plane; the part of it on the facet
is where that facet's shadow boundary can run. :func:`shadow_segments` finds these parts; whether a shadow really
changes across a part is for the caller to test with rays (the sun's lit fractions in
:func:`~torch_interreflect.lights.sun_shadow_gradient`, the image's shadow edges in
:mod:`~torch_interreflect.camera.image_grad`). Not differentiated: callers rebuild the differentiable positions
from the edge parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ._polygon import clip_interval, clip_segments
from .edges import candidate_edges
from .scene import Scene

__all__ = ["ShadowSegments", "shadow_segments"]


@dataclass(frozen=True)
class ShadowSegments:
    """Projected edge parts, one row each (float64, CPU).

    Attributes:
        facet: The facet the part lies on. ``[N]`` int64.
        edge_facet, edge_corner: The casting edge, from corner ``edge_corner`` to ``edge_corner + 1`` (mod 4) of
            ``edge_facet``. ``[N]`` int64.
        s_a, s_b: The edge parameters of the part's ends (the projection is affine: ``s = s_a + λ (s_b − s_a)``
            along the part, ``λ ∈ [0, 1]``). ``[N]``.
        start, end: The part's ends on the facet, in metres. ``[N, 3]``.
    """

    facet: Tensor
    edge_facet: Tensor
    edge_corner: Tensor
    s_a: Tensor
    s_b: Tensor
    start: Tensor
    end: Tensor


def shadow_segments(sc: Scene, direction: Tensor, facets: Tensor, eps: float) -> ShadowSegments:
    """The parts of the scene's candidate edges that a light travelling along ``direction`` projects onto
    ``facets`` (each edge's part in front of the facet, projected along the light, clipped to the facet; parts
    shorter than ``eps`` are dropped).

    Args:
        sc: The scene (detached, float64, CPU).
        direction: Unit direction the light travels. ``[3]``.
        facets: The receiving facets (int64 ``[K]``); facets facing away from the light get no parts.
        eps: Length tolerance in metres (:func:`~torch_interreflect.geometry._polygon.plane_eps`).

    Returns:
        The :class:`ShadowSegments`.
    """
    cd, normals, d = sc.corners, sc.normals, direction
    facet, corner = candidate_edges(sc, eps)
    empty = torch.zeros(0, dtype=torch.int64)
    if facet.numel() == 0 or facets.numel() == 0:
        z = torch.zeros(0, dtype=cd.dtype)
        return ShadowSegments(empty, empty, empty, z, z, z.reshape(0, 3), z.reshape(0, 3))
    e0, e1 = cd[facet, corner], cd[facet, (corner + 1) % 4]
    f, e = (t.reshape(-1) for t in torch.meshgrid(facets, torch.arange(facet.numel()), indexing="ij"))
    n, o = normals[f], cd[f, 0]
    h0, h1 = ((e0[e] - o) * n).sum(-1), ((e1[e] - o) * n).sum(-1)
    sa, sb = clip_interval(torch.zeros_like(h0), torch.ones_like(h0), h0 - eps, h1 - h0)  # in front of the facet
    dn = n @ d
    keep = (sb > sa) & (dn < 0)
    f, e, n, o, sa, sb, dn = f[keep], e[keep], n[keep], o[keep], sa[keep], sb[keep], dn[keep]

    def project(s: Tensor) -> Tensor:
        b = e0[e] + s[:, None] * (e1[e] - e0[e])
        return b - (((b - o) * n).sum(-1) / dn)[:, None] * d

    ya, yb = project(sa), project(sb)
    la, lb = clip_segments(ya, yb, cd[f], n)  # the projection's part on the facet
    keep = (lb - la) * (yb - ya).norm(dim=-1) > eps
    f, e, sa, sb, la, lb, ya, yb = (t[keep] for t in (f, e, sa, sb, la, lb, ya, yb))
    seg = yb - ya
    return ShadowSegments(f, facet[e], corner[e], sa + la * (sb - sa), sa + lb * (sb - sa),
                          ya + la[:, None] * seg, ya + lb[:, None] * seg)
