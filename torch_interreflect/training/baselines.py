"""Classic statistics-based illuminant estimators on linear camera-RGB images ``[B, 3, H, W]``.

All return unit-norm illuminant estimates ``[B, 3]`` and ignore pixels where ``mask`` is False (e.g. the
background, which is black in generated images and so changes none of them anyway):

- :func:`grey_world` (Buchsbaum 1980): the mean colour is grey, ``ê ∝ mean(I)``.
- :func:`white_patch` (Land's max-RGB): the brightest response per channel is white, ``ê ∝ max(I)`` (or a high
  percentile, more robust to noise).
- :func:`grey_edge` (van de Weijer et al. 2007): the mean edge is grey, ``ê ∝ (Σ |∇(G_σ * I)|^p)^{1/p}``.
  ``p = 1, σ = 1`` is the usual first-order Grey-Edge; ``p → ∞`` gives max-edge.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import ShapeError

__all__ = ["BASELINES", "grey_edge", "grey_world", "white_patch"]


def _check(image: Tensor, mask: Tensor | None) -> Tensor:
    if not isinstance(image, Tensor) or image.ndim != 4 or image.shape[1] != 3:
        raise ShapeError(f"image must be a tensor [B, 3, H, W]; got {getattr(image, 'shape', type(image).__name__)}")
    if mask is None:
        return torch.ones(image.shape[0], 1, *image.shape[2:], dtype=torch.bool, device=image.device)
    m = mask.reshape(mask.shape[0], 1, *mask.shape[-2:]) if mask.ndim in (3, 4) else None
    if m is None or m.shape[0] != image.shape[0] or m.shape[2:] != image.shape[2:]:
        raise ShapeError(f"mask must be [B, H, W] or [B, 1, H, W] matching the image; got {list(mask.shape)}")
    return m.bool()


def _unit(x: Tensor) -> Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def grey_world(image: Tensor, mask: Tensor | None = None) -> Tensor:
    """Grey-World estimate: the (masked) mean colour, normalised.

    Args:
        image: Linear camera RGB. Shape ``[B, 3, H, W]``.
        mask: Pixels to use. Shape ``[B, H, W]`` or ``[B, 1, H, W]`` (default all).

    Returns:
        Unit-norm illuminant estimates. Shape ``[B, 3]``.

    Example:
        >>> import torch
        >>> from torch_interreflect.training.baselines import grey_world
        >>> grey_world(torch.tensor([1.0, 2.0, 2.0]).reshape(1, 3, 1, 1).expand(1, 3, 4, 4)).tolist()
        [[0.3333333432674408, 0.6666666865348816, 0.6666666865348816]]
    """
    m = _check(image, mask).to(image.dtype)
    return _unit((image * m).sum((2, 3)) / m.sum((2, 3)).clamp_min(1))


def white_patch(image: Tensor, mask: Tensor | None = None, *, percentile: float = 100.0) -> Tensor:
    """White-Patch (max-RGB) estimate: the per-channel maximum (or ``percentile``) of the masked pixels.

    Args:
        image: Linear camera RGB. Shape ``[B, 3, H, W]``.
        mask: Pixels to use. Shape ``[B, H, W]`` or ``[B, 1, H, W]``.
        percentile: 100 for the maximum; e.g. 99 for a robust variant.

    Returns:
        Unit-norm illuminant estimates. Shape ``[B, 3]``.
    """
    if not 0.0 < percentile <= 100.0:
        raise ValueError(f"percentile must lie in (0, 100]; got {percentile}")
    m = _check(image, mask)
    out = []
    for b in range(image.shape[0]):
        px = image[b].reshape(3, -1)[:, m[b].reshape(-1)]
        if px.shape[1] == 0:
            px = image[b].reshape(3, -1)
        out.append(px.amax(1) if percentile == 100.0 else torch.quantile(px, percentile / 100.0, dim=1))
    return _unit(torch.stack(out))


def grey_edge(image: Tensor, mask: Tensor | None = None, *, p: float = 1.0, sigma: float = 1.0) -> Tensor:
    """First-order Grey-Edge estimate: the Minkowski ``p``-mean of gradient magnitudes per channel.

    The image is smoothed by a Gaussian of ``sigma`` pixels and differentiated by Sobel filters (kornia);
    ``ê_c ∝ (Σ_x |∇I_c(x)|^p)^{1/p}`` over masked pixels.

    Args:
        image: Linear camera RGB. Shape ``[B, 3, H, W]``.
        mask: Pixels to use. Shape ``[B, H, W]`` or ``[B, 1, H, W]``.
        p: Minkowski norm (≥ 1).
        sigma: Gaussian pre-smoothing in pixels (0: none).

    Returns:
        Unit-norm illuminant estimates. Shape ``[B, 3]``.
    """
    import kornia.filters

    if p < 1:
        raise ValueError(f"p must be >= 1; got {p}")
    m = _check(image, mask).to(image.dtype)
    x = image
    if sigma > 0:
        k = 2 * int(3 * sigma + 0.5) + 1
        x = kornia.filters.gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")
    grad = kornia.filters.spatial_gradient(x, mode="sobel", order=1)  # [B, 3, 2, H, W]
    mag = grad.norm(dim=2) * m
    return _unit((mag**p).sum((2, 3)).clamp_min(0) ** (1.0 / p))


#: The baselines by name, as the training report lists them.
BASELINES = {"Grey-World": grey_world, "White-Patch": white_patch, "Grey-Edge": grey_edge}
