"""Helpers shared by the inverse tools: input checks, the camera kernel, reflectance bases and the alternating
least-squares fixed point (used by :func:`estimate_reflectance` and :func:`remove_interreflections`)."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from .._checks import broadcast_shapes
from ..camera.sensor import Camera
from ..errors import ShapeError, ValueRangeError
from ..formfactors.operator import FormFactors
from ..layers.interreflection import Interreflection
from ..solver.api import solve

__all__ = [
    "alternating",
    "basis_parts",
    "camera_kernel",
    "check_facets",
    "check_form_factors",
    "e0_from",
    "fmatmul",
    "observed_from",
    "rel_residual",
    "safe_div",
]


def check_form_factors(form_factors: Any) -> FormFactors:
    """``form_factors`` if it is a :class:`FormFactors`, else ``TypeError``."""
    if not isinstance(form_factors, FormFactors):
        raise TypeError(f"form_factors must be a FormFactors; got {type(form_factors).__name__}")
    return form_factors


def check_facets(t: Any, name: str, n: int, last: int | None, what: str) -> Tensor:
    """``t`` if it is a finite floating tensor ``[..., n, last]`` (``what`` names the shape), else a typed error."""
    if not isinstance(t, Tensor) or not t.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor {what}; got {type(t).__name__}")
    if t.ndim < 2 or t.shape[-2] != n or (last is not None and t.shape[-1] != last):
        raise ShapeError(
            f"{name} must have shape {what} with F = {n}"
            + (f", last = {last}" if last else "")
            + f"; got {list(t.shape)}"
        )
    if not bool(torch.isfinite(t).all()):
        raise ValueRangeError(f"{name} must be finite; got NaN or inf")
    return t


def safe_div(num: Tensor, den: Tensor) -> Tensor:
    """``num / den`` where ``den > 0``, else 0."""
    ok = den > 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def fmatmul(ff: FormFactors, x: Tensor) -> Tensor:
    """``F x`` in the dtype of ``x``."""
    return ff.to(x.dtype).matmul(x) if ff.dtype != x.dtype else ff.matmul(x)


def camera_kernel(camera: Camera, like: Tensor) -> Tensor:
    """``K [C, L] = C(λ) Δλ / π`` so that ``rgb = (r ⊙ E) @ Kᵀ``."""
    return (camera.sensitivities * camera.weights / math.pi).to(device=like.device, dtype=like.dtype)


def basis_parts(basis: Any, like: Tensor) -> tuple[Tensor, Tensor, str]:
    """``(mean [L], components [K, L], space)`` of a reflectance basis, like ``like``."""
    mean, comps = getattr(basis, "mean", None), getattr(basis, "components", None)
    if not isinstance(mean, Tensor) or not isinstance(comps, Tensor):
        raise TypeError(
            "basis must expose tensors `mean` [L] and `components` [K, L] (ReflectanceBasis, RGBToSpectrum); got "
            f"{type(basis).__name__}"
        )
    return mean.to(like), comps.to(like), getattr(basis, "space", "linear")


def alternating(
    ff: FormFactors,
    camera: Camera,
    observed: Tensor,
    E0: Tensor,
    mean: Tensor,
    comps: Tensor,
    *,
    bounces: int | None,
    max_iter: int,
    tol: float | None,
) -> tuple[Tensor, Tensor, int, bool]:
    """Fixed point: least-squares coefficients for fixed E, then E = solve(F, R, E0)."""
    if tol is None:
        tol = 1e-9 if observed.dtype == torch.float64 else 1e-5
    kern = camera_kernel(camera, observed)  # [C, L]
    shape = broadcast_shapes(observed.shape[:-1], E0.shape[:-1])
    obs = observed.expand(*shape, observed.shape[-1])
    E = E0.expand(*shape, E0.shape[-1])
    r_prev: Tensor | None = None
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        ke = kern * E[..., None, :]  # [..., F, C, L]
        A = ke @ comps.T  # [..., F, C, K]
        b = obs - ke @ mean  # [..., F, C]
        c = torch.linalg.lstsq(A, b[..., None], driver="gelsd" if A.device.type == "cpu" else None).solution[..., 0]
        r = (mean + c @ comps).clamp(0.0, 1.0)
        if bounces == 1:
            converged = True
            break
        if r_prev is not None and float((r - r_prev).abs().max()) <= tol:
            converged = True
            break
        r_prev = r
        if bounces is None:
            # E ← E0 + F (r ⊙ E): the radiosity r ⊙ E already matches the observation through the camera, so this
            # converges much faster than re-solving with the current r (same fixed point, E = E0 + F R E)
            E = E0 + fmatmul(ff, r * E)
        else:
            E = solve(ff, r, E0, bounces=bounces, tol=max(0.1 * tol, 1e-14)).expand(*shape, E0.shape[-1])
    return r, c, it, converged


def observed_from(model: Interreflection, observed: Tensor) -> Tensor:
    """Observed camera RGB ``[..., F, C]``, checked against the model."""
    return check_facets(observed, "observed", model.num_facets, model.camera.num_channels, "[..., F, C]")


def e0_from(model: Interreflection, illuminant: Tensor | None, E0: Tensor | None) -> Tensor:
    """``E0 [..., F, L]`` from exactly one of an illuminant spectrum (through the model's light) and ``E0``."""
    if (illuminant is None) == (E0 is None):
        raise ValueError("give exactly one of illuminant (a spectrum [..., L]) and E0 ([..., F, L])")
    if E0 is not None:
        return check_facets(E0, "E0", model.num_facets, model.num_wavelengths, "[..., F, L]")
    return model.direct(illuminant)


def rel_residual(pred: Tensor, obs: Tensor) -> float:
    """Relative residual ``‖pred − obs‖ / ‖obs‖``."""
    return float((pred - obs).norm() / obs.norm().clamp_min(1e-300))
