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

from .._checks import as_real_tensor, check_finite, check_reflectance
from ..errors import SingularSystemError
from ..formfactors.operator import FormFactorOperator
from .columns import broadcast_facet_shapes, from_columns, to_columns
from .info import SolveInfo, warn_if_not_converged
from .krylov import operator_cg, operator_neumann
from .method import DEFAULT_MAX_ITER
from .plan import Stats


@dataclass
class _OpConfig:
    op: FormFactorOperator
    method: str
    tol: float
    max_iter: int
    stats: Stats


def _run(cfg: _OpConfig, r: Tensor, b: Tensor, transpose: bool, stats: Stats) -> Tensor:
    areas = cfg.op.areas
    rmax_one = (r == 1).all(0)
    if bool(rmax_one.any()) and float(cfg.op.row_sums().min()) >= 1 - math.sqrt(torch.finfo(r.dtype).eps):
        raise SingularSystemError(
            "the interreflection system (I - F R) E = E0 is singular: reflectance is 1 on every facet of a closed "
            f"scene (column {int(torch.nonzero(rmax_one)[0])}); light never leaves it. Use reflectance < 1."
        )
    core = operator_cg if cfg.method == "cg" else operator_neumann
    return core(cfg.op.matmul, areas, r, b, transpose, cfg.tol, cfg.max_iter, stats)


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
        stats = Stats()
        gam = _run(cfg, r, gx, True, stats)
        warn_if_not_converged(stats, "adjoint (backward) solve")
        grad_r = cfg.op.rmatmul(gam) * x if need_r else None
        return grad_r, (gam if need_b else None), None


def solve_operator(
    op: FormFactorOperator,
    reflectance: Tensor,
    E0: Tensor,
    *,
    bounces: int | None,
    tol: float,
    method: str,
    max_iter: int | None,
    return_info: bool,
) -> Tensor | tuple[Tensor, SolveInfo]:
    """The body of :func:`~torch_interreflect.solve` for a :class:`HierarchicalFormFactors` (validated args)."""
    if method == "dense":
        raise ValueError(
            "method='dense' needs the [F, F] matrix; an operator (HierarchicalFormFactors) supports method 'auto', "
            "'cg' or "
            "'neumann'"
        )
    method = "cg" if method == "auto" else method
    reflectance = as_real_tensor(reflectance, "reflectance")
    E0 = as_real_tensor(E0, "E0")
    dtype = op.dtype
    for name, t in (("reflectance", reflectance), ("E0", E0)):
        if t.device != op.device:
            raise ValueError(f"{name} is on {t.device} but the form factors are on {op.device}")
        if t.dtype.is_floating_point:
            dtype = torch.promote_types(dtype, t.dtype)
    if dtype != op.dtype:
        op = op.to(dtype)
    n = op.num_facets
    r, e0, shape = broadcast_facet_shapes(n, reflectance.to(dtype), E0.to(dtype))
    check_reflectance(r)
    check_finite(e0, "E0", -2)
    r_cols = to_columns(r, shape)
    b_cols = to_columns(e0, shape)
    stats = Stats()
    if bounces is not None:
        x = b_cols
        for _ in range(bounces - 1):
            x = b_cols + op.matmul(r_cols * x)
        method_used, iters = "series", bounces - 1
    else:
        cfg = _OpConfig(op=op, method=method, tol=float(tol),
                        max_iter=int(max_iter if max_iter is not None else DEFAULT_MAX_ITER[method]), stats=stats)
        x = _OperatorSolve.apply(r_cols, b_cols, cfg)
        warn_if_not_converged(stats, f"solve(method={method!r})")
        method_used, iters = method, stats.iterations
    E = from_columns(x, shape)
    if not return_info:
        return E
    with torch.no_grad():
        rd, bd, xd = r_cols.detach(), b_cols.detach(), x.detach()
        res = bd - xd + op.matmul(rd * xd)
        sa = op.areas.sqrt()[:, None]
        rn, bn = (sa * res).norm(dim=0), (sa * bd).norm(dim=0)
        rel = torch.where(bn > 0, rn / torch.where(bn > 0, bn, 1), rn)
        rho = float(op.row_sums().max()) if n else 0.0
        denom = 1 - (rd.amax(0) if n else torch.zeros_like(rn)) * rho
        bound = torch.where(denom > 0, rn / denom.clamp_min(1e-300), torch.full_like(rn, math.inf))
        bound = torch.where(rn == 0, torch.zeros_like(bound), bound)
        relb = torch.where(bn > 0, bound / torch.where(bn > 0, bn, 1), bound)
    empty = rn.numel() == 0
    info = SolveInfo(
        method=method_used,
        iterations=int(iters),
        residual=0.0 if empty else float(rel.max()),
        error_bound=0.0 if empty else float(bound.max()),
        relative_error_bound=0.0 if empty else float(relb.max()),
        converged=bool(stats.converged),
        num_components=1,
        facets_skipped=0,
        num_columns=int(bd.shape[1]),
        extra={"operator": "hierarchical", "kernel_estimated_rel_error": op.info.get("estimated_rel_error")},
    )
    return E, info
