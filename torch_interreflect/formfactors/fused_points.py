"""The compiled contour formula from single points to polygons (no quadrature rule): one pair per row, for the
per-pixel final gather (:mod:`~torch_interreflect.camera.point_kernel`) and the image gradients
(:mod:`~torch_interreflect.camera.image_grad`).

:func:`point_sums` evaluates many ``(point, polygon)`` pairs by index, without gathering; :func:`point_polygon_factors`
evaluates one polygon per point with a compiled adjoint for autograd. Both run numba loops on the CPU
(:mod:`._numba_kernels`) and :func:`~torch_interreflect.formfactors.contour.point_polygon_factor` in torch elsewhere
or with ``backend="torch"``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .compiled import launch, loops
from .contour import point_polygon_factor
from .fused import Backend, first_order_only, resolve_backend

__all__ = ["horizon_point_sums", "point_polygon_factors", "point_sums"]


def _np(t: Tensor):
    return t.detach().contiguous().numpy()


def point_sums(
    x: Tensor,
    normal: Tensor,
    rows: Tensor,
    polygon: Tensor,
    which: Tensor,
    plane: tuple[Tensor, Tensor],
    backend: Backend = "auto",
    chunk: int = 1 << 16,
) -> tuple[Tensor, Tensor]:
    """Point-to-polygon form factors over pairs ``(x[rows[n]], polygon[which[n]])``, and which side of a plane
    each point lies on.

    The compiled loop of :func:`~torch_interreflect.formfactors.contour.point_polygon_factor` over pairs, without
    gathering points or polygons per pair (one point and one polygon serve many pairs).

    Args:
        x: Points in metres. Shape ``[P, 3]``.
        normal: Unit normal at each point. Shape ``[P, 3]``.
        rows: The point of each pair (int64 in ``[0, P)``). Shape ``[N]``.
        polygon: Polygons, each on or above the tangent plane of the points paired with it, padded by repeating
            a corner. Shape ``[Q, K, 3]``.
        which: The polygon of each pair (int64 in ``[0, Q)``). Shape ``[N]``.
        plane: ``(centre [Q, 3], axis [Q, 3])``: a plane per polygon (e.g. its facet's centroid and normal).
        backend: As for :func:`group_sums`.
        chunk: Pairs per step of the torch path (bounds its temporaries).

    Returns:
        ``(factors, ahead)``: ``F(x_rows → polygon_which)`` (dimensionless, the dtype of ``x``) and whether
        ``(x_rows − centre_which)·axis_which > 0`` (bool). Shape ``[N]`` each.
    """
    centre, axis = plane
    if not resolve_backend(backend, x, normal, polygon):
        outs, aheads = [], []
        for s in range(0, rows.numel(), chunk):
            r, w = rows[s : s + chunk], which[s : s + chunk]
            outs.append(point_polygon_factor(x[r][:, None, :], normal[r], polygon[w])[:, 0])
            aheads.append(((x[r] - centre[w]) * axis[w]).sum(-1) > 0)
        if not outs:
            return x.new_zeros(0), torch.zeros(0, dtype=torch.bool, device=x.device)
        return torch.cat(outs), torch.cat(aheads)
    out = torch.empty(rows.numel(), dtype=torch.float64)
    ahead = torch.empty(rows.numel(), dtype=torch.bool)
    if rows.numel():
        d = [_np(t.double()) for t in (x, normal)]
        launch(loops().point_factors, *d, _np(rows.long()), _np(polygon.double()), _np(which.long()),
             _np(centre.double()), _np(axis.double()), out.numpy(), ahead.numpy())
    return out.to(x.dtype), ahead


def horizon_point_sums(
    x: Tensor,
    normal: Tensor,
    base: Tensor,
    rows: Tensor,
    corners: Tensor,
    which: Tensor,
    plane: tuple[Tensor, Tensor],
    eps: float,
) -> tuple[Tensor, Tensor] | None:
    """:func:`point_sums` to whole facets, each clipped at the point's horizon inside the compiled loop (no clipped
    polygons in memory); ``None`` where the compiled loop does not run (numba missing or disabled, tensors off the
    CPU, inputs that require grad): clip with :func:`~torch_interreflect.geometry._polygon.clip_polygons` and call
    :func:`point_sums`.

    Args:
        x: Points in metres. Shape ``[P, 3]``.
        normal: Unit normal at each point. Shape ``[P, 3]``.
        base: A point of each point's tangent plane (e.g. its facet's centroid). Shape ``[P, 3]``.
        rows: The point of each pair (int64 in ``[0, P)``). Shape ``[N]``.
        corners: Facet corners (a triangle's last corner repeated). Shape ``[F, 4, 3]``.
        which: The facet of each pair (int64 in ``[0, F)``). Shape ``[N]``.
        plane: ``(centre [F, 3], axis [F, 3])``: a plane per facet, as in :func:`point_sums`.
        eps: Corners within ``eps`` (metres) below the horizon count as above it.

    Returns:
        ``(factors, ahead)`` as :func:`point_sums` (float64), or ``None``.
    """
    if not resolve_backend("auto", x, normal, corners):
        return None
    centre, axis = plane
    out = torch.empty(rows.numel(), dtype=torch.float64)
    ahead = torch.empty(rows.numel(), dtype=torch.bool)
    if rows.numel():
        blocks = max(1, min(256, rows.numel() // 4096))
        launch(loops().horizon_point_factors, _np(x.double()), _np(normal.double()), _np(base.double()),
               _np(rows.long()), _np(corners.double()), _np(which.long()), _np(centre.double()), _np(axis.double()),
               float(eps), blocks, out.numpy(), ahead.numpy())
    return out, ahead


class _PointPolygon(torch.autograd.Function):
    """The compiled contour formula from points to polygons, one pair per row, with its compiled adjoint
    (gradients to the points, normals and polygon corners). First derivatives only."""

    @staticmethod
    def forward(ctx, x, normal, poly, count):  # type: ignore[override]
        out = torch.empty(x.shape[0], dtype=torch.float64)
        if x.shape[0]:
            launch(loops().point_polygon_sums, _np(x.double()), _np(normal.double()), _np(poly.double()),
                   _np(count.long()), out.numpy())
        ctx.save_for_backward(x, normal, poly, count)
        return out.to(x.dtype)

    @staticmethod
    def backward(ctx, gout):  # type: ignore[override]
        first_order_only()
        x, normal, poly, count = ctx.saved_tensors
        gx = torch.empty(x.shape, dtype=torch.float64)
        gn = torch.empty(normal.shape, dtype=torch.float64)
        gp = torch.empty(poly.shape, dtype=torch.float64)
        if x.shape[0]:
            launch(loops().point_polygon_grad, _np(x.double()), _np(normal.double()), _np(poly.double()),
                   _np(count.long()), _np(gout.double()), gx.numpy(), gn.numpy(), gp.numpy())
        return gx.to(x.dtype), gn.to(normal.dtype), gp.to(poly.dtype), None


def point_polygon_factors(x: Tensor, normal: Tensor, polygon: Tensor, backend: Backend = "auto") -> Tensor:
    """``F(x_p → polygon_p)`` per row: :func:`~torch_interreflect.formfactors.contour.point_polygon_factor` with one
    point per polygon, through the compiled loop and its compiled adjoint on the CPU (first derivatives; memory
    O(rows) under autograd), torch elsewhere or with ``backend="torch"``.

    Args:
        x: Points in metres. Shape ``[P, 3]``.
        normal: Unit normal at each point. Shape ``[P, 3]``.
        polygon: Polygons on or above the points' tangent planes, padded by repeating a corner. Shape ``[P, K, 3]``.
        backend: ``"auto"`` / ``"fused"`` (compiled where it applies) or ``"torch"``.

    Returns:
        Form factors (dimensionless), the dtype of ``x``. Shape ``[P]``.
    """
    if backend not in ("auto", "fused", "torch"):
        raise ValueError(f"backend must be 'auto', 'fused' or 'torch'; got {backend!r}")
    compiled = backend != "torch" and loops() is not None and all(t.device.type == "cpu" for t in (x, normal, polygon))
    if not compiled:
        return point_polygon_factor(x[:, None, :], normal, polygon)[:, 0]
    count = torch.full((x.shape[0],), polygon.shape[1], dtype=torch.int64)
    return _PointPolygon.apply(x, normal, polygon, count)
