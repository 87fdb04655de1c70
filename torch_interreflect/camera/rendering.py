"""From solved facets to an image in one call: the cached gather operator of a view, the image, and its gradient
to the geometry when the corners or a sun direction require grad."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..geometry.scene import Scene
from .gather import gather_operator, gathered_image, gathered_radiance
from .image_grad import image_gradient
from .sensor import Camera
from .view import View

__all__ = ["render_view"]


def render_view(scene: Scene, reflectance: Tensor, irradiance: Tensor, spd: Tensor | None, camera: Camera | None,
                view: View, light: str | Tensor | Sequence[float] = "uniform", *, shading: str = "gather",
                supersample: int = 3, samples: int = 4, geometry: Scene | None = None,
                edge_supersample: int | None = None) -> Tensor:
    """One call from solved facets to an image: the cached :func:`gather_operator`, then the image.

    ``reflectance``, ``irradiance`` (solved for ``E0 = g ⊗ spd``, ``g`` the light's geometric factor), ``spd`` and
    ``shading`` as for :func:`gathered_radiance`; ``view``, ``light``, ``supersample``, ``edge_supersample`` (e.g.
    16: a path tracer's pixel integral, at a fraction of uniform 16 × 16 rays) and ``samples`` as for
    :func:`gather_operator`. With a :class:`~torch_interreflect.camera.Camera` the result is camera RGB
    ``[..., C, H, W]`` (:func:`gathered_image`), with ``camera=None`` spectral radiance ``[..., L, H, W]``.

    When ``scene``'s corners (or ``geometry``'s: the same facets carrying the graph, e.g. moved leaves) or a light
    direction require grad, the image also passes gradients to them
    (:func:`~torch_interreflect.camera.image_grad.image_gradient`; values unchanged).
    """
    op = gather_operator(scene, view, light, supersample=supersample, samples=samples, shading=shading,
                         edge_supersample=edge_supersample)
    moving = geometry if geometry is not None else scene
    light_grad = isinstance(light, Tensor) and light.requires_grad
    gradient = None
    if torch.is_grad_enabled() and (moving.corners.requires_grad or light_grad):
        gradient = image_gradient(op, moving, light, shading=shading)
    if camera is None:
        return gathered_radiance(op, reflectance, irradiance, spd, shading=shading, gradient=gradient)
    return gathered_image(op, reflectance, irradiance, spd, camera, shading=shading, gradient=gradient)
