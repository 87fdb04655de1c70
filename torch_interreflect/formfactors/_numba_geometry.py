"""Compiled geometry helpers shared by the numba loops of the form-factor stage (internal)."""

from __future__ import annotations

import math

from numba import njit

__all__ = ["bilinear_map", "jacobian_norm"]


@njit(cache=True, inline="always")
def bilinear_map(dom, uu, vv):
    """The point ``x(u, v)`` of the bilinear map of the quad ``dom [4, 3]`` and its tangents ``∂x/∂u``, ``∂x/∂v``."""
    a = (1 - uu) * (1 - vv)
    b = uu * (1 - vv)
    c = uu * vv
    e = (1 - uu) * vv
    x0 = a * dom[0, 0] + b * dom[1, 0] + c * dom[2, 0] + e * dom[3, 0]
    x1 = a * dom[0, 1] + b * dom[1, 1] + c * dom[2, 1] + e * dom[3, 1]
    x2 = a * dom[0, 2] + b * dom[1, 2] + c * dom[2, 2] + e * dom[3, 2]
    du0 = (1 - vv) * (dom[1, 0] - dom[0, 0]) + vv * (dom[2, 0] - dom[3, 0])
    du1 = (1 - vv) * (dom[1, 1] - dom[0, 1]) + vv * (dom[2, 1] - dom[3, 1])
    du2 = (1 - vv) * (dom[1, 2] - dom[0, 2]) + vv * (dom[2, 2] - dom[3, 2])
    dv0 = (1 - uu) * (dom[3, 0] - dom[0, 0]) + uu * (dom[2, 0] - dom[1, 0])
    dv1 = (1 - uu) * (dom[3, 1] - dom[0, 1]) + uu * (dom[2, 1] - dom[1, 1])
    dv2 = (1 - uu) * (dom[3, 2] - dom[0, 2]) + uu * (dom[2, 2] - dom[1, 2])
    return x0, x1, x2, du0, du1, du2, dv0, dv1, dv2


@njit(cache=True, inline="always")
def jacobian_norm(du0, du1, du2, dv0, dv1, dv2):
    """``|∂x/∂u × ∂x/∂v|``: the area Jacobian of the bilinear map at a point."""
    j0 = du1 * dv2 - du2 * dv1
    j1 = du2 * dv0 - du0 * dv2
    j2 = du0 * dv1 - du1 * dv0
    return math.sqrt(j0 * j0 + j1 * j1 + j2 * j2)
