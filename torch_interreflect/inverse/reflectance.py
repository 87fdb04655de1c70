"""Reflectance from observations with known geometry and light: exact from spectral radiance
(:func:`reflectance_from_radiance`), by alternating least squares or L-BFGS from camera RGB
(:func:`estimate_reflectance`). The maths: :mod:`torch_interreflect.inverse`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from .._checks import broadcast_shapes
from ..camera.facet_rgb import facet_rgb
from ..errors import ValueRangeError
from ..formfactors.operator import FormFactors
from ..layers.interreflection import Interreflection
from ..layers.reflectance import RGBToSpectrum
from ..solver.api import radiance, solve
from ._common import (
    alternating,
    basis_parts,
    check_facets,
    check_form_factors,
    e0_from,
    fmatmul,
    observed_from,
    rel_residual,
    safe_div,
)

__all__ = ["ReflectanceEstimate", "estimate_reflectance", "reflectance_from_radiance"]


def reflectance_from_radiance(form_factors: FormFactors, radiance: Tensor, E0: Tensor) -> Tensor:
    """Exact reflectance from observed spectral radiance: ``R = B / (E0 + F B)`` with ``B = π L``.

    Facets with zero irradiance ``E0 + F B`` get reflectance 0 (undetermined). Differentiable.

    Args:
        form_factors: The scene's form factors ``[F, F]``.
        radiance: Observed radiance in W·sr⁻¹·m⁻²·nm⁻¹ of every facet. Shape ``[..., F, L]``.
        E0: Direct irradiance in W·m⁻²·nm⁻¹, broadcastable. Shape ``[..., F, L]``.

    Returns:
        Reflectance. Shape ``[..., F, L]``.

    Raises:
        ShapeError, ValueRangeError: bad shapes, non-finite or negative values.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.solver import solve, radiance
        >>> from torch_interreflect.inverse import reflectance_from_radiance
        >>> K = ti.form_factors(ti.scenes.v_groove(45.0, divisions=2))
        >>> r = torch.rand(8, 31, dtype=torch.float64); E0 = torch.ones(8, 31, dtype=torch.float64)
        >>> L = radiance(solve(K.to(torch.float64), r, E0), r)
        >>> bool(torch.allclose(reflectance_from_radiance(K, L, E0), r))
        True
    """
    ff = check_form_factors(form_factors)
    n = ff.num_facets
    radiance = check_facets(radiance, "radiance", n, None, "[..., F, L]")
    E0 = check_facets(E0, "E0", n, None, "[..., F, L]")
    if bool((radiance.detach() < 0).any()) or bool((E0.detach() < 0).any()):
        raise ValueRangeError("radiance and E0 must be non-negative")
    B = math.pi * radiance
    return safe_div(B, E0 + fmatmul(ff, B))


@dataclass
class ReflectanceEstimate:
    """Result of :func:`estimate_reflectance`.

    Attributes:
        reflectance: Recovered reflectance ``[..., F, L]`` in [0, 1].
        coefficients: Basis coefficients ``[..., F, K]`` (None for spectral observations).
        iterations: Alternating iterations (or L-BFGS steps) used.
        residual: Relative RMS RGB (or radiance) residual of the re-rendered estimate.
        converged: Whether the fixed point / optimiser met its tolerance.
    """

    reflectance: Tensor
    coefficients: Tensor | None
    iterations: int
    residual: float
    converged: bool
    info: dict[str, Any] = field(default_factory=dict)


def estimate_reflectance(
    model: Interreflection | FormFactors,
    observed: Tensor,
    illuminant: Tensor | None = None,
    *,
    E0: Tensor | None = None,
    basis: Any = None,
    bounces: int | str | None = "model",
    method: str = "alternating",
    max_iter: int = 100,
    tol: float | None = None,
    steps: int = 50,
) -> ReflectanceEstimate:
    """Recover per-facet reflectance from observations, with known geometry and light.

    Two cases (module docstring):

    - ``model`` is a :class:`~torch_interreflect.FormFactors` and ``observed`` is spectral radiance
      ``[..., F, L]``: exact, ``R = B / (E0 + F B)`` (``E0`` required).
    - ``model`` is an :class:`~torch_interreflect.layers.Interreflection` and ``observed`` camera RGB
      ``[..., F, 3]``: reflectance in a linear ``basis`` by alternating least squares (``method="alternating"``)
      or, in addition, L-BFGS through the renderer (``method="gradient"``; works with non-linear bases).

    Args:
        model: Form factors (spectral case) or the renderer (RGB case: its form factors, camera, light).
        observed: Radiance ``[..., F, L]`` or camera RGB ``[..., F, C]`` of every facet.
        illuminant: Spectrum ``[..., L]`` turned into ``E0`` by the model's light (RGB case).
        E0: Direct irradiance ``[..., F, L]`` (instead of ``illuminant``; required in the spectral case).
        basis: Reflectance basis with ``mean [L]``, ``components [K, L]`` (and ``forward`` for the gradient
            method): :class:`~torch_interreflect.layers.ReflectanceBasis` (``space="linear"`` for alternating) or
            :class:`~torch_interreflect.layers.RGBToSpectrum` (default). ``K ≤ 3`` makes the per-facet problems
            determined.
        bounces: Interreflection model used for the inversion: ``"model"`` (the renderer's), ``None`` (infinite),
            or ``n`` (``1`` = ignore interreflection).
        method: ``"alternating"`` or ``"gradient"``.
        max_iter: Alternating iterations at most.
        tol: Stop when the reflectance changes by at most ``tol`` (alternating); default 1e-9 in float64,
            1e-5 in float32.
        steps: L-BFGS iterations (gradient).

    Returns:
        A :class:`ReflectanceEstimate`.

    Raises:
        ShapeError, ValueRangeError, TypeError: bad inputs; ValueError: unknown method, missing light.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.layers import Interreflection, RGBToSpectrum
        >>> from torch_interreflect.inverse import estimate_reflectance
        >>> wl = ti.spectral.wavelengths(dtype=torch.float64)
        >>> up = RGBToSpectrum(wl)
        >>> layer = Interreflection(ti.scenes.v_groove(45.0, divisions=2, dtype=torch.float64), wl)
        >>> r_true = up(torch.rand(8, 3, dtype=torch.float64) * 0.9)
        >>> D65 = ti.spectral.illuminant("D65", wl)
        >>> est = estimate_reflectance(layer, layer(r_true, D65), D65, basis=up)
        >>> bool((est.reflectance - r_true).abs().max() < 1e-6)
        True
    """
    if isinstance(model, FormFactors):
        if E0 is None:
            raise ValueError("the spectral case (model = FormFactors) needs E0 [..., F, L]")
        r = reflectance_from_radiance(model, observed, E0)
        with torch.no_grad():
            res = rel_residual(radiance(solve(model, r.clamp(0, 1), E0), r.clamp(0, 1)), observed)
        return ReflectanceEstimate(r, None, 0, res, True)
    if not isinstance(model, Interreflection):
        raise TypeError(f"model must be an Interreflection layer or FormFactors; got {type(model).__name__}")
    if method not in ("alternating", "gradient"):
        raise ValueError(f"method must be 'alternating' or 'gradient'; got {method!r}")
    obs = observed_from(model, observed)
    e0 = e0_from(model, illuminant, E0).to(obs)
    if bounces == "model":
        bounces = model.bounces
    if basis is None:
        basis = RGBToSpectrum(model.wavelengths).to(obs)
    mean, comps, space = basis_parts(basis, obs)
    ff = model.form_factors
    with torch.no_grad():
        if space == "linear":
            r, c, it, conv = alternating(
                ff, model.camera, obs.detach(), e0.detach(), mean, comps, bounces=bounces, max_iter=max_iter, tol=tol
            )
        else:  # a non-linear basis: start from the mean spectrum
            c = torch.zeros(*broadcast_shapes(obs.shape[:-1], e0.shape[:-1]), comps.shape[0]).to(obs)
            r, it, conv = basis(c), 0, False
    if method == "gradient":
        c = c.detach().clone().requires_grad_(True)
        opt = torch.optim.LBFGS(
            [c], lr=1.0, max_iter=steps, tolerance_grad=1e-12, tolerance_change=1e-14, line_search_fn="strong_wolfe"
        )
        scale = obs.detach().pow(2).sum().clamp_min(1e-300)

        def closure() -> Tensor:
            opt.zero_grad()
            pred = facet_rgb(ff, basis(c), e0, model.camera, bounces=bounces, tol=model.tol)
            loss = (pred - obs.detach()).pow(2).sum() / scale
            loss.backward()
            return loss

        opt.step(closure)
        c = c.detach()
        r = basis(c).detach()
        it = int(opt.state[opt._params[0]].get("n_iter", steps))
        conv = True
    with torch.no_grad():
        pred = facet_rgb(ff, r, e0, model.camera, bounces=bounces, tol=model.tol)
    return ReflectanceEstimate(r, c, it, rel_residual(pred, obs), conv, {"method": method, "bounces": bounces})
