"""The camera stage: spectral radiance → camera RGB (sensor), facets → images (projection), image-space ops.

- :mod:`.facet_rgb`: :func:`facet_rgb`, facet camera RGB in one call (solve → radiance → sensor).
- :mod:`.sensor`: :func:`spectral_to_rgb` and the :class:`Camera` module (paper eq. 61).
- :mod:`.projection`: :func:`look_at`, :func:`project` → :class:`Projection` (pixel × facet coverage),
  :func:`render_image`.
- :mod:`.image`: :func:`to_srgb`, :func:`blur`, :func:`white_balance`, :func:`add_noise`, :func:`to_lab`,
  :func:`delta_e` (kornia).
"""

from .facet_rgb import facet_rgb
from .image import add_noise, blur, delta_e, to_lab, to_srgb, white_balance
from .projection import Projection, look_at, project, render_image
from .sensor import Camera, spectral_to_rgb

__all__ = [
    "Camera",
    "Projection",
    "add_noise",
    "blur",
    "delta_e",
    "facet_rgb",
    "look_at",
    "project",
    "render_image",
    "spectral_to_rgb",
    "to_lab",
    "to_srgb",
    "white_balance",
]
