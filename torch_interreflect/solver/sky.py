"""The sky with its two estimates of the open part weighed per facet: on the polynomial basis
(:func:`solve_moments_sky`) and on the constant one (:func:`solve_sky`).

Where a facet's rows are ray cast and some facet's back may be in view, the sky's open part is sampled twice over by
the same rays (:func:`~torch_interreflect.light_moments.sky_estimates`): ``escape`` counts the escaping rays,
``rows`` takes ``1 − Σ_j F − b`` from the moments. With the moments' visibility error ``δ`` on a facet's row (the
part of its hemisphere wrongly taken as blocked or open), the escape estimate's answer is off by ``ρ̄ Ē δ`` (the
interreflected light alone moves) plus its own count's error, and ``rows``' by ``(ρ̄ Ē − π L) δ`` (the direct light
moves the other way), where ``ρ̄ Ē / π`` is the radiance of what the facet sees and ``L`` the sky's. The mix
``escape + β (rows − escape)`` cancels the visibility part at ``β = ρ̄ Ē / (π L)``, the ratio of the two radiances,
and is near the least-error weight wherever the visibility's error is the larger (3 × 3 visibility rays against
8 × 8 sky directions from 8 × 8 points per piece on the Cornell box). That ratio is read from a first solve with the
escape estimate: its interreflected part ``c − e0`` over ``π L Σ_j F``. Both estimates being of the same light, any
weight keeps the answer consistent; the weight only trades their errors. On the constant basis
(:func:`~torch_interreflect.sky_parts.sky_open_parts`, as :func:`~torch_interreflect.lights.sky`) the escaping rays
are counted on every facet whose row is ray cast, back faces in view or not.

Measured while building this on the Cornell box under the sky (split at contacts, cut to 0.4 m: 65 pieces, tol 1e-3,
3 × 3 visibility rays, 8² directions from 8² points; RMS over four draws against converged Mitsuba): r = 0.9 0.61 %
with the escape estimate, 0.43 % with ``rows``, 0.19 % weighed; r = 0.2 1.16 %, 5.3 %, 1.15 %.
``benchmarks/results/cornell.md`` (three other draws): 0.61 % → 0.20 % and 1.28 % → 1.26 %.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import as_real_tensor
from ..errors import ShapeError, ValueRangeError
from ..formfactors.moments import MomentFormFactors
from ..formfactors.operator import FormFactorOperator
from .api import solve
from .moments import solve_moments, solve_moments_twice

__all__ = ["sky_weights", "solve_moments_sky", "solve_sky"]


def sky_weights(form_factors: MomentFormFactors, c: Tensor, e0: Tensor, radiance: Tensor) -> Tensor:
    """The weight of ``rows`` per facet and wavelength: the radiance of what the facet sees over the sky's,
    ``(c − e0)[i, 0] / (π L Σ_j G[(i, 0), (j, 0)])``, within ``[0, 1]`` (0 where the facet sees no facet).

    Args:
        form_factors: The moments.
        c: A solution with the escape estimate (W·m⁻²·nm⁻¹). Shape ``[..., F, nb, L]``.
        e0: Its direct light. Shape ``[..., F, nb, L]``.
        radiance: The sky's radiance (W·m⁻²·sr⁻¹·nm⁻¹). Shape ``[..., L]`` (broadcast with ``c``'s batch).

    Returns:
        ``β``. Shape ``[..., F, 1, L]``.

    Raises:
        ShapeError: ``c`` and ``e0`` not ``[..., F, nb, L]`` of the moments.

    Shape:
        - ``c``, ``e0``: ``[..., F, nb, L]``; ``radiance``: ``[..., L]``; output ``[..., F, 1, L]``
    """
    F, nb = form_factors.num_facets, form_factors.size
    for name, t in (("c", c), ("e0", e0)):
        if t.ndim < 3 or tuple(t.shape[-3:-1]) != (F, nb):
            raise ShapeError(f"{name} must have shape [..., F, nb, L] = [..., {F}, {nb}, L]; got {list(t.shape)}")
    G = form_factors.matrix.detach().to(c.dtype).to(c.device)
    covered = G.reshape(F, nb, F, nb)[:, 0, :, 0].sum(1)  # [F]: the mean over each facet of Σ_j F(x → j)
    return _ratio((c - e0)[..., :, :1, :], covered[:, None, None], radiance[..., None, None, :])


def _ratio(seen: Tensor, covered: Tensor, radiance: Tensor) -> Tensor:
    """``seen / (π L covered)`` within [0, 1], 0 where nothing is covered (broadcast)."""
    sky = math.pi * radiance * covered
    return torch.where(sky > 0, seen / torch.where(sky > 0, sky, 1.0), 0.0).clamp(0.0, 1.0)


def solve_moments_sky(
    form_factors: MomentFormFactors,
    reflectance: Tensor,
    escape: Tensor,
    rows: Tensor,
    radiance: Tensor | float,
    *,
    tol: float = 1e-6,
    method: str = "auto",
    max_iter: int | None = None,
) -> Tensor:
    """:func:`~torch_interreflect.solver.solve_moments` under a uniform sky of radiance ``radiance``, its open part
    weighed per facet between its two estimates (module docstring): one solve with ``escape`` for the weights
    (:func:`sky_weights`), and one with the weighed light, on one factorisation (:func:`~.moments.solve_moments_twice`).

    Differentiable in ``reflectance`` and ``radiance`` (through both solves and the weights).

    Args:
        form_factors: The :class:`~torch_interreflect.formfactors.moments.MomentFormFactors` of the scene.
        reflectance: Per facet, in [0, 1]. Shape ``[..., F, L]`` or ``[..., F]`` (grey).
        escape: The sky's geometric factor with the escaping rays' count
            (:func:`~torch_interreflect.light_moments.sky_estimates`). Shape ``[F, nb]``.
        rows: The same with ``1 − Σ_j F − b`` everywhere. Shape ``[F, nb]``.
        radiance: The sky's radiance (W·m⁻²·sr⁻¹·nm⁻¹), a number or a spectrum. Shape ``[..., L]``.
        tol, method, max_iter: As for :func:`~torch_interreflect.solver.solve_moments`.

    Returns:
        ``c``, irradiance on every facet's basis (W·m⁻²·nm⁻¹): ``c[..., i, 0, :]`` is facet ``i``'s average.
        Shape ``[..., F, nb, L]``.

    Raises:
        TypeError: ``form_factors`` are not moments. ShapeError: ``escape`` and ``rows`` not both ``[F, nb]`` of the
        moments. ValueRangeError: a negative or non-finite radiance. As
        :func:`~torch_interreflect.solver.solve_moments` for the rest.

    Shape:
        - ``reflectance``: ``[..., F, L]`` or ``[..., F]``; ``radiance``: ``[..., L]``
        - output: ``[..., F, nb, L]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.formfactors import moment_form_factors
        >>> from torch_interreflect.light_moments import sky_estimates
        >>> from torch_interreflect.solver import solve_moments, solve_moments_sky
        >>> box = ti.scenes.cornell_box(light=False, dtype=torch.float64)   # open in front, blocks inside
        >>> G = moment_form_factors(box, 2, quadrature_tol=1e-4)
        >>> escape, rows = sky_estimates(box, G, sky_samples=4, sky_points=4)
        >>> r = torch.full((16,), 0.9, dtype=torch.float64)
        >>> c = solve_moments_sky(G, r, escape, rows, torch.tensor([1.0], dtype=torch.float64))
        >>> c.shape   # [F, nb, L]; c[:, 0] the facets' average irradiance
        torch.Size([16, 6, 1])
    """
    if not isinstance(form_factors, MomentFormFactors):
        raise TypeError(f"form_factors must be MomentFormFactors; got {type(form_factors).__name__}")
    F, nb = form_factors.num_facets, form_factors.size
    g_esc, g_rows = _estimates(escape, rows, (F, nb), "the sky's geometric factor per facet and basis function, "
                               "from sky_estimates")
    L_sky = _radiance(radiance)
    dtype = torch.promote_types(L_sky.dtype, form_factors.matrix.dtype)
    dtype = dtype if dtype.is_floating_point else torch.get_default_dtype()
    dev = form_factors.matrix.device
    L_sky = L_sky.to(dtype=dtype, device=dev)
    g_esc, g_rows = g_esc.to(dtype=dtype, device=dev), g_rows.to(dtype=dtype, device=dev)
    kw = {"tol": tol, "method": method, "max_iter": max_iter}
    lead = L_sky[..., None, None, :]  # [..., 1, 1, L]
    e_esc = g_esc[:, :, None] * lead
    if torch.equal(g_esc, g_rows):  # no facet where the two differ: one solve
        return solve_moments(form_factors, reflectance, e_esc, **kw)
    step = (g_rows - g_esc)[:, :, None] * lead

    def weighed(c0: Tensor) -> Tensor:  # the light with the rows' estimate weighed by β [..., F, 1, L]
        return e_esc + sky_weights(form_factors, c0, e_esc, L_sky) * step

    return solve_moments_twice(form_factors, reflectance, e_esc, weighed, **kw)[1]


def solve_sky(
    form_factors: FormFactorOperator,
    reflectance: Tensor,
    escape: Tensor,
    rows: Tensor,
    radiance: Tensor | float,
    **kwargs: object,
) -> Tensor:
    """:func:`~torch_interreflect.solve` under a uniform sky of radiance ``radiance`` on the constant basis, its open
    part weighed per facet between its two estimates (:func:`~torch_interreflect.sky_parts.sky_open_parts`), as
    :func:`solve_moments_sky` does on the polynomial basis: one solve with ``escape``, the weight
    ``β = (E − E0) / (π L Σ_j F_ij)`` per facet and wavelength, and one solve with ``π L (escape + β (rows − escape))``
    (clamped at 0).

    Gradients: to ``reflectance`` and ``radiance`` through both solves and the weights; to the geometry (form factors
    that carry the graph of the corners) through ``F`` and, as :func:`~torch_interreflect.lights.sky` does, through
    ``1 − Σ_j F_ij`` for the direct light (the estimates themselves are constants of the geometry).

    On the Cornell box under the sky (r = 0.9, the default kernel), the visibility's part of the error (against 100×
    its rays, weighed the same way) is 0.16 % of a total 7.2 % at 16 facets and 0.14 % of 4.5 % at 64, against 1.8 %
    of 7.6 % and 0.48 % of 5.0 % with the escape count alone (``benchmarks/results/visibility.md``).

    Args:
        form_factors: Form factors of the scene (``ti.form_factors``).
        reflectance: Per facet, in [0, 1]. Shape ``[..., F, L]`` or ``[..., F]``.
        escape, rows: The open part per facet, two ways. Shape ``[F]``.
        radiance: The sky's radiance (W·m⁻²·sr⁻¹·nm⁻¹). Shape ``[..., L]``.
        **kwargs: Passed to :func:`~torch_interreflect.solve` (``method``, ``tol``, ...).

    Returns:
        Irradiance ``E`` (W·m⁻²·nm⁻¹). Shape ``[..., F, L]``.

    Raises:
        ShapeError: ``escape`` or ``rows`` not ``[F]``. ValueRangeError: a negative or non-finite radiance.

    Shape:
        - ``reflectance``: ``[..., F, L]`` or ``[..., F]``; ``radiance``: ``[..., L]``; output ``[..., F, L]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.sky_parts import sky_open_parts
        >>> from torch_interreflect.solver import solve_sky
        >>> box = ti.scenes.cornell_box(light=False, dtype=torch.float64)
        >>> K = ti.form_factors(box)
        >>> escape, rows = sky_open_parts(box, K, sky_samples=4)
        >>> r, L = torch.full((16,), 0.9, dtype=torch.float64), torch.ones(1, dtype=torch.float64)
        >>> solve_sky(K, r, escape, rows, L).shape
        torch.Size([16, 1])
    """
    g_esc, g_rows = _estimates(escape, rows, (form_factors.num_facets,), "the open part per facet, from "
                               "sky_open_parts")
    L_sky = _radiance(radiance)
    row_sums = form_factors.row_sums()
    dtype = torch.promote_types(L_sky.dtype, row_sums.dtype)
    L_sky = L_sky.to(dtype=dtype, device=row_sums.device)
    live = -(row_sums - row_sums.detach()).to(dtype)[:, None]  # the derivative of 1 − Σ_j F_ij, value 0
    g_esc = g_esc.to(L_sky)[:, None] + live
    g_rows = g_rows.to(L_sky)[:, None] + live
    E0 = math.pi * g_esc * L_sky[..., None, :]
    if torch.equal(g_esc, g_rows):  # no facet where the two differ: one solve
        return solve(form_factors, reflectance, E0, **kwargs)  # type: ignore[arg-type]
    E1 = solve(form_factors, reflectance, E0, **kwargs)  # type: ignore[arg-type]
    beta = _ratio(E1 - E0, row_sums.detach().to(dtype)[:, None], L_sky[..., None, :])
    g = (g_esc + beta * (g_rows - g_esc)).clamp_min(0.0)
    return solve(form_factors, reflectance, math.pi * g * L_sky[..., None, :], **kwargs)  # type: ignore[arg-type]


def _estimates(escape: Tensor, rows: Tensor, shape: tuple[int, ...], what: str) -> tuple[Tensor, Tensor]:
    """The two estimates as real tensors, checked to have ``shape``."""
    out = as_real_tensor(escape, "escape"), as_real_tensor(rows, "rows")
    for name, g in zip(("escape", "rows"), out, strict=True):
        if tuple(g.shape) != shape:
            dims = "[F, nb]" if len(shape) == 2 else "[F]"
            raise ShapeError(f"{name} must have shape {dims} = {list(shape)} ({what}); got {list(g.shape)}")
    return out


def _radiance(radiance: Tensor | float) -> Tensor:
    """The sky's radiance as a float tensor ``[..., L]``, checked finite and non-negative."""
    L_sky = as_real_tensor(radiance, "radiance")
    L_sky = L_sky.reshape(1) if L_sky.ndim == 0 else L_sky
    if not bool(torch.isfinite(L_sky).all()) or bool((L_sky < 0).any()):
        raise ValueRangeError(f"radiance must be finite and non-negative (W·m⁻²·sr⁻¹·nm⁻¹); got values in "
                              f"[{float(L_sky.min())}, {float(L_sky.max())}]")
    return L_sky if L_sky.is_floating_point() else L_sky.to(torch.get_default_dtype())
