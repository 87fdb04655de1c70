"""The :class:`FormFactors` container: the form-factor matrix ``F`` of a scene, dense or sparse.

``F[i, j]`` is the fraction of the light leaving facet ``i`` that arrives at facet ``j`` (DESIGN.md §1). The
container also holds the facet areas (for reciprocity ``A_i F_ij = A_j F_ji`` and the symmetric form
``G = A^{1/2} F A^{-1/2}`` used by the Krylov solver).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from .errors import ShapeError

__all__ = ["FormFactors"]


@dataclass
class FormFactors:
    """Form factors of a scene.

    Attributes:
        matrix: ``F_ij``, dense ``[F, F]`` or a sparse CSR tensor of that shape. May require grad.
        areas: Facet areas in m², ``[F]``.
        info: What was computed and how (method, quadrature points, rays cast, times, ...).

    Shape:
        - matrix: ``[F, F]``
        - areas: ``[F]``

    Example:
        >>> import torch_interreflect as ti
        >>> K = ti.form_factors(ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1))
        >>> round(float(K.to_dense()[0, 1]), 5)
        0.20004
    """

    matrix: Tensor
    areas: Tensor
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = self.matrix
        if m.ndim != 2 or m.shape[0] != m.shape[1]:
            raise ShapeError(f"form-factor matrix must be square [F, F]; got {list(m.shape)}")
        if self.areas.shape != (m.shape[0],):
            raise ShapeError(f"areas must have shape [{m.shape[0]}]; got {list(self.areas.shape)}")

    # ------------------------------------------------------------------ properties
    @property
    def num_facets(self) -> int:
        return int(self.matrix.shape[0])

    @property
    def is_sparse(self) -> bool:
        return self.matrix.layout != torch.strided

    @property
    def dtype(self) -> torch.dtype:
        return self.matrix.dtype

    @property
    def device(self) -> torch.device:
        return self.matrix.device

    @property
    def nnz(self) -> int:
        """Number of stored nonzero entries."""
        if self.is_sparse:
            return int(self.matrix.values().numel())
        return int((self.matrix != 0).sum())

    def to_dense(self) -> Tensor:
        """The matrix as a dense tensor ``[F, F]`` (differentiable)."""
        return self.matrix.to_dense() if self.is_sparse else self.matrix

    def to_sparse(self) -> FormFactors:
        """The same form factors stored as a sparse CSR matrix."""
        if self.is_sparse:
            return self
        return FormFactors(self.matrix.to_sparse_csr(), self.areas, dict(self.info))

    def row_sums(self) -> Tensor:
        """``Σ_j F_ij`` per facet ``[F]``: 1 in a closed scene, less where part of the hemisphere is open."""
        if self.is_sparse:
            ones = torch.ones(self.num_facets, 1, dtype=self.dtype, device=self.device)
            return (self.matrix @ ones).reshape(-1)
        return self.matrix.sum(dim=1)

    def matmul(self, x: Tensor) -> Tensor:
        """``F @ x`` for ``x`` of shape ``[..., F, K]`` (one product with all columns)."""
        if x.shape[-2] != self.num_facets:
            raise ShapeError(f"x must have {self.num_facets} facets on dim -2; got {list(x.shape)}")
        if self.is_sparse:
            lead = x.shape[:-2]
            cols = x.movedim(-2, 0).reshape(self.num_facets, -1)
            out = self.matrix @ cols
            return out.reshape(self.num_facets, *lead, x.shape[-1]).movedim(0, -2)
        return self.matrix @ x

    def to(self, *args: Any, **kwargs: Any) -> FormFactors:
        """Move/cast like :meth:`torch.Tensor.to`."""
        return FormFactors(self.matrix.to(*args, **kwargs), self.areas.to(*args, **kwargs), dict(self.info))

    def __repr__(self) -> str:
        layout = "sparse CSR" if self.is_sparse else "dense"
        return (
            f"FormFactors(num_facets={self.num_facets}, {layout}, nnz={self.nnz}, dtype={self.dtype}, "
            f"device={self.device})"
        )
