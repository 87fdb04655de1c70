"""Deterministic low-discrepancy sampling shared by the ray-cast estimates (visibility between facets, the
hemisphere fractions of the sky): sequence steps and per-pair seeds. (Sample counts are checked by
:func:`torch_interreflect._checks.check_count`.)"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["KRONECKER_STEP", "R2_STEP", "pair_seeds"]

#: The R2 sequence's step (Roberts 2018): ``1/φ₂, 1/φ₂²`` with ``φ₂`` the plastic number; consecutive points fill the
#: unit square with low discrepancy. (The compiled loops in ``_numba_visibility`` hold the same numbers.)
R2_STEP = (0.7548776662466927, 0.5698402909980532)
#: Steps of a second Kronecker sequence (√2 − 1, √3 − 1), for a rotation that must not follow an R2 offset.
KRONECKER_STEP = (0.41421356237309515, 0.7320508075688772)


def pair_seeds(dom: Tensor, tgt: Tensor) -> Tensor:
    """A rotation ``[P, 2]`` in ``[0, 1)`` per pair ``(dom, tgt)`` ``[P]`` (a hash of the two facet indices), so that
    neighbouring pairs draw different samples; deterministic."""
    d, t = dom.to(torch.int64), tgt.to(torch.int64)
    seed = torch.stack([(d * 2654435761 + t * 2246822519) % 1048573, (d * 3266489917 + t * 668265263) % 1048571], -1)
    return seed.to(torch.float64) / 1048576.0
