"""Validation of facet corners when a :class:`~torch_interreflect.Scene` is built: finite, not degenerate, planar
and convex quads. Each failure raises :class:`~torch_interreflect.errors.GeometryError` naming the facet."""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import GeometryError

__all__ = ["AREA_RTOL", "PLANARITY_RTOL", "check_facets"]

#: Relative tolerance for planarity of quads (distance of the 4th vertex to the plane / facet diameter).
PLANARITY_RTOL = 1e-5
#: Facets with area below ``AREA_RTOL * scene_diameter**2`` are degenerate.
AREA_RTOL = 1e-12


def check_facets(corners: Tensor, is_triangle: Tensor) -> None:
    """Raise ``GeometryError`` for the first facet that is non-finite, degenerate, non-planar or non-convex.

    Shape:
        - corners: ``[F, 4, 3]`` (triangles repeat their last corner); is_triangle: ``[F]``
    """
    c = corners
    if c.shape[0] == 0:
        raise GeometryError("a scene needs at least one facet; got 0")
    finite = torch.isfinite(c).reshape(c.shape[0], -1).all(dim=1)
    if not bool(finite.all()):
        bad = int(torch.nonzero(~finite)[0])
        raise GeometryError(f"facet {bad} has non-finite corners: {c[bad].tolist()}")
    cd = c.detach().double()  # validation only: no graph, no warnings for corners that require grad
    diam = float((cd.reshape(-1, 3).max(0).values - cd.reshape(-1, 3).min(0).values).norm())
    # fan area (sum of the two triangles' areas): a bow-tie quad is caught later, as non-convex
    a, b, cc, d = cd.unbind(1)
    area = 0.5 * torch.linalg.cross(b - a, cc - a, dim=-1).norm(dim=-1)
    area = area + 0.5 * torch.linalg.cross(cc - a, d - a, dim=-1).norm(dim=-1)
    tiny = area <= AREA_RTOL * max(diam, 1e-300) ** 2
    if bool(tiny.any()):
        bad = int(torch.nonzero(tiny)[0])
        raise GeometryError(
            f"facet {bad} is degenerate: area {float(area[bad]):.3g} m² (corners {cd[bad].tolist()})"
        )
    quad = ~is_triangle
    if bool(quad.any()):
        n = torch.linalg.cross(cd[:, 2] - cd[:, 0], cd[:, 3] - cd[:, 1], dim=-1)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        size = (cd - cd.mean(1, keepdim=True)).norm(dim=-1).max(dim=1).values
        # planarity: every corner within PLANARITY_RTOL * size of the mean plane
        dev = ((cd - cd.mean(1, keepdim=True)) * n[:, None, :]).sum(-1).abs().max(dim=1).values
        nonplanar = quad & (dev > PLANARITY_RTOL * size)
        if bool(nonplanar.any()):
            bad = int(torch.nonzero(nonplanar)[0])
            raise GeometryError(
                f"facet {bad} is not planar: a corner lies {float(dev[bad]):.3g} m off its plane "
                f"(tolerance {PLANARITY_RTOL:g} × size {float(size[bad]):.3g} m)"
            )
        # convexity: the turn at every corner has the orientation of the facet normal
        e = torch.roll(cd, -1, dims=1) - cd
        turn = torch.linalg.cross(e, torch.roll(e, -1, dims=1), dim=-1)
        s = (turn * n[:, None, :]).sum(-1)
        nonconvex = quad & (s <= 1e-12 * size[:, None] ** 2).any(dim=1)
        if bool(nonconvex.any()):
            bad = int(torch.nonzero(nonconvex)[0])
            raise GeometryError(
                f"facet {bad} is not a convex quad with corners in order (turn orientations "
                f"{[round(float(x), 6) for x in s[bad]]}); corners {cd[bad].tolist()}"
            )
