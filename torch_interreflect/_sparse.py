"""Sparse matrices for every stage: COO entries → coalesced COO or CSR, without torch's warnings about them.

torch warns on each process's first CSR tensor ("sparse CSR support is in beta") and on COO tensors built without
an explicit invariant choice; entries built here are valid by construction, so the checks are off and the
warnings are not shown to users.
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

__all__ = ["constant_product", "sparse_matrix", "to_csr"]


def sparse_matrix(rows: Tensor, cols: Tensor, vals: Tensor, shape: tuple[int, int], dtype: torch.dtype | None,
                  ordered: bool = False) -> Tensor:
    """COO entries (duplicates summed, in the dtype of ``vals``) → CSR in ``dtype``; ``dtype=None`` keeps the
    coalesced COO.

    ``ordered``: the ``(row, col)`` pairs are already unique and sorted row-major (no sort needed).

    Shape:
        - rows, cols, vals: ``[N]``
        - output: ``shape``
    """
    coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, shape, is_coalesced=ordered,
                                  check_invariants=False)
    coo = coo if ordered else coo.coalesce()
    return coo if dtype is None else to_csr(coo).to(dtype)


def to_csr(matrix: Tensor) -> Tensor:
    """``matrix.to_sparse_csr()`` without torch's beta warning."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse CSR tensor support is in beta.*")
        return matrix.to_sparse_csr()


class _ConstantProduct(torch.autograd.Function):
    """``m @ x`` for a constant sparse ``m`` whose transpose ``mt`` is given: the backward is ``mt @ g``."""

    @staticmethod
    def forward(m: Tensor, mt: Tensor, x: Tensor) -> Tensor:  # type: ignore[override]
        return m @ x

    @staticmethod
    def setup_context(ctx: object, inputs: tuple[Tensor, Tensor, Tensor], output: Tensor) -> None:
        ctx.mt = inputs[1]  # type: ignore[attr-defined]

    @staticmethod
    def backward(ctx: object, g: Tensor) -> tuple[None, None, Tensor]:  # type: ignore[override]
        return None, None, ctx.mt @ g  # type: ignore[attr-defined]


def constant_product(m: Tensor, mt: Tensor, x: Tensor) -> Tensor:
    """``m @ x`` for a sparse ``m`` that takes no gradient, with ``mt`` its transpose in CSR (built once by the
    caller).

    The same values and gradient in ``x`` as ``m @ x``, whose backward converts ``mᵀ`` to CSR at every call (a
    sort of the entries: 3.5× the cost of the product for a ``[785, 144]`` gather matrix with 28 % of its entries
    stored). Differentiable twice (the backward is an ordinary product in ``g``).

    Shape:
        - m: ``[R, N]``, mt: ``[N, R]``, x: ``[N, C]``
        - output: ``[R, C]``
    """
    if m.requires_grad or mt.requires_grad:
        raise ValueError("constant_product passes no gradient to m; use m @ x for a matrix that requires grad")
    return _ConstantProduct.apply(m, mt, x)
