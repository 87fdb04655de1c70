"""Solving the Galerkin system on a polynomial basis per facet: ``(I − G R) c = e0`` for every batch element and
wavelength (:func:`solve_moments`), with the moments of
:func:`~torch_interreflect.formfactors.moment_form_factors` and the light of
:func:`~torch_interreflect.light_moments.light_moments`.

``R`` repeats each facet's reflectance over its basis functions (reflectance is constant over a facet). The system
has the structure of the piecewise-constant one, blockwise reciprocal with every facet's area repeated, so it goes
through the same column driver and adjoint (:class:`~torch_interreflect.solver.functions.InterreflectSolve`):
Cholesky of the symmetric positive definite form per distinct reflectance column (``"dense"``), or conjugate
gradients on it (``"cg"``). Unlike ``F``, ``G`` and ``e0`` have negative entries (the basis functions beyond the
constant change sign), so the checks of :func:`~torch_interreflect.solve` that rest on ``F ≥ 0`` do not apply.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from .._checks import as_real_tensor, broadcast_shapes, check_finite, check_reflectance, check_same_device
from ..errors import ShapeError
from ..formfactors.moments import MomentFormFactors
from .columns import from_columns, to_columns
from .functions import SolveConfig, apply_solve, apply_solve_keeping
from .info import warn_if_not_converged
from .method import DEFAULT_MAX_ITER, choose_method
from .plan import Component, SolvePlan, Stats

__all__ = ["DENSE_MAX_UNKNOWNS", "facet_averages", "solve_moments", "solve_moments_twice"]

#: ``method="auto"`` uses CG above this many unknowns (facets × basis functions); below, the solver's cost model
#: (:func:`~torch_interreflect.solver.method.choose_method`) picks dense or CG.
DENSE_MAX_UNKNOWNS = 6000


def _plan(K: MomentFormFactors, matrix: Tensor) -> SolvePlan:
    """The plan of the whole moment matrix as one component (no isolated facets are split off: a facet that sees
    nothing keeps ``c = e0``, which the solve gives anyway)."""
    cached = K.info.get("_moment_plan")
    if isinstance(cached, SolvePlan) and cached.key == (id(matrix), matrix._version):
        return cached
    n = int(matrix.shape[0])
    nb = K.size
    rows = matrix.detach()[::nb, ::nb].sum(1) if n else matrix.new_zeros(0)
    rs = float(rows.max()) if n else 0.0
    tol = float(K.info.get("quadrature_tol", 1e-6))
    comp = Component(index=None, size=n, row_min=float(rows.min()) if n else 1.0,
                     leak=float((K.areas * (1 - rows)).sum() / K.areas.sum()) if n else 1.0,
                     closure_error=max(tol, math.sqrt(max(n, 1)) * torch.finfo(matrix.dtype).eps))
    plan = SolvePlan(key=(id(matrix), matrix._version), num_facets=n, is_sparse=False, nnz=n * n, components=[comp],
                     isolated=0, row_sums=rows.repeat_interleave(nb), max_row_sum=rs, reciprocal=True,
                     reciprocity_error=0.0, worst_pair=(0, 0), kernel_tol=tol, closure_error=comp.closure_error)
    K.info["_moment_plan"] = plan
    return plan


@dataclass
class _System:
    """A checked system in columns: the detached matrix, the reflectance and right-hand-side columns, the solve's
    configuration, and the output's ``[..., F·nb, L]`` shape."""

    matrix: Tensor
    r_cols: Tensor
    b_cols: Tensor
    cfg: SolveConfig
    shape: torch.Size
    nb: int

    def coefficients(self, x: Tensor) -> Tensor:
        """``c [..., F, nb, L]`` from solution columns."""
        return from_columns(x, self.shape).unflatten(-2, (self.shape[-2] // self.nb, self.nb))


def _check_options(tol: float, method: str, max_iter: int | None) -> None:
    if method not in ("auto", "dense", "cg"):
        raise ValueError(f"method must be 'auto', 'dense' or 'cg'; got {method!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive finite number; got {tol!r}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ValueError(f"max_iter must be None or an integer >= 1; got {max_iter!r}")


def _system(form_factors: MomentFormFactors, reflectance: Tensor, E0: Tensor, tol: float, method: str,
            max_iter: int | None, keep: bool = False) -> _System:
    """Check the inputs of :func:`solve_moments` and put them in columns (``keep``: keep the dense factors)."""
    if not isinstance(form_factors, MomentFormFactors):
        raise TypeError(f"form_factors must be MomentFormFactors; got {type(form_factors).__name__} (for form "
                        "factors of degree 0 use torch_interreflect.solve)")
    _check_options(tol, method, max_iter)
    F, nb = form_factors.num_facets, form_factors.size
    r = as_real_tensor(reflectance, "reflectance")
    e0 = as_real_tensor(E0, "E0")
    matrix = form_factors.matrix
    check_same_device(matrix.device, "the moments", reflectance=r, E0=e0)
    if e0.ndim < 3 or tuple(e0.shape[-3:-1]) != (F, nb):
        raise ShapeError(f"E0 must have shape [..., F, nb, L] = [..., {F}, {nb}, L] (moments per facet and basis "
                         f"function); got {list(e0.shape)}")
    grey = r.ndim >= 1 and r.shape[-1] == F and (r.ndim < 2 or r.shape[-2] != F)
    r = r.unsqueeze(-1) if grey else r
    if r.ndim < 2 or r.shape[-2] != F:
        raise ShapeError(f"reflectance must have shape [..., F] or [..., F, L] with F = {F}; got "
                         f"{list(reflectance.shape)}")
    dtype = torch.promote_types(torch.promote_types(matrix.dtype, r.dtype), e0.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    r, e0 = r.to(dtype), e0.to(dtype)
    check_reflectance(r)
    check_finite(e0.flatten(-2), "E0", -2)
    lead = broadcast_shapes(r.shape[:-2], e0.shape[:-3])
    L = max(int(r.shape[-1]), int(e0.shape[-1]))
    shape = torch.Size([*lead, F * nb, L])
    r_rep = r.repeat_interleave(nb, dim=-2)  # [..., F·nb, L]
    try:
        r_cols, b_cols = to_columns(r_rep, shape), to_columns(e0.flatten(-3, -2), shape)
    except RuntimeError as exc:
        raise ShapeError(f"reflectance {list(r.shape)} and E0 {list(e0.shape)} do not broadcast") from exc
    mat = matrix.to(dtype)
    plan = _plan(form_factors, mat)
    if method == "auto":  # the solver's cost model (many distinct reflectance columns favour CG), CG when large
        method = choose_method(plan, r_cols, float(tol)) if F * nb <= DENSE_MAX_UNKNOWNS else "cg"
    need_grad = torch.is_grad_enabled() and (r.requires_grad or e0.requires_grad)
    iters = int(max_iter if max_iter is not None else DEFAULT_MAX_ITER.get(method, 1))
    cfg = SolveConfig(plan=plan, areas=form_factors.areas.detach().to(dtype).repeat_interleave(nb), method=method,
                      tol=float(tol), max_iter=iters, transpose=False,
                      keep=bool((need_grad or keep) and method == "dense"), stats=Stats())
    return _System(mat.detach(), r_cols, b_cols, cfg, shape, nb)


def solve_moments(
    form_factors: MomentFormFactors,
    reflectance: Tensor,
    E0: Tensor,
    *,
    tol: float = 1e-6,
    method: str = "auto",
    max_iter: int | None = None,
) -> Tensor:
    """The coefficients ``c`` of irradiance on every facet's basis: ``(I − G R) c = e0``.

    Differentiable in ``reflectance`` and ``E0`` (adjoint solves, as :func:`torch_interreflect.solve`); the moments
    themselves are constants of the geometry.

    Args:
        form_factors: The :class:`~torch_interreflect.formfactors.moments.MomentFormFactors` of the scene.
        reflectance: Per facet, in [0, 1], constant over each facet. Shape ``[..., F, L]`` or ``[..., F]`` (grey).
        E0: The direct light's moments (W·m⁻²·nm⁻¹), e.g. ``light_moments(...)[:, :, None] * spectrum``. Shape
            ``[..., F, nb, L]``.
        tol: Relative error of the iterative method (``"cg"``); the dense one is direct.
        method: ``"auto"`` (the solver's cost model up to :data:`DENSE_MAX_UNKNOWNS` unknowns, CG above), ``"dense"`` or
            ``"cg"``.
        max_iter: Most CG iterations (default: the solver's).

    Returns:
        ``c`` in the promoted dtype of the inputs. ``c[..., i, 0, :]`` is facet ``i``'s average irradiance
        (:func:`facet_averages`). Shape ``[..., F, nb, L]``.

    Raises:
        ShapeError: shapes that do not match the moments. ValueRangeError: reflectance outside [0, 1], non-finite
        light.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.formfactors import moment_form_factors
        >>> from torch_interreflect.light_moments import light_moments
        >>> from torch_interreflect.solver.moments import solve_moments
        >>> box = ti.scenes.closed_box(divisions=2, dtype=torch.float64)
        >>> G = moment_form_factors(box, 2)
        >>> c = solve_moments(G, torch.full((24,), 0.5, dtype=torch.float64), light_moments(box, G)[..., None])
        >>> round(float(c[0, 0, 0]), 4), float(c[..., 1:, :].abs().max()) < 1e-4   # E0 / (1 − r) = 2
        (2.0, True)
    """
    sys = _system(form_factors, reflectance, E0, tol, method, max_iter)
    x = apply_solve(sys.matrix, sys.r_cols, sys.b_cols, sys.cfg)
    warn_if_not_converged(sys.cfg.stats, f"solve_moments(method={sys.cfg.method!r})")
    return sys.coefficients(x)


def solve_moments_twice(
    form_factors: MomentFormFactors,
    reflectance: Tensor,
    E0: Tensor,
    then: Callable[[Tensor], Tensor],
    *,
    tol: float = 1e-6,
    method: str = "auto",
    max_iter: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Two solves of one system, the second's light made from the first's answer: ``c₁ = (I − G R)⁻¹ e0`` and
    ``c₂ = (I − G R)⁻¹ then(c₁)``, on one dense factorisation per distinct reflectance column (the second solve
    reuses the first's; CG solves twice).

    Differentiable as :func:`solve_moments`, through both solves and ``then``.

    Args:
        form_factors, reflectance, E0, tol, method, max_iter: As for :func:`solve_moments`.
        then: The second solve's light from ``c₁`` (W·m⁻²·nm⁻¹), shaped as ``c₁`` (a light of another shape, or of
            a wider dtype, is solved afresh, as :func:`solve_moments` would).

    Returns:
        ``(c₁, c₂)``. Shape ``[..., F, nb, L]`` each.

    Raises:
        As :func:`solve_moments`, for either solve.

    Shape:
        - ``reflectance``: ``[..., F, L]`` or ``[..., F]``; ``E0`` and ``then(c₁)``: ``[..., F, nb, L]``
        - outputs: ``[..., F, nb, L]`` each

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.formfactors import moment_form_factors
        >>> from torch_interreflect.light_moments import light_moments
        >>> from torch_interreflect.solver.moments import solve_moments, solve_moments_twice
        >>> box = ti.scenes.closed_box(divisions=2, dtype=torch.float64)
        >>> G = moment_form_factors(box, 2)
        >>> r = torch.full((24,), 0.5, dtype=torch.float64)
        >>> e0 = light_moments(box, G)[..., None]
        >>> c1, c2 = solve_moments_twice(G, r, e0, lambda c: e0 + 0.1 * c)
        >>> bool(torch.allclose(c2, solve_moments(G, r, e0 + 0.1 * c1)))
        True
    """
    first = _system(form_factors, reflectance, E0, tol, method, max_iter, keep=True)
    x, factors = apply_solve_keeping(first.matrix, first.r_cols, first.b_cols, first.cfg)
    warn_if_not_converged(first.cfg.stats, f"solve_moments_twice(method={first.cfg.method!r}), first solve")
    c1 = first.coefficients(x)
    e1 = as_real_tensor(then(c1), "then(c1)")
    check_same_device(first.matrix.device, "the moments", **{"then(c1)": e1})
    if (tuple(e1.shape) != tuple(c1.shape) or torch.promote_types(x.dtype, e1.dtype) != x.dtype or not factors
            or not factors[0].numel()):  # another shape or a wider dtype: what two solve_moments would give
        return c1, solve_moments(form_factors, reflectance, e1, tol=tol, method=method, max_iter=max_iter)
    e1 = e1.to(x.dtype)
    check_finite(e1.flatten(-2), "then(c1)", -2)
    need_grad = torch.is_grad_enabled() and (first.r_cols.requires_grad or e1.requires_grad)
    cfg = replace(first.cfg, keep=need_grad, stats=Stats(), given=factors)
    x2 = apply_solve(first.matrix, first.r_cols, to_columns(e1.flatten(-3, -2), first.shape), cfg)
    warn_if_not_converged(cfg.stats, f"solve_moments_twice(method={cfg.method!r}), second solve")
    return c1, first.coefficients(x2)


def facet_averages(coefficients: Tensor) -> Tensor:
    """Facet averages ``[..., F, L]`` from coefficients ``[..., F, nb, L]`` (the constant basis function's)."""
    return coefficients[..., 0, :]
