"""Reflectance modules: :class:`ReflectanceBasis` (PCA of measured spectra) and :class:`RGBToSpectrum`.

The maths lives in :mod:`torch_interreflect.spectral.reflectances`; these modules hold bases as buffers.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from .. import spectral
from ..errors import ShapeError, ValueRangeError
from ..spectral.reflectances import (
    check_space,
    coefficients_from_reflectance,
    fit_reflectance_basis,
    mallett2019_basis,
    reflectance_data,
    reflectance_from_coefficients,
    rgb_to_spectrum,
)

__all__ = ["RGBToSpectrum", "ReflectanceBasis"]


class ReflectanceBasis(nn.Module):
    """A linear (PCA) basis of reflectance spectra; ``forward`` maps coefficients ``[..., K]`` to ``[..., L]``.

    Fitted at construction by :func:`fit_reflectance_basis` on ``data`` (default :func:`reflectance_data`: all
    reflectance sets in colour-science, ≈ 300 spectra). ``mean`` and ``components`` are buffers. With
    ``space="linear"`` the output is ``clamp(mean + c @ components, 0, 1)``; with ``"logit"``,
    ``sigmoid(mean + c @ components)`` (see :func:`reflectance_from_coefficients`).

    Args:
        wavelengths: Strictly increasing grid in nm. Shape ``[L]``.
        num_components: ``K`` (default 3: as many as an RGB camera measures).
        space: ``"linear"`` or ``"logit"``.
        data: Optional reflectances to fit instead. Shape ``[N, L]``.

    Shape:
        - Input: coefficients ``[..., K]``
        - Output: reflectance ``[..., L]``

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.layers import ReflectanceBasis
        >>> basis = ReflectanceBasis(spectral.wavelengths(), num_components=8)
        >>> red = spectral.reflectance("red", spectral.wavelengths())
        >>> c = basis.encode(red)                      # [8]
        >>> bool((basis(c) - red).abs().max() < 0.05)
        True
    """

    wavelengths: Tensor
    mean: Tensor
    components: Tensor

    def __init__(
        self,
        wavelengths: Tensor | Sequence[float] | np.ndarray,
        num_components: int = 3,
        *,
        space: str = "linear",
        data: Tensor | None = None,
    ) -> None:
        super().__init__()
        check_space(space)
        wl = spectral.check_wavelengths(wavelengths)
        if data is None:
            data = reflectance_data(wl)
        elif not isinstance(data, Tensor) or data.ndim != 2 or data.shape[1] != wl.shape[0]:
            raise ShapeError(
                f"data must be a tensor [N, L] with L = {wl.shape[0]}; got {getattr(data, 'shape', type(data))}"
            )
        elif bool(((data < 0) | (data > 1)).any()) or not bool(torch.isfinite(data).all()):
            raise ValueRangeError("data must hold finite reflectances in [0, 1]")
        mean, comps = fit_reflectance_basis(data.to(wl.dtype), num_components, space=space)
        self.space = space
        self.register_buffer("wavelengths", wl.detach().clone())
        self.register_buffer("mean", mean.to(wl.device))
        self.register_buffer("components", comps.to(wl.device))

    @property
    def num_components(self) -> int:
        """``K``."""
        return int(self.components.shape[0])

    def forward(self, coefficients: Tensor) -> Tensor:
        """Reflectance ``[..., L]`` of coefficients ``[..., K]``."""
        return reflectance_from_coefficients(coefficients, self.mean, self.components, space=self.space)

    def encode(self, reflectance: Tensor) -> Tensor:
        """Least-squares coefficients ``[..., K]`` of reflectances ``[..., L]``."""
        return coefficients_from_reflectance(reflectance, self.mean, self.components, space=self.space)

    def extra_repr(self) -> str:
        return f"num_components={self.num_components}, space={self.space!r}, wavelengths={self.wavelengths.numel()}"


class RGBToSpectrum(nn.Module):
    """RGB → reflectance upsampling (Mallett & Yuksel 2019); the basis ``[3, L]`` is a buffer.

    Also usable as a 3-component linear reflectance basis: ``mean`` is zero and ``components`` is the basis.

    Args:
        wavelengths: Strictly increasing grid in nm. Shape ``[L]``.

    Shape:
        - Input: linear sRGB ``[..., 3]`` in [0, 1]
        - Output: reflectance ``[..., L]``

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.layers import RGBToSpectrum
        >>> up = RGBToSpectrum(spectral.wavelengths())
        >>> up(torch.rand(5, 3)).shape
        torch.Size([5, 31])
    """

    wavelengths: Tensor
    basis: Tensor

    space = "linear"

    def __init__(self, wavelengths: Tensor | Sequence[float] | np.ndarray) -> None:
        super().__init__()
        wl = spectral.check_wavelengths(wavelengths)
        self.register_buffer("wavelengths", wl.detach().clone())
        self.register_buffer("basis", mallett2019_basis(wl))

    @property
    def mean(self) -> Tensor:
        """Zero spectrum ``[L]`` (the basis has no offset)."""
        return torch.zeros_like(self.basis[0])

    @property
    def components(self) -> Tensor:
        """The basis ``[3, L]``."""
        return self.basis

    @property
    def num_components(self) -> int:
        return 3

    def forward(self, rgb: Tensor) -> Tensor:
        """Reflectance ``[..., L]`` of linear sRGB ``[..., 3]`` (not clamped)."""
        return rgb_to_spectrum(rgb, self.basis)

    def encode(self, reflectance: Tensor) -> Tensor:
        """Least-squares linear sRGB ``[..., 3]`` of reflectances ``[..., L]``."""
        return coefficients_from_reflectance(reflectance, self.mean, self.basis)
