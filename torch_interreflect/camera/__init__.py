"""The camera stage: spectral radiance → camera RGB (sensor), facets → images (projection), image-space ops.

- :mod:`.facet_rgb`: :func:`facet_rgb`, facet camera RGB in one call (solve → radiance → sensor).
- :mod:`.sensor`: :func:`spectral_to_rgb` and the :class:`Camera` module (paper eq. 61).
- :mod:`.projection`: :func:`look_at`, :func:`project` → :class:`Projection` (pixel × facet coverage),
  :func:`render_image`.
- :mod:`.view`: :class:`View` (eye, target, up, field of view, size), a hashable view.
- :mod:`.gather`: :func:`gather_operator` → :class:`Gather`, :func:`gathered_image`, :func:`gathered_radiance`
  (per-pixel final gather, or flat shading); :mod:`.fragments` (a view's sub-pixel rays grouped per pixel and
  facet) and :mod:`.point_kernel` (:func:`point_form_factors`, point-to-facet form factors with occlusion) under it.
- :mod:`.image_grad`: :func:`~.image_grad.image_gradient`, the terms (:mod:`.image_terms`) that carry a gathered
  image's gradient to the corners and a sun's direction (hit points, kernel, visibility; the edges of silhouettes
  and shadows sampled by :mod:`.edge_samples`).
- :mod:`.rendering`: :func:`render_view`, solved facets → image in one call (with the image's gradient).
- :mod:`.io`: :func:`save_image` (8-bit sRGB preview or 16-bit linear PNG).
- :mod:`.image`: :func:`to_srgb`, :func:`blur`, :func:`white_balance`, :func:`add_noise`, :func:`to_lab`,
  :func:`delta_e` (kornia).
"""

from .facet_rgb import facet_rgb
from .gather import (
    Gather,
    gather_operator,
    gathered_image,
    gathered_radiance,
    mix_direct,
    source_irradiance,
)
from .image import add_noise, blur, delta_e, to_lab, to_srgb, white_balance
from .io import save_image
from .point_kernel import point_form_factors
from .projection import Projection, look_at, project, render_image
from .rendering import render_view
from .sensor import Camera, spectral_to_rgb
from .view import View

__all__ = [
    "Camera",
    "Gather",
    "Projection",
    "View",
    "add_noise",
    "blur",
    "delta_e",
    "facet_rgb",
    "gather_operator",
    "gathered_image",
    "gathered_radiance",
    "look_at",
    "mix_direct",
    "point_form_factors",
    "project",
    "render_image",
    "render_view",
    "save_image",
    "source_irradiance",
    "spectral_to_rgb",
    "to_lab",
    "to_srgb",
    "white_balance",
]
