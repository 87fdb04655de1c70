"""Lambert's contour formula: the exact form factor from a differential area to a polygon."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["point_polygon_factor"]



_INV_2PI = 1.0 / (2.0 * math.pi)


def point_polygon_factor(x: Tensor, normal: Tensor, polygon: Tensor) -> Tensor:
    """Exact form factor from differential areas to a polygon (Lambert's contour formula, no occlusion).

    ``F(dA_x → P) = -(1/2π) Σ_k γ_k n·(R_k × R_{k+1}) / |R_k × R_{k+1}|`` with ``R_k = v_k − x`` and
    ``γ_k`` the angle between ``R_k`` and ``R_{k+1}``; the polygon's vertices run counter-clockwise seen from
    ``x`` (i.e. ``x`` is in front of it). The polygon must lie on or above the tangent plane of ``x`` (clip it
    first otherwise). Repeated vertices (zero-length edges) contribute nothing, so padded polygons work.

    Args:
        x: Points in metres. Shape ``[P, Q, 3]``.
        normal: Unit normal at the points of each row. Shape ``[P, 3]``.
        polygon: Polygon vertices. Shape ``[P, K, 3]``.

    Returns:
        Form factors (dimensionless). Shape ``[P, Q]``.

    Example:
        >>> import torch
        >>> sq = torch.tensor([[[-.5, -.5, 1.], [-.5, .5, 1.], [.5, .5, 1.], [.5, -.5, 1.]]])  # faces down
        >>> x = torch.zeros(1, 1, 3); n = torch.tensor([[0., 0., 1.]])
        >>> round(float(point_polygon_factor(x, n, sq)), 7)
        0.2394565
    """
    # component-major layout [3, P, Q, K]: every temporary is a contiguous [P, Q, K] block
    X = x.permute(2, 0, 1)[..., None]
    V = polygon.permute(2, 0, 1)[:, :, None, :]
    rx, ry, rz = V - X
    sx, sy, sz = torch.roll(V, -1, dims=3) - X
    cx = ry * sz - rz * sy
    cy = rz * sx - rx * sz
    cz = rx * sy - ry * sx
    tiny = torch.finfo(x.dtype).tiny ** 0.5
    cn2 = cx * cx + cy * cy + cz * cz
    ok = cn2 > tiny * tiny  # a zero-length edge (a padded or triangle corner) adds nothing, and no NaN gradient:
    cn = torch.sqrt(torch.where(ok, cn2, torch.ones_like(cn2)))  # sqrt(0) and atan2(0, 0) are kept out of autograd
    gamma = torch.atan2(cn, torch.where(ok, rx * sx + ry * sy + rz * sz, torch.ones_like(cn2)))
    n = normal.T[:, :, None, None]
    proj = cx * n[0] + cy * n[1] + cz * n[2]
    term = torch.where(ok, gamma * proj / cn, torch.zeros_like(cn))
    return -_INV_2PI * term.sum(-1)
