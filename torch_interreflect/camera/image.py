"""Image-space operations on ``[B, 3, H, W]`` linear camera RGB, from kornia where kornia has them.

:func:`to_srgb` (``kornia.color.linear_rgb_to_rgb``), :func:`blur` (``kornia.filters.gaussian_blur2d``),
:func:`white_balance` (a division), :func:`add_noise` (shot and read noise; not in kornia), :func:`to_lab` and
:func:`delta_e` (``kornia.color.rgb_to_lab``, CIE 1976 ΔE).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import ShapeError, ValueRangeError

__all__ = ["add_noise", "blur", "delta_e", "to_lab", "to_srgb", "white_balance"]



def _check_image(image: Tensor, name: str = "image") -> None:
    if not isinstance(image, Tensor) or image.ndim != 4 or image.shape[1] != 3:
        raise ShapeError(f"{name} must be a tensor [B, 3, H, W]; got {getattr(image, 'shape', type(image).__name__)}")


def to_srgb(image: Tensor, *, exposure: float | Tensor = 1.0) -> Tensor:
    """Linear RGB → display sRGB in [0, 1]: ``linear_rgb_to_rgb(clamp(exposure · image, 0, 1))`` (kornia).

    Args:
        image: Linear RGB (e.g. white-balanced camera RGB). Shape ``[B, 3, H, W]``.
        exposure: Multiplier applied first (e.g. ``1 / percentile``), number or ``[B, 1, 1, 1]``.

    Returns:
        sRGB-encoded image in [0, 1]. Shape ``[B, 3, H, W]``.

    Example:
        >>> from torch_interreflect.camera import to_srgb
        >>> round(float(to_srgb(torch.full((1, 3, 1, 1), 0.18))[0, 0]), 3)
        0.461
    """
    import kornia.color

    _check_image(image)
    return kornia.color.linear_rgb_to_rgb((image * exposure).clamp(0.0, 1.0))


def blur(image: Tensor, sigma: float, *, kernel_size: int | None = None) -> Tensor:
    """Optical blur: a Gaussian point-spread function of ``sigma`` pixels (``kornia.filters.gaussian_blur2d``).

    Args:
        image: Shape ``[B, C, H, W]``.
        sigma: Standard deviation in pixels (> 0).
        kernel_size: Odd kernel size; default ``2·ceil(3σ) + 1``.

    Returns:
        Blurred image (reflect padding). Shape ``[B, C, H, W]``.

    Example:
        >>> from torch_interreflect.camera import blur
        >>> blur(torch.rand(1, 3, 8, 8), 1.0).shape
        torch.Size([1, 3, 8, 8])
    """
    import kornia.filters

    if not (isinstance(sigma, (int, float)) and sigma > 0 and math.isfinite(sigma)):
        raise ValueRangeError(f"sigma must be a positive number of pixels; got {sigma!r}")
    k = kernel_size if kernel_size is not None else 2 * math.ceil(3 * sigma) + 1
    if k % 2 == 0 or k < 1:
        raise ValueError(f"kernel_size must be a positive odd integer; got {k}")
    return kornia.filters.gaussian_blur2d(image, (k, k), (float(sigma), float(sigma)), border_type="reflect")


def white_balance(image: Tensor, white: Tensor) -> Tensor:
    """Divide each channel by the camera RGB of the illuminant (von Kries), normalised to the green channel.

    ``white`` is typically ``camera(illuminant_spd[None] / π)``: the response to a perfect white diffuser.
    After balancing, a grey surface lit by that illuminant has equal channels.

    Args:
        image: Shape ``[B, 3, H, W]``.
        white: Camera RGB of the illuminant. Shape ``[3]`` or ``[B, 3]``, positive.

    Returns:
        Balanced image. Shape ``[B, 3, H, W]``.

    Raises:
        ValueRangeError: non-positive ``white``.

    Example:
        >>> from torch_interreflect.camera import white_balance
        >>> img = torch.tensor([2.0, 4.0, 1.0]).reshape(1, 3, 1, 1)
        >>> white_balance(img, torch.tensor([2.0, 4.0, 1.0])).flatten().tolist()
        [4.0, 4.0, 4.0]
    """
    _check_image(image)
    if not isinstance(white, Tensor) or white.shape[-1] != 3 or white.ndim > 2:
        raise ShapeError(f"white must be a tensor [3] or [B, 3]; got {getattr(white, 'shape', white)}")
    if bool((white.detach() <= 0).any()):
        raise ValueRangeError(f"white must be positive in every channel; got {white.detach().tolist()}")
    gain = white[..., 1:2] / white
    return image * gain.reshape(-1, 3, 1, 1).to(image)


def add_noise(
    image: Tensor,
    *,
    shot: float = 0.0,
    read: float = 0.0,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Shot-and-read sensor noise (heteroscedastic Gaussian): ``y = x + sqrt(shot · max(x, 0) + read²) · ε``.

    The Gaussian approximation of Poisson photon noise (variance proportional to the signal, gain ``shot``) plus
    signal-independent read noise (standard deviation ``read``), ``ε ~ N(0, 1)``. Differentiable in ``image``
    (reparametrised). kornia has only signal-independent noise, hence this function.

    Args:
        image: Linear RGB. Shape ``[B, C, H, W]``.
        shot: Shot-noise gain (variance per unit signal), ≥ 0.
        read: Read-noise standard deviation, ≥ 0.
        generator: Optional random generator (reproducibility).

    Returns:
        Noisy image. Shape ``[B, C, H, W]``.

    Example:
        >>> from torch_interreflect.camera import add_noise
        >>> g = torch.Generator().manual_seed(0)
        >>> add_noise(torch.ones(1, 3, 4, 4), shot=1e-4, read=1e-3, generator=g).shape
        torch.Size([1, 3, 4, 4])
    """
    for name, v in (("shot", shot), ("read", read)):
        if not (isinstance(v, (int, float)) and v >= 0 and math.isfinite(v)):
            raise ValueRangeError(f"{name} must be a finite number >= 0; got {v!r}")
    eps = torch.randn(image.shape, generator=generator, dtype=image.dtype, device=image.device)
    return image + torch.sqrt(shot * image.clamp_min(0) + read**2) * eps


def to_lab(image: Tensor) -> Tensor:
    """CIE L*a*b* (D65) of linear RGB treated as linear sRGB: ``rgb_to_lab(linear_rgb_to_rgb(clamp(x)))`` (kornia).

    White-balance camera RGB first (:func:`white_balance`) so that white maps near ``L* = 100, a* = b* = 0``.

    Args:
        image: Linear RGB in [0, 1] (clamped). Shape ``[B, 3, H, W]``.

    Returns:
        ``L*`` in [0, 100], ``a*``, ``b*``. Shape ``[B, 3, H, W]``.

    Example:
        >>> from torch_interreflect.camera import to_lab
        >>> round(float(to_lab(torch.ones(1, 3, 1, 1))[0, 0]), 3)
        100.0
    """
    import kornia.color

    _check_image(image)
    return kornia.color.rgb_to_lab(kornia.color.linear_rgb_to_rgb(image.clamp(0.0, 1.0)))


def delta_e(image: Tensor, reference: Tensor) -> Tensor:
    """Per-pixel CIE 1976 colour difference ``ΔE*ab = |Lab(image) − Lab(reference)|`` (see :func:`to_lab`).

    Args:
        image: Linear RGB. Shape ``[B, 3, H, W]``.
        reference: Linear RGB. Shape ``[B, 3, H, W]``.

    Returns:
        ΔE per pixel. Shape ``[B, H, W]``.

    Example:
        >>> from torch_interreflect.camera import delta_e
        >>> float(delta_e(torch.ones(1, 3, 2, 2), torch.ones(1, 3, 2, 2)).max())
        0.0
    """
    _check_image(reference, "reference")
    return (to_lab(image) - to_lab(reference)).norm(dim=1)
