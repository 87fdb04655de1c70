"""Form factors of the leaves across refinement steps: the rows of leaves that did not change are reused.

A refinement step keeps some leaves (first, in their old order) and replaces the others by their children. An
entry ``F_ij`` depends only on the two facets (and, for pairs that a third facet could block, on the geometry
around them, which refinement does not change: children tile their parent), so the block of kept × kept pairs
is copied from the previous kernel and only the pairs with at least one new leaf are integrated
(:func:`torch_interreflect.formfactors.quadrature.pair_values`, the same rule and tolerance as
:func:`~torch_interreflect.formfactors.form_factors`).
"""

from __future__ import annotations

import time

import torch
from torch import Tensor

from ..formfactors.operator import FormFactors
from ..formfactors.quadrature import assemble, form_factors, pair_entries, pair_values
from ..geometry._polygon import facing_matrix, plane_eps
from ..geometry.scene import Scene

__all__ = ["leaf_kernel"]


def _old_block(K: FormFactors, kept: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entries ``(rows, cols, values)`` of ``K`` between kept leaves, renumbered ``0..m-1`` (float64, CPU)."""
    if K.is_sparse:
        coo = K.matrix.detach().to_sparse_coo().coalesce()
        r, c = coo.indices()
        v = coo.values()
    else:
        dense = K.matrix.detach()
        r, c = torch.nonzero(dense, as_tuple=True)
        v = dense[r, c]
    r, c, v = r.cpu(), c.cpu(), v.detach().to(torch.float64).cpu()
    new_of = torch.full((K.num_facets,), -1, dtype=torch.int64)
    new_of[kept.cpu()] = torch.arange(kept.numel())
    keep = (new_of[r] >= 0) & (new_of[c] >= 0)
    return new_of[r[keep]], new_of[c[keep]], v[keep]


def leaf_kernel(
    scene: Scene, tol: float, previous: FormFactors | None = None, kept: Tensor | None = None
) -> FormFactors:
    """Form factors of ``scene`` (the leaves), reusing ``previous`` for the pairs of its first ``len(kept)``
    leaves, which are ``previous``'s leaves ``kept``.

    Args:
        scene: The leaves (``n`` facets); the first ``m = len(kept)`` are unchanged leaves of the previous step.
        tol: Per-entry quadrature tolerance.
        previous: Form factors of the previous step's leaves (``None``: compute everything).
        kept: Indices into ``previous`` of the first ``m`` leaves. Shape ``[m]``.

    Returns:
        :class:`~torch_interreflect.FormFactors` of the ``n`` leaves; ``info`` has ``occluded_facets [n]``,
        ``pairs`` (integrated now) and ``reused_entries``.
    """
    if previous is None or kept is None or kept.numel() == 0:
        return form_factors(scene, quadrature_tol=tol, progress=False)
    t0 = time.perf_counter()
    sc = scene.to(torch.float64).to("cpu")
    n, m = sc.num_facets, int(kept.numel())
    eps = plane_eps(scene)
    front = facing_matrix(sc.corners, sc.normals, sc.centroids, eps)
    mutual = torch.triu(front & front.T, diagonal=1)
    mutual[:m, :m] = False  # the kept × kept block comes from the previous step
    iu, ju = torch.nonzero(mutual, as_tuple=True)
    info: dict = {"method": "quadrature", "pairs": int(iu.numel())}
    r0, c0, v0 = _old_block(previous, kept)
    occ = torch.zeros(n, dtype=torch.bool)
    old_occ = previous.info.get("occluded_facets")
    if isinstance(old_occ, Tensor):
        occ[:m] = old_occ.cpu()[kept.cpu()]
    rows, cols, vals = [r0], [c0], [v0]
    if iu.numel():
        dom, tgt, value, need, vis = pair_values(sc, iu, ju, "auto", tol, None, 3, 1 << 18, False, info, eps)
        occ[dom[need]] = True
        occ[tgt[need]] = True
        info["rays"] = vis.rays if vis is not None else 0
        for part, new in zip((rows, cols, vals), pair_entries(sc.areas, dom, tgt, value), strict=True):
            part.append(new)
    r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    dtype, dev = scene.dtype, scene.device
    matrix, layout = assemble(r, c, v, n, "auto", dtype)
    info.update(
        occluded_facets=occ,
        reused_entries=int(v0.numel()),
        quadrature_tol=tol,
        layout=layout,
        nnz=int(r.numel()),
        seconds=time.perf_counter() - t0,
    )
    return FormFactors(matrix.to(dev), scene.areas.detach().to(dtype), info)
