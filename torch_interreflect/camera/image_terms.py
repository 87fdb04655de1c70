"""The gradient terms of a gathered image, and how they enter it.

:func:`~torch_interreflect.camera.image_grad.image_gradient` builds an :class:`ImageGradient` (zero-valued tensors
whose graph reaches the corners and a sun's direction); :func:`~torch_interreflect.camera.gather.gathered_radiance`
adds them to an image with :func:`edge_pixels` and :func:`shadow_pixels`. Kept apart from both so that the image
functions do not depend on how the terms are built.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["ImageGradient", "edge_pixels", "shadow_pixels"]


@dataclass
class ImageGradient:
    """The zero-valued terms that carry a gathered image's gradient (built by :func:`image_gradient`).

    Attributes:
        gather: ``V (F(x → j) − F(x → j).detach())`` at the gather points. Sparse COO ``[Kp, F]`` (``None`` for flat
            shading).
        weights: Sparse ``[K, Kp]`` that carry gather points to fragments (``stride > 1``), or ``None`` (``Kp = K``).
        direct: The same for ``g0`` per fragment. ``[K]`` (``None`` when nothing moves it).
        edge_pixel: The pixel (``row · W + column``) of each edge sample. ``[S]`` int64.
        edge_weight: ``Δl (v − v.detach())``, the sample's length times its normal speed in the image. ``[S]``.
        side_fragment: The fragment on side ``a`` (row 0) and ``b`` (row 1) of each sample, ``-1`` if none. ``[2, S]``.
        side_facet: The facet hit from its front on each side, ``-1`` for the background or a back. ``[2, S]``.
        shadow_pixel, shadow_facet: Pixel and receiving facet of each sample of a sun's shadow edges. ``[S2]``.
        shadow_weight: Its ``Δl (v − v.detach())`` times the facet's cosine and ``lit_a − lit_b``. ``[S2]``.
    """

    gather: Tensor | None
    weights: Tensor | None
    direct: Tensor | None
    edge_pixel: Tensor
    edge_weight: Tensor
    side_fragment: Tensor
    side_facet: Tensor
    shadow_pixel: Tensor
    shadow_weight: Tensor
    shadow_facet: Tensor


def shadow_pixels(grad: ImageGradient, reflectance: Tensor, spd: Tensor, pixels: int) -> Tensor:
    """The sun's shadow-edge term of a gathered radiance image: zero-valued ``[..., H·W, L]``.

    Args:
        grad: The :class:`ImageGradient`.
        reflectance: ``[..., F, L]``. spd: the sun's spectrum ``[..., L]``. pixels: ``H · W``.
    """
    r = reflectance.index_select(-2, grad.shadow_facet).detach()
    contrib = r * spd.detach()[..., None, :] * grad.shadow_weight.to(r.dtype)[:, None] / torch.pi
    out = torch.zeros(*contrib.shape[:-2], pixels, contrib.shape[-1], dtype=contrib.dtype, device=contrib.device)
    return out.index_add(-2, grad.shadow_pixel, contrib)


def edge_pixels(grad: ImageGradient, fragment_values: Tensor | None, facet_values: Tensor, pixels: int) -> Tensor:
    """The edge term of an image: zero-valued per pixel, carrying ``∫ (f_a − f_b) v dl`` to the geometry.

    Args:
        grad: The :class:`ImageGradient`.
        fragment_values: Radiance (or any per-channel value) per fragment, ``[..., K, C]``; ``None`` for flat
            shading (the facets' values then stand on both sides).
        facet_values: Per facet, ``[..., F, C]`` (the value on a side with no fragment of that facet).
        pixels: ``H · W``.

    Returns:
        ``[..., H·W, C]``.
    """
    sides = []
    for row in range(2):
        facet, frag = grad.side_facet[row], grad.side_fragment[row]
        val = facet_values.index_select(-2, facet.clamp_min(0)) * (facet >= 0).to(facet_values.dtype)[:, None]
        if fragment_values is not None:
            fv = fragment_values.index_select(-2, frag.clamp_min(0))
            val, fv = torch.broadcast_tensors(val, fv)
            val = torch.where((frag >= 0)[:, None], fv, val)
        sides.append(val.detach())
    a, b = torch.broadcast_tensors(*sides)
    contrib = (a - b) * grad.edge_weight.to(a.dtype)[:, None]
    out = torch.zeros(*contrib.shape[:-2], pixels, contrib.shape[-1], dtype=contrib.dtype, device=contrib.device)
    return out.index_add(-2, grad.edge_pixel, contrib)
