"""Checks of a computed kernel: row sums within their stated tolerance (overlapping facets), and the warning for
meshes whose reflecting sides face away from each other."""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor

from ..errors import GeometryError, GeometryWarning
from ..geometry._polygon import facing_matrix
from ..geometry.scene import Scene

__all__ = ["OCCLUDED_ROW_SLACK", "ROW_SUM_SLACK", "check_row_sums", "check_sums", "warn_if_wrong_side"]

#: A row may exceed 1 by this many times ``quadrature_tol`` (the quadrature's error on a closed row: measured
#: below 1e-8 at the default 1e-6).
ROW_SUM_SLACK = 10.0


#: A row with ray-cast visibility may exceed 1 by this much (estimated visibility: up to 0.84 % measured on the
#: Cornell box and the room at the default ``visibility_samples``; duplicated surfaces give 40-60 %).
OCCLUDED_ROW_SLACK = 0.05


def check_row_sums(
    rows: Tensor, vals: Tensor, F: int, quadrature_tol: float, method: str, occlusion: Any, occluded: Any
) -> float:
    """The largest row sum of ``F`` (float64); ``GeometryError`` when a row exceeds 1 beyond the kernel's tolerance.

    Not checked for ``method="monte_carlo"`` (a row counts first hits of its rays: it cannot exceed 1) nor for
    ``occlusion=False`` (facets hidden behind others are counted: rows may exceed 1 by design).
    """
    if rows.numel() == 0:
        return 0.0
    sums = torch.zeros(F, dtype=torch.float64).index_add_(0, rows, vals.detach())
    return check_sums(sums, quadrature_tol, method, occlusion, occluded)


def check_sums(sums: Tensor, quadrature_tol: float, method: str, occlusion: Any, occluded: Any) -> float:
    """:func:`check_row_sums` for row sums already summed (float64 ``[F]``)."""
    F = sums.numel()
    if F == 0:
        return 0.0
    if method != "quadrature" or occlusion is False:
        return float(sums.max())
    limit = torch.full((F,), 1.0 + max(ROW_SUM_SLACK * quadrature_tol, 1e-12), dtype=torch.float64)
    if isinstance(occluded, Tensor):
        limit[occluded] = 1.0 + OCCLUDED_ROW_SLACK
    bad = torch.nonzero(sums > limit).reshape(-1)
    if bad.numel():
        worst = int(bad[torch.argmax(sums[bad] - limit[bad])])
        raise GeometryError(
            f"form-factor rows must sum to at most 1; got {float(sums[worst]):.6g} at facet {worst} ({bad.numel()} "
            f"rows above their tolerance, here 1 + {float(limit[worst]) - 1:.1e}). The scene probably holds "
            "overlapping or intersecting facets (the same surface counted twice); build it with "
            "Scene(..., duplicates='error') to name coincident ones, or 'drop' to remove them"
        )
    return float(sums.max())


def warn_if_wrong_side(sc: Scene, eps: float) -> None:
    """Warn when no pair exchanges light but the facets' back sides would (normals out of a concave mesh)."""
    if sc.num_facets < 2:
        return
    back = facing_matrix(sc.corners, -sc.normals, sc.centroids, eps)
    if bool((back & back.T).fill_diagonal_(False).any()):
        warnings.warn(
            f"no pair of the scene's {sc.num_facets} facets can exchange light: every facet faces away from the "
            "others, but their back sides face each other (normals pointing out of a concave mesh, e.g. trimesh's "
            "outward normals of a bowl or a room). The form factors are all zero. If the inside should reflect, "
            "build the scene with Scene.from_trimesh(mesh, side='inside') (or reverse the facets' corner order)",
            GeometryWarning,
            stacklevel=5,
        )
