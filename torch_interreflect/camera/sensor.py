"""Camera model: spectral radiance of facets to camera responses (paper eq. 61).

``ρ_k = Σ_λ C_k(λ) L(λ) Δλ`` for every channel ``k``, with ``Δλ`` from
:func:`torch_interreflect.spectral.integration_weights` (the step on a uniform grid). The function
:func:`spectral_to_rgb` does the work; :class:`Camera` is a thin :class:`torch.nn.Module` holding the
sensitivities, the grid and the weights as buffers (kornia style: ``rgb_to_xyz`` beside ``RgbToXyz``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from .. import spectral
from ..errors import ShapeError

__all__ = ["Camera", "spectral_to_rgb"]


def _check_inputs(radiance: Tensor, sensitivities: Tensor, wavelengths: Tensor) -> None:
    if not isinstance(radiance, Tensor):
        raise TypeError(f"radiance must be a tensor [..., F, L]; got {type(radiance).__name__}")
    if not isinstance(sensitivities, Tensor):
        raise TypeError(f"sensitivities must be a tensor [C, L]; got {type(sensitivities).__name__}")
    if not isinstance(wavelengths, Tensor):
        raise TypeError(f"wavelengths must be a tensor [L]; got {type(wavelengths).__name__}")
    if not radiance.is_floating_point():
        raise TypeError(f"radiance must be a floating tensor; got dtype {radiance.dtype}")
    if sensitivities.ndim != 2:
        raise ShapeError(f"sensitivities must be [C, L]; got shape {list(sensitivities.shape)}")
    if wavelengths.ndim != 1:
        raise ShapeError(f"wavelengths must be 1-D [L]; got shape {list(wavelengths.shape)}")
    n_wl = wavelengths.shape[0]
    if sensitivities.shape[1] != n_wl:
        raise ShapeError(
            f"sensitivities have {sensitivities.shape[1]} wavelengths (shape {list(sensitivities.shape)}) "
            f"but the grid has {n_wl}"
        )
    if radiance.ndim < 1 or radiance.shape[-1] != n_wl:
        got = radiance.shape[-1] if radiance.ndim else "none (a scalar)"
        raise ShapeError(
            f"radiance must be [..., F, L] with L = {n_wl} wavelengths (the camera's grid); got last "
            f"dimension {got} (shape {list(radiance.shape)})"
        )


def spectral_to_rgb(
    radiance: Tensor,
    sensitivities: Tensor,
    wavelengths: Tensor,
    *,
    weights: Tensor | None = None,
) -> Tensor:
    """Camera responses of spectral radiance: ``ρ_k = Σ_λ C_k(λ) L(λ) Δλ`` (paper eq. 61).

    ``Δλ`` are the cell widths of :func:`torch_interreflect.spectral.integration_weights`: the step for
    every sample on a uniform grid (the paper's plain Riemann sum), ``(λ_{i+1} − λ_{i−1}) / 2`` inside a
    non-uniform grid and the neighbouring interval at its two ends. With radiance in W·sr⁻¹·m⁻²·nm⁻¹ and
    dimensionless sensitivities the response is in W·sr⁻¹·m⁻².

    Differentiable in ``radiance`` and ``sensitivities``. The result follows the dtype and device of
    ``radiance``: the sensitivities and weights are converted to them.

    Args:
        radiance: Spectral radiance per facet, in W·sr⁻¹·m⁻²·nm⁻¹. Shape ``[..., F, L]`` (any leading
            dimensions, ``[L]`` included).
        sensitivities: Channel sensitivities ``C_k(λ)``. Shape ``[C, L]`` (``C = 3`` for RGB).
        wavelengths: The grid in nm, strictly increasing. Shape ``[L]``, ``L >= 2`` unless ``weights`` is
            given.
        weights: Optional precomputed ``Δλ`` in nm (e.g. from :class:`Camera`); when given, the grid's
            values are not checked again. Shape ``[L]``.

    Returns:
        Camera responses. Shape ``[..., F, C]``.

    Raises:
        ShapeError: the last dimension of ``radiance`` or of ``sensitivities`` differs from ``L``, or
            ``wavelengths``/``weights`` are not ``[L]``.
        ValueRangeError: a non-finite, non-positive or non-increasing grid.
        TypeError: non-tensor or non-floating input.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.camera import spectral_to_rgb
        >>> wl = spectral.wavelengths()
        >>> C = spectral.camera_sensitivities("Nikon 5100 (NPL)", wl)
        >>> L = spectral.illuminant("D65", wl) * spectral.colorchecker(wl)[0] / torch.pi  # [24, 31]
        >>> spectral_to_rgb(L, C, wl).shape
        torch.Size([24, 3])
    """
    _check_inputs(radiance, sensitivities, wavelengths)
    if weights is None:
        weights = spectral.integration_weights(wavelengths)
    elif not isinstance(weights, Tensor) or weights.shape != wavelengths.shape:
        got = list(weights.shape) if isinstance(weights, Tensor) else type(weights).__name__
        raise ShapeError(f"weights must be a tensor of shape {list(wavelengths.shape)}; got {got}")
    kernel = sensitivities * weights.to(sensitivities.dtype)
    kernel = kernel.to(device=radiance.device, dtype=radiance.dtype)
    return radiance @ kernel.transpose(0, 1)


class Camera(nn.Module):
    """A spectral camera: holds sensitivities ``[C, L]`` on a grid ``[L]`` and applies eq. 61.

    The sensitivities, the wavelengths and the integration weights ``Δλ``
    (:func:`~torch_interreflect.spectral.integration_weights`) are buffers, so ``.to(device, dtype)``
    moves them and they are saved in the ``state_dict``. ``forward`` calls :func:`spectral_to_rgb`.

    Args:
        sensitivities: Channel sensitivities. Shape ``[C, L]`` (``C = 3`` for RGB).
        wavelengths: Strictly increasing grid in nm. Shape ``[L]``, ``L >= 2``.
        name: Optional label, shown in ``repr``.

    Shape:
        - Input: radiance ``[..., F, L]`` in W·sr⁻¹·m⁻²·nm⁻¹
        - Output: responses ``[..., F, C]``

    Raises:
        ShapeError: ``sensitivities`` not ``[C, L]`` for the grid's ``L``; grid not 1-D or shorter than 2.
        ValueRangeError: a non-finite, non-positive or non-increasing grid.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.camera import Camera
        >>> wl = spectral.wavelengths()
        >>> cam = Camera.from_colour("CIE 1931", wl)
        >>> rgb = cam(spectral.illuminant("E", wl).expand(5, -1))  # 5 facets of equal-energy radiance
        >>> rgb.shape
        torch.Size([5, 3])
    """

    sensitivities: Tensor
    wavelengths: Tensor
    weights: Tensor

    def __init__(
        self,
        sensitivities: Tensor | Sequence[Sequence[float]] | np.ndarray,
        wavelengths: Tensor | Sequence[float] | np.ndarray,
        *,
        name: str | None = None,
    ) -> None:
        super().__init__()
        wl = spectral.check_wavelengths(wavelengths, min_samples=2)
        if not isinstance(sensitivities, Tensor):
            sensitivities = torch.as_tensor(np.asarray(sensitivities, dtype=np.float64), dtype=wl.dtype)
        if not sensitivities.is_floating_point():
            sensitivities = sensitivities.to(wl.dtype)
        if sensitivities.ndim != 2 or sensitivities.shape[1] != wl.shape[0]:
            raise ShapeError(
                f"sensitivities must be [C, L] with L = {wl.shape[0]} (the grid's length); "
                f"got shape {list(sensitivities.shape)}"
            )
        self.name = name
        self.register_buffer("sensitivities", sensitivities)
        wl = wl.detach().to(device=sensitivities.device, dtype=sensitivities.dtype, copy=True)
        self.register_buffer("wavelengths", wl)
        self.register_buffer("weights", spectral.integration_weights(self.wavelengths))

    @classmethod
    def from_colour(
        cls,
        name: str,
        wavelengths: Tensor | Sequence[float] | np.ndarray,
        *,
        extrapolate: spectral.Extrapolate = "error",
    ) -> Camera:
        """A camera with colour-science sensitivities (see :func:`spectral.camera_sensitivities`).

        Args:
            name: ``"Nikon 5100 (NPL)"``, ``"Sigma SDMerill (NPL)"``, ``"CIE 1931"`` (x̄, ȳ, z̄), ...
            wavelengths: Strictly increasing grid in nm. Shape ``[L]``; its dtype/device are used.
            extrapolate: Range handling outside the data, as in :func:`spectral.camera_sensitivities`.

        Returns:
            The camera.

        Example:
            >>> from torch_interreflect import spectral
            >>> Camera.from_colour("Nikon 5100 (NPL)", spectral.wavelengths()).num_channels
            3
        """
        sens = spectral.camera_sensitivities(name, wavelengths, extrapolate=extrapolate)
        return cls(sens, spectral.check_wavelengths(wavelengths, min_samples=2), name=name)

    @property
    def num_channels(self) -> int:
        """Number of channels ``C``."""
        return int(self.sensitivities.shape[0])

    @property
    def num_wavelengths(self) -> int:
        """Number of wavelengths ``L``."""
        return int(self.wavelengths.shape[0])

    def forward(self, radiance: Tensor) -> Tensor:
        """Camera responses ``[..., F, C]`` of radiance ``[..., F, L]`` (W·sr⁻¹·m⁻²·nm⁻¹)."""
        return spectral_to_rgb(radiance, self.sensitivities, self.wavelengths, weights=self.weights)

    def extra_repr(self) -> str:
        wl = self.wavelengths
        label = f"name={self.name!r}, " if self.name else ""
        return (
            f"{label}channels={self.num_channels}, wavelengths={self.num_wavelengths} "
            f"({float(wl[0]):g}–{float(wl[-1]):g} nm)"
        )
