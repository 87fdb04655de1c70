"""Writing images: an 8-bit sRGB preview or a 16-bit linear PNG, through kornia's image I/O (``kornia_rs``)."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from ..errors import ShapeError, ValueRangeError
from .image import to_srgb

__all__ = ["save_image"]


def save_image(path: str | Path, image: Tensor, exposure: float = 1.0, srgb: bool = True) -> Path:
    """Save a linear RGB (or grey) image as PNG (or JPEG / TIFF for 8-bit sRGB).

    ``srgb=True``: ``exposure · image`` clipped to [0, 1], sRGB-encoded (:func:`~torch_interreflect.camera.to_srgb`)
    and rounded to 8 bits: a preview for eyes. ``srgb=False``: ``exposure · image`` clipped to [0, 1] and stored
    *linear* in 16 bits (``round(65535 · v)``, PNG or TIFF), for data: read it back with
    ``kornia.io.load_image(path, ImageLoadType.UNCHANGED) / 65535``.

    Args:
        path: File name; the extension picks the format (``.png``; also ``.jpg``/``.tif`` for 8 bits, ``.tif`` for
            16). Missing parent folders are created.
        image: Linear camera RGB or grey. Shape ``[3, H, W]``, ``[1, H, W]``, ``[H, W]`` or ``[1, C, H, W]``.
        exposure: Multiplier applied before clipping (e.g. ``0.9 / percentile_99``).
        srgb: 8-bit sRGB preview (default) or 16-bit linear.

    Returns:
        The path written.

    Raises:
        ShapeError: an image of another shape (a batch of several images, 2 or ≥ 4 channels).
        ValueRangeError: non-finite values or a non-positive exposure.

    Example:
        >>> import tempfile, torch, kornia
        >>> from torch_interreflect.camera import save_image
        >>> p = save_image(tempfile.mkdtemp() + "/x.png", torch.full((3, 2, 2), 0.5), srgb=False)
        >>> int(kornia.io.load_image(p, kornia.io.ImageLoadType.UNCHANGED)[0, 0, 0])
        32768
    """
    import kornia.io

    img = image.detach()
    if img.ndim == 4 and img.shape[0] == 1:
        img = img[0]
    if img.ndim == 2:
        img = img[None]
    if img.ndim != 3 or img.shape[0] not in (1, 3):
        raise ShapeError(f"image must be [3, H, W], [1, H, W], [H, W] or [1, C, H, W]; got {list(image.shape)}")
    if not bool(torch.isfinite(img).all()):
        raise ValueRangeError("image must be finite; got NaN or inf (check the exposure and the render)")
    if not float(exposure) > 0:
        raise ValueRangeError(f"exposure must be a positive number; got {exposure!r}")
    img = img.to(torch.float64).cpu()
    if srgb:
        rgb = img.expand(3, -1, -1) if img.shape[0] == 1 else img
        enc = to_srgb(rgb[None], exposure=float(exposure))[0]
        enc = enc[:1] if img.shape[0] == 1 else enc
        data = (enc * 255.0).round().to(torch.uint8)
    else:
        data = ((img * float(exposure)).clamp(0.0, 1.0) * 65535.0).round().to(torch.int32).to(torch.uint16)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    kornia.io.write_image(out, data.contiguous())
    return out
