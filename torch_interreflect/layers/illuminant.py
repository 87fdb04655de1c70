"""The :class:`IlluminantBasis` module: an illuminant spectrum from a few (learnable) parameters.

The maths lives in :mod:`torch_interreflect.spectral.illuminants`; this module holds the basis as buffers.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from torch import Tensor, nn

from .. import spectral
from .._checks import as_float_tensor
from ..spectral.illuminants import daylight, daylight_basis, daylight_from_cct, planck

__all__ = ["IlluminantBasis"]


class IlluminantBasis(nn.Module):
    """Illuminant spectra from a few parameters: CIE daylight by ``(M1, M2)`` or by CCT, or a blackbody.

    Holds the grid and the daylight basis ``S0, S1, S2`` as buffers (``.to(device, dtype)`` moves them) and calls
    :func:`daylight`, :func:`daylight_from_cct` or :func:`planck`. The parameters come in as inputs, so they can
    be ``nn.Parameter``\\ s of the caller, network outputs, or fixed.

    Args:
        wavelengths: Strictly increasing grid in nm, inside 300–830 nm. Shape ``[L]``.
        model: What ``forward`` takes: ``"coefficients"`` (``(M1, M2)``, shape ``[..., 2]``), ``"cct"``
            (temperature ``[...]`` in K on the daylight locus) or ``"blackbody"`` (temperature ``[...]`` in K).

    Shape:
        - Input: ``[..., 2]`` (coefficients) or ``[...]`` (temperatures); optional ``scale`` broadcastable to
          ``[...]``.
        - Output: ``[..., L]``, relative (100 at 560 nm) times ``scale``.

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.layers import IlluminantBasis
        >>> ill = IlluminantBasis(spectral.wavelengths(), model="cct")
        >>> T = torch.tensor([5000.0, 6500.0], requires_grad=True)
        >>> S = ill(T)
        >>> S.shape
        torch.Size([2, 31])
        >>> S.sum().backward(); T.grad.shape
        torch.Size([2])
    """

    wavelengths: Tensor
    basis: Tensor

    MODELS = ("coefficients", "cct", "blackbody")

    def __init__(self, wavelengths: Tensor | Sequence[float] | np.ndarray, *, model: str = "coefficients") -> None:
        super().__init__()
        if model not in self.MODELS:
            raise ValueError(f"model must be one of {list(self.MODELS)}; got {model!r}")
        wl = spectral.check_wavelengths(wavelengths)
        self.model = model
        self.register_buffer("wavelengths", wl.detach().clone())
        self.register_buffer("basis", daylight_basis(wl))

    @property
    def num_parameters(self) -> int:
        """Parameters per spectrum (2 for ``"coefficients"``, 1 otherwise), scale not counted."""
        return 2 if self.model == "coefficients" else 1

    def forward(self, params: Tensor | float, scale: Tensor | float | None = None) -> Tensor:
        """Spectrum ``[..., L]`` from ``params`` (see the class docstring), times ``scale`` if given."""
        if self.model == "coefficients":
            if not isinstance(params, Tensor):
                raise TypeError(f"coefficients must be a tensor [..., 2]; got {type(params).__name__}")
            s = daylight(params, self.basis)
        elif self.model == "cct":
            s = daylight_from_cct(params, self.basis)
        else:
            s = planck(params, self.wavelengths)
        if scale is not None:
            scale = as_float_tensor(scale, "scale", s)
            s = s * scale.to(s.device)[..., None]
        return s

    def extra_repr(self) -> str:
        wl = self.wavelengths
        return f"model={self.model!r}, wavelengths={wl.numel()} ({float(wl[0]):g}–{float(wl[-1]):g} nm)"
