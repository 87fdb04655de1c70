"""The form-factor operator: the :class:`FormFactorOperator` protocol that the solver relies on, and the
:class:`FormFactors` container (the matrix ``F`` of a scene, dense or sparse), which implements it.

``F[i, j]`` is the fraction of the light leaving facet ``i`` that arrives at facet ``j`` (DESIGN.md §1). The
container also holds the facet areas (for reciprocity ``A_i F_ij = A_j F_ji`` and the symmetric form
``G = A^{1/2} F A^{-1/2}`` used by the Krylov solver).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from .._sparse import to_csr
from ..errors import ShapeError, ValueRangeError

__all__ = ["FormFactorOperator", "FormFactors"]


@runtime_checkable
class FormFactorOperator(Protocol):
    """What :func:`torch_interreflect.solve` needs of form factors: size, dtype, device, areas, ``F @ x``, row sums.

    :class:`FormFactors` (a stored matrix) and :class:`~torch_interreflect.formfactors.HierarchicalFormFactors`
    (an operator: near field plus far blocks) both implement it. The solver uses a stored ``matrix`` when the
    object has one (dense Cholesky, CG on the stored matrix, gradients for ``F``); otherwise it needs only
    ``matmul`` (CG / Neumann on the operator, gradients for reflectance and ``E0``).

    Shape:
        - areas: ``[F]`` (m²)
        - matmul: ``[F, N] → [F, N]``
        - row_sums: ``[F]``
    """

    @property
    def num_facets(self) -> int: ...

    @property
    def dtype(self) -> torch.dtype: ...

    @property
    def device(self) -> torch.device: ...

    areas: Tensor

    def matmul(self, x: Tensor) -> Tensor: ...

    def row_sums(self) -> Tensor: ...


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

    def sparsify(self, max_row_mass: float) -> FormFactors:
        """Drop the smallest entries while the dropped part of every row sums to at most ``max_row_mass``.

        An entry ``F_ij`` is dropped only together with ``F_ji``, so reciprocity (and conjugate gradients) still
        hold. The effect on the solution is bounded: with ``ρ = r_max · max_i Σ_j F_ij < 1``, dropping ``δF ≥ 0``
        changes ``E`` by at most ``max_row_mass · r_max · ‖E‖∞ / (1 − ρ)`` on every facet (max norm).

        Args:
            max_row_mass: Largest dropped sum per row, ``>= 0``.

        Returns:
            Sparse CSR form factors (detached), with ``info["dropped"]`` (fraction of the stored entries
            dropped), ``info["dropped_row_mass"]`` (the largest dropped row sum) and ``info["density"]``.

        Shape:
            - output ``.to_dense()``: ``[F, F]``

        Example:
            >>> import torch_interreflect as ti
            >>> K = ti.form_factors(ti.scenes.closed_box(divisions=4))
            >>> Ks = K.sparsify(1e-3)
            >>> Ks.info["dropped_row_mass"] <= 1e-3, Ks.nnz < K.nnz
            (True, True)
        """
        if not (isinstance(max_row_mass, (int, float)) and math.isfinite(max_row_mass) and max_row_mass >= 0):
            raise ValueRangeError(f"max_row_mass must be a finite number >= 0; got {max_row_mass!r}")
        n = self.num_facets
        coo = self.matrix.detach().to_sparse_coo().coalesce() if self.is_sparse else self.matrix.detach().to_sparse()
        coo = coo.coalesce()
        (row, col), val = coo.indices(), coo.values()
        # eligible: within each row, the smallest entries whose running sum stays under the bound
        order = torch.argsort(row.to(torch.float64) + 0.5 * val.to(torch.float64) / max(float(val.max()), 1e-300))
        r_s, v_s = row[order], val[order]
        csum = torch.cumsum(v_s.to(torch.float64), 0)
        counts = torch.bincount(r_s, minlength=n)
        first = torch.cumsum(counts, 0) - counts
        before = torch.cat([csum.new_zeros(1), csum])  # before[k]: sum of the first k sorted entries
        within = csum - before[first][r_s]
        eligible = torch.zeros_like(val, dtype=torch.bool)
        eligible[order] = within <= max_row_mass
        # drop (i, j) only if (j, i) is eligible too
        key = row * n + col
        key_t = col * n + row
        pos = torch.searchsorted(key, key_t).clamp_max(max(key.numel() - 1, 0))
        mirror = (key[pos] == key_t) & eligible[pos] if key.numel() else eligible
        drop = eligible & mirror
        dropped_mass = torch.zeros(n, dtype=torch.float64, device=val.device).index_add(
            0, row[drop], val[drop].to(torch.float64)
        )
        keep = ~drop
        mat = torch.sparse_coo_tensor(
            torch.stack([row[keep], col[keep]]), val[keep], (n, n), check_invariants=False
        ).coalesce()
        info = dict(self.info)
        info.update(
            dropped=float(drop.sum()) / max(val.numel(), 1),
            dropped_row_mass=float(dropped_mass.max()) if n else 0.0,
            density=float(keep.sum()) / max(n * n, 1),
            max_row_mass=float(max_row_mass),
        )
        info.pop("_solve_plan", None)
        csr = to_csr(mat)
        return FormFactors(csr, self.areas.detach(), info)

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
