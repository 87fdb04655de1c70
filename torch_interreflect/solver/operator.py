""":func:`~torch_interreflect.solve` for form factors given as an operator (e.g.
:class:`~torch_interreflect.HierarchicalFormFactors`).

Same system, same methods as the matrix path (conjugate gradients on the symmetric form, or the Neumann series),
but ``F`` is only applied through its product. Gradients reach the reflectance and ``E0`` through the adjoint
system (DESIGN.md §1): with ``γ = (I − R Fᵀ)⁻¹ g``, ``∂E0 = γ`` and ``∂r = (Fᵀ γ) ⊙ E`` where
``Fᵀ γ = A F (γ / A)`` (reciprocity). The operator itself gets no gradient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..formfactors.operator import FormFactorOperator
from .columns import check_closed_r1, finish_output, prepare_inputs, to_columns
from .functions import check_upstream_gradient
from .info import (
    SolveInfo,
    error_report,
    relative_bound_estimate,
    solver_error,
    warn_if_inaccurate,
    warn_if_not_converged,
)
from .krylov import bounce_series, error_tolerance, operator_cg, operator_neumann
from .method import DEFAULT_MAX_ITER
from .plan import Component, Stats, operator_component


@dataclass
class _OpConfig:
    op: FormFactorOperator
    method: str
    tol: float
    max_iter: int
    stats: Stats
    comp: Component
    kernel_tol: float


def _run(cfg: _OpConfig, r: Tensor, b: Tensor, transpose: bool, stats: Stats) -> Tensor:
    areas = cfg.op.areas
    check_closed_r1(r, cfg.comp, max(cfg.kernel_tol, math.sqrt(torch.finfo(r.dtype).eps)))
    core = operator_cg if cfg.method == "cg" else operator_neumann
    tol = error_tolerance(cfg.tol, r, float(cfg.op.row_sums().max()))
    return core(cfg.op.matmul, areas, r, b, transpose, tol, cfg.max_iter, stats)


class _OperatorSolve(torch.autograd.Function):
    """``x = (I − F R)⁻¹ b`` for ``[F, N]`` columns with ``F`` an operator; adjoint backward (module docstring)."""

    @staticmethod
    def forward(r: Tensor, b: Tensor, cfg: _OpConfig) -> Tensor:  # type: ignore[override]
        return _run(cfg, r.detach(), b.detach(), False, cfg.stats)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Tensor) -> None:
        r, _, cfg = inputs
        ctx.cfg = cfg
        ctx.save_for_backward(r, output)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, gx: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        r, x = ctx.saved_tensors
        cfg: _OpConfig = ctx.cfg
        need_r, need_b = ctx.needs_input_grad[:2]
        if not (need_r or need_b):
            return None, None, None
        check_upstream_gradient(gx)
        stats = Stats()
        gam = _run(cfg, r, gx, True, stats)
        warn_if_not_converged(stats, "adjoint (backward) solve")
        grad_r = cfg.op.rmatmul(gam) * x if need_r else None
        return grad_r, (gam if need_b else None), None


def solve_operator(
    op: FormFactorOperator,
    reflectance: Any,
    E0: Any,
    *,
    bounces: int | None,
    tol: float,
    method: str,
    max_iter: int | None,
    want_info: bool,
) -> tuple[Tensor, SolveInfo | None]:
    """The body of :func:`~torch_interreflect.solve` for an operator (validated options): ``(E, info or None)``.

    Dtypes and devices are handled as on the matrix path: the inputs must be on the operator's device
    (:class:`~torch_interreflect.errors.DeviceError` otherwise); the operator is cast to the promoted dtype
    (half precision computed in float32, returned in the input's dtype).
    """
    if method == "dense":
        raise ValueError(
            "method='dense' needs the [F, F] matrix; an operator (e.g. HierarchicalFormFactors) supports method "
            "'auto', 'cg' or 'neumann'"
        )
    method = "cg" if method == "auto" else method
    n = op.num_facets
    r, e0, shape, out_dtype, drop = prepare_inputs(n, op.device, reflectance, E0, op.dtype)
    if r.dtype != op.dtype:
        op = op.to(r.dtype)  # type: ignore[attr-defined]
    r_cols, b_cols = to_columns(r, shape), to_columns(e0, shape)
    comp, kernel_tol = operator_component(op)
    stats = Stats()
    if bounces is not None:
        x = bounce_series(op.matmul, r_cols, b_cols, bounces)
        method_used, iters = "series", bounces - 1
    else:
        cfg = _OpConfig(op=op, method=method, tol=float(tol), stats=stats, comp=comp, kernel_tol=kernel_tol,
                        max_iter=int(max_iter if max_iter is not None else DEFAULT_MAX_ITER[method]))
        x = _OperatorSolve.apply(r_cols, b_cols, cfg)
        warn_if_not_converged(stats, f"solve(method={method!r})")
        method_used, iters = method, stats.iterations
    rho = float(op.row_sums().max()) if n else 0.0
    info = None
    if want_info:
        rel, bound, relb = error_report(op.matmul, op.areas, r_cols, b_cols, x, comp.closure_error, rho)
        info = SolveInfo(method=method_used, iterations=int(iters), residual=rel, error_bound=bound,
                         relative_error_bound=relb, converged=bool(stats.converged), num_components=1,
                         facets_skipped=0, num_columns=int(b_cols.shape[1]),
                         extra={"operator": type(op).__name__, "kernel_closure_error": comp.closure_error,
                                "kernel_tol": kernel_tol,
                                "kernel_estimated_rel_error": getattr(op, "info", {}).get("estimated_rel_error")})
    if bounces is None:
        rmax = float(r_cols.max()) if r_cols.numel() else 0.0
        relb = info.relative_error_bound if info is not None else relative_bound_estimate(
            solver_error(method, stats, r_cols.detach(), tol, rho, n), comp.closure_error, rmax, rho)
        warn_if_inaccurate(relb, tol, out_dtype, comp.closure_error, rmax, rho, f"solve(method={method!r})",
                           stacklevel=4)
    return finish_output(x, shape, out_dtype, drop), info
