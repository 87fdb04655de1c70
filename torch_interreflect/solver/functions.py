"""The autograd Functions of the solve: the adjoint backward (DESIGN.md §1) and ``F @ y`` for sparse ``F``."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from ..errors import ValueRangeError
from .columns import solve_columns
from .info import warn_if_not_converged
from .plan import SolvePlan, Stats

__all__ = ["CsrMatmul", "InterreflectSolve", "SolveConfig", "apply_solve", "apply_solve_keeping",
           "check_upstream_gradient", "matmul",
           "outer_on_pattern", "transposed_matmul"]



@dataclass
class SolveConfig:
    plan: SolvePlan
    areas: Tensor
    method: str
    tol: float
    max_iter: int
    transpose: bool
    keep: bool
    stats: Stats
    #: dense factors of an earlier solve with the same reflectance columns (:func:`apply_solve_keeping`), reused
    given: list[Tensor] | None = None

    def adjoint(self) -> SolveConfig:
        return replace(self, transpose=not self.transpose, keep=False, stats=Stats(), given=None)


class InterreflectSolve(torch.autograd.Function):
    """``x = (I − F R)⁻¹ b`` (or ``(I − R Fᵀ)⁻¹ b`` when transposed) for ``[F, N]`` columns.

    Gradients (adjoint method, DESIGN.md §1), with ``γ`` the solution of the transposed system for the
    upstream gradient ``g``:

    - not transposed, ``γ = (I − R Fᵀ)⁻¹ g``: ``∂b = γ``, ``∂r = (Fᵀ γ) ⊙ x``, ``∂F = γ (r ⊙ x)ᵀ``;
    - transposed, ``γ = (I − F R)⁻¹ g``: ``∂b = γ``, ``∂r = γ ⊙ (Fᵀ x)``, ``∂F = x (r ⊙ γ)ᵀ``.

    ``∂F`` is summed over columns; for a sparse ``F`` it is computed on the stored entries only. When a graph
    is requested for the backward (double backward), the adjoint solve calls this Function again.
    """

    @staticmethod
    def forward(matrix: Tensor, r: Tensor, b: Tensor, cfg: SolveConfig) -> tuple[Tensor, ...]:  # type: ignore[override]
        x, factors = solve_columns(
            matrix.detach(),
            cfg.plan,
            cfg.areas,
            r.detach(),
            b.detach(),
            transpose=cfg.transpose,
            method=cfg.method,
            tol=cfg.tol,
            max_iter=cfg.max_iter,
            factors=cfg.given,
            keep_factors=cfg.keep,
            stats=cfg.stats,
        )
        return (x, *factors)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: tuple[Tensor, ...]) -> None:
        matrix, r, _, cfg = inputs
        x, *factors = output
        ctx.cfg = replace(cfg, given=None)  # the factors it used are saved below; the config need not hold them
        if factors:
            ctx.mark_non_differentiable(*factors)
        ctx.save_for_backward(matrix, r, x, *factors)

    @staticmethod
    def backward(ctx: Any, gx: Tensor, *_: Any) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        matrix, r, x, *factors = ctx.saved_tensors
        cfg: SolveConfig = ctx.cfg
        need_f, need_r, need_b = ctx.needs_input_grad[:3]
        if not (need_f or need_r or need_b):
            return None, None, None, None
        check_upstream_gradient(gx)
        acfg = cfg.adjoint()
        if torch.is_grad_enabled():  # create_graph=True: the adjoint solve itself must be differentiable
            gam = apply_solve(matrix, r, gx, acfg)
        else:
            gam, _ = solve_columns(
                matrix.detach(),
                cfg.plan,
                cfg.areas,
                r.detach(),
                gx.detach(),
                transpose=acfg.transpose,
                method=cfg.method,
                tol=cfg.tol,
                max_iter=cfg.max_iter,
                factors=factors or None,
                stats=acfg.stats,
            )
        warn_if_not_converged(acfg.stats, "adjoint (backward) solve")
        grad_f = grad_r = None
        if not cfg.transpose:
            if need_r:
                grad_r = transposed_matmul(matrix, gam) * x
            if need_f:
                grad_f = outer_on_pattern(matrix, gam, r * x)
        else:
            if need_r:
                grad_r = gam * transposed_matmul(matrix, x)
            if need_f:
                grad_f = outer_on_pattern(matrix, x, r * gam)
        return grad_f, grad_r, (gam if need_b else None), None


def check_upstream_gradient(g: Tensor) -> None:
    """Raise :class:`ValueRangeError` when the gradient reaching the solve's backward is not finite.

    ``g`` is ``[F, N]`` (facets × flattened batch and wavelength columns).
    """
    bad = ~torch.isfinite(g)
    if bool(bad.any()):
        k = int(torch.nonzero(bad.reshape(-1))[0])
        i, j = divmod(k, g.shape[1])
        raise ValueRangeError(
            f"the upstream gradient dloss/dE reaching solve's backward is not finite: {int(bad.sum())} NaN/inf "
            f"values (first {float(g.reshape(-1)[k])} at facet {i}, column {j} of batch x wavelength). The "
            "loss or an operation between solve and the loss produced it; the solve itself is fine. Check the loss "
            "(torch.autograd.set_detect_anomaly(True) finds the operation)."
        )


def apply_solve(matrix: Tensor, r: Tensor, b: Tensor, cfg: SolveConfig) -> Tensor:
    return InterreflectSolve.apply(matrix, r, b, cfg)[0]


def apply_solve_keeping(matrix: Tensor, r: Tensor, b: Tensor, cfg: SolveConfig) -> tuple[Tensor, list[Tensor]]:
    """:func:`apply_solve` and the dense factors it kept (``cfg.keep``; empty otherwise): passed as ``given`` to a
    later solve with the same matrix and reflectance columns, they save its factorisation.

    Shape:
        - ``r``, ``b``, output ``x``: ``[F, N]`` columns; factors: three tensors per component (Cholesky or LU
          factors ``[k, c, c]``, pivots, distinct-column index ``[N]``)
    """
    x, *factors = InterreflectSolve.apply(matrix, r, b, cfg)
    return x, list(factors)


def transposed_matmul(matrix: Tensor, y: Tensor) -> Tensor:
    """``Fᵀ y``."""
    if matrix.layout == torch.strided:
        return matrix.mT @ y
    return matrix.detach().t() @ y


def outer_on_pattern(matrix: Tensor, a: Tensor, c: Tensor) -> Tensor:
    """``a cᵀ`` summed over columns, dense or sampled at the stored entries of a sparse ``matrix``."""
    if matrix.layout == torch.strided:
        return a @ c.mT
    return torch.sparse.sampled_addmm(matrix.detach().to_sparse_csr(), a, c.mT, beta=0.0)


class CsrMatmul(torch.autograd.Function):
    """``F @ y`` for a sparse CSR ``F`` whose gradient lives on its stored entries only."""

    @staticmethod
    def forward(matrix: Tensor, y: Tensor) -> Tensor:  # type: ignore[override]
        return matrix.detach() @ y.detach()

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Tensor) -> None:
        ctx.save_for_backward(*inputs)

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        matrix, y = ctx.saved_tensors
        gm = outer_on_pattern(matrix, g, y) if ctx.needs_input_grad[0] else None
        gy = transposed_matmul(matrix, g) if ctx.needs_input_grad[1] else None
        return gm, gy


def matmul(matrix: Tensor, y: Tensor) -> Tensor:
    if matrix.layout == torch.strided:
        return matrix @ y
    return CsrMatmul.apply(matrix, y)
