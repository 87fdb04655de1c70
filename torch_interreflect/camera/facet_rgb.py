"""Facet camera RGB in one call: ``camera(R · solve(F, R, E0) / π)`` (solve → radiance → sensor)."""

from __future__ import annotations

from torch import Tensor

from ..formfactors.operator import FormFactors
from ..solver.api import radiance, solve
from .sensor import Camera

__all__ = ["facet_rgb"]



def facet_rgb(
    form_factors: FormFactors,
    reflectance: Tensor,
    E0: Tensor,
    camera: Camera,
    *,
    bounces: int | None = None,
    tol: float = 1e-6,
    method: str = "auto",
) -> Tensor:
    """Camera RGB of a scene after ``bounces`` reflections: ``camera(R · solve(F, R, E0) / π)``.

    Differentiable in ``reflectance``, ``E0``, the form-factor values and the camera's sensitivities.

    Args:
        form_factors: The scene's form factors.
        reflectance: In [0, 1]. Shape ``[..., F, L]`` (or ``[..., F]`` grey).
        E0: Direct irradiance in W·m⁻²·nm⁻¹. Shape ``[..., F, L]`` broadcastable with the reflectance.
        camera: The camera (its grid must have ``L`` wavelengths).
        bounces: ``None`` (infinite) or ``n ≥ 1`` (see :func:`torch_interreflect.solve`).
        tol: Solver tolerance.
        method: Solver method.

    Returns:
        Camera responses. Shape ``[..., F, C]``.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.camera import facet_rgb
        >>> scene = ti.scenes.v_groove(60.0, divisions=2)
        >>> wl = ti.spectral.wavelengths()
        >>> rgb = facet_rgb(ti.form_factors(scene), torch.full((8, 31), 0.5), torch.ones(8, 31),
        ...                 ti.Camera.from_colour("Nikon 5100 (NPL)", wl))
        >>> rgb.shape
        torch.Size([8, 3])
    """
    E = solve(form_factors, reflectance, E0, bounces=bounces, tol=tol, method=method)
    return camera(radiance(E, reflectance))
