"""The dense column solver: one factorisation of ``I − F R`` per distinct reflectance column, shared by every
right-hand side with that column."""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import SingularSystemError
from .plan import Stats

__all__ = ["LU_CHUNK_BYTES", "dense_solve"]



LU_CHUNK_BYTES = 256 * 2**20


def dense_solve(
    f: Tensor,
    r: Tensor,
    b: Tensor,
    transpose: bool,
    given: list[Tensor] | None,
    keep: bool,
    stats: Stats,
) -> tuple[Tensor, list[Tensor]]:
    """Batched LU: one ``[c, c]`` factorisation per distinct reflectance column, all RHS sharing it at once."""
    if f.layout != torch.strided:
        f = f.to_dense()
    c, n = b.shape
    if given is not None and given[0].numel():
        lu_all, piv_all, inv = given
        uniq = None
        k = int(lu_all.shape[0])
    else:
        lu_all = piv_all = None
        uniq, inv = torch.unique(r, dim=1, return_inverse=True)
        k = int(uniq.shape[1])
    stats.distinct_columns += k
    # pack the right-hand sides by distinct column: rhs[k, :, slot]
    order = torch.argsort(inv, stable=True)
    sinv = inv[order]
    counts = torch.bincount(inv, minlength=k)
    starts = counts.cumsum(0) - counts
    slot = torch.arange(n, device=b.device) - starts[sinv]
    width = int(counts.max())
    rhs = b.new_zeros(k, c, width)
    rhs[sinv, :, slot] = b[:, order].T
    bytes_one = c * c * b.element_size()
    chunk = max(1, LU_CHUNK_BYTES // max(bytes_one, 1))
    keep = keep and k <= chunk
    sols = []
    lus, pivs = [], []
    for k0 in range(0, k, chunk):
        k1 = min(k, k0 + chunk)
        if lu_all is not None and piv_all is not None:
            lu, piv = lu_all[k0:k1], piv_all[k0:k1]
        else:
            m = f.unsqueeze(0) * uniq[:, k0:k1].T.unsqueeze(1)  # built in place: one [k, c, c] buffer
            m.neg_().diagonal(dim1=-2, dim2=-1).add_(1)
            lu, piv, info = torch.linalg.lu_factor_ex(m)
            del m
            if bool((info > 0).any()):
                raise SingularSystemError(
                    "the interreflection system (I - F R) E = E0 is singular (zero pivot in the LU "
                    "factorisation): reflectance 1 in a closed group of facets?"
                )
            if keep:
                lus.append(lu)
                pivs.append(piv)
        sols.append(torch.linalg.lu_solve(lu, piv, rhs[k0:k1], adjoint=transpose))
    sol = torch.cat(sols) if len(sols) > 1 else sols[0]
    x = torch.empty_like(b)
    x[:, order] = sol[sinv, :, slot].T
    if not bool(torch.isfinite(x).all()):
        raise SingularSystemError(
            "the interreflection system (I - F R) E = E0 is singular or too ill-conditioned for the LU "
            "solve (non-finite result)"
        )
    kept: list[Tensor] = []
    if keep and lus:
        kept = [
            torch.cat(lus) if len(lus) > 1 else lus[0],
            torch.cat(pivs) if len(pivs) > 1 else pivs[0],
            inv,
        ]
    return x, kept
