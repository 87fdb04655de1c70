"""Differentiable reflectance parametrisations: a PCA basis of measured spectra, and RGB → spectrum upsampling.

- :func:`reflectance_data` — every reflectance spectrum colour-science ships that we know of, on a grid: the
  ColorChecker sets of ``colour.SDS_COLOURCHECKERS`` (N Ohta, BabelColor average, PMC), the CIE test colour
  samples (``colour.quality.SDS_TCS``: CIE 1995 and 2024 sets), the NIST CQS samples (``colour.quality.SDS_VS``)
  and the 190 RAW-to-ACES training spectra (``colour.characterisation.read_training_data_rawtoaces_v1``);
  exact duplicates removed. Data that do not cover the grid are extended with their end values.
- :func:`fit_reflectance_basis` — PCA (SVD of the centred data): ``mean [L]`` and orthonormal ``components
  [K, L]``, either on the reflectances (``space="linear"``) or on their logits (``space="logit"``).
- :func:`reflectance_from_coefficients` — ``r = clamp(mean + c @ components, 0, 1)`` (linear) or
  ``r = sigmoid(mean + c @ components)`` (logit). The clamp has zero gradient where it is active; the logit
  space keeps every reflectance inside (0, 1) with a gradient everywhere, at the price of non-linearity.
- :func:`coefficients_from_reflectance` — the least-squares coefficients of given spectra (in the same space).
- :func:`rgb_to_spectrum` — Mallett & Yuksel (2019) upsampling: ``r(λ) = R b_R(λ) + G b_G(λ) + B b_B(λ)`` with
  the three basis spectra of ``colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019``; linear (so exactly
  differentiable), and a reflectance in [0, 1] for any linear sRGB in [0, 1]³.

:class:`~torch_interreflect.layers.ReflectanceBasis` and :class:`~torch_interreflect.layers.RGBToSpectrum` hold the
basis as buffers and call these functions. Both
expose ``mean [L]`` and ``components [K, L]`` (zero mean and the three Mallett spectra for the latter), which is
what the linear least-squares solver of :func:`torch_interreflect.inverse.estimate_reflectance` uses.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import ShapeError
from .data import sample_spd
from .grid import cached_on_grid

__all__ = [
    "LOGIT_EPS",
    "check_linear_basis",
    "check_space",
    "coefficients_from_reflectance",
    "fit_reflectance_basis",
    "mallett2019_basis",
    "reflectance_data",
    "reflectance_from_coefficients",
    "rgb_to_spectrum",
]



_SPACES = ("linear", "logit")


#: Reflectances are clipped to [LOGIT_EPS, 1 − LOGIT_EPS] before taking logits.
LOGIT_EPS = 1e-3


def _datasets() -> list[tuple[str, object]]:
    """(label, spectral distribution) of every reflectance data set used (colour's objects, never mutated)."""
    import colour
    from colour.characterisation import read_training_data_rawtoaces_v1
    from colour.quality import SDS_TCS, SDS_VS

    out: list[tuple[str, object]] = []
    for name in ("ColorChecker N Ohta", "BabelColor Average", "PMC"):
        out += [(f"{name} {k}", sd) for k, sd in colour.SDS_COLOURCHECKERS[name].items()]
    for group in (SDS_TCS, SDS_VS):
        for set_name, sds in group.items():
            out += [(f"{set_name} {k}", sd) for k, sd in sds.items()]
    msds = read_training_data_rawtoaces_v1()
    out += [(f"rawtoaces {k}", sd) for k, sd in zip(msds.labels, msds.to_sds(), strict=True)]
    return out


@functools.lru_cache(maxsize=16)
def _reflectance_data_np(grid: tuple[float, ...]) -> np.ndarray:
    g = np.asarray(grid)
    rows = [sample_spd(sd, g, "constant", label) for label, sd in _datasets()]
    data = np.clip(np.stack(rows), 0.0, 1.0)
    _, keep = np.unique(np.round(data, 8), axis=0, return_index=True)
    data = data[np.sort(keep)]
    data.setflags(write=False)
    return data


def reflectance_data(wavelengths: Tensor | Sequence[float] | np.ndarray) -> Tensor:
    """All reflectance spectra shipped with colour-science (see the module docstring), sampled on a grid.

    Args:
        wavelengths: Strictly increasing grid in nm. Shape ``[L]``.

    Returns:
        Reflectances in [0, 1] on the dtype/device of ``wavelengths``. Shape ``[N, L]`` (N ≈ 300).

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import reflectance_data
        >>> reflectance_data(spectral.wavelengths()).shape[0] > 250
        True
    """
    return cached_on_grid(_reflectance_data_np, wavelengths)


def check_space(space: str) -> None:
    if space not in _SPACES:
        raise ValueError(f"space must be one of {list(_SPACES)}; got {space!r}")


def _logit(r: Tensor) -> Tensor:
    return torch.logit(r.clamp(LOGIT_EPS, 1 - LOGIT_EPS))


def fit_reflectance_basis(data: Tensor, num_components: int, *, space: str = "linear") -> tuple[Tensor, Tensor]:
    """PCA basis of reflectance spectra: the mean and the ``K`` leading principal directions.

    Args:
        data: Reflectances in [0, 1]. Shape ``[N, L]``.
        num_components: ``K``, 1 ≤ K ≤ min(N, L).
        space: ``"linear"`` (fit the reflectances) or ``"logit"`` (fit ``logit(clip(r, 1e-3, 1 − 1e-3))``).

    Returns:
        ``(mean, components)``: shapes ``[L]`` and ``[K, L]`` (orthonormal rows, by decreasing variance).

    Raises:
        ShapeError: ``data`` not ``[N, L]``.
        ValueError: ``num_components`` out of range, or an unknown ``space``.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import fit_reflectance_basis, reflectance_data
        >>> mean, comps = fit_reflectance_basis(reflectance_data(spectral.wavelengths()), 6)
        >>> comps.shape
        torch.Size([6, 31])
    """
    check_space(space)
    if not isinstance(data, Tensor) or data.ndim != 2:
        raise ShapeError(f"data must be a tensor [N, L]; got {getattr(data, 'shape', type(data).__name__)}")
    n, length = data.shape
    k = int(num_components)
    if not 1 <= k <= min(n, length):
        raise ValueError(f"num_components must lie in [1, {min(n, length)}] (min(N, L)); got {num_components}")
    x = data.detach().to(torch.float64)
    if space == "logit":
        x = _logit(x)
    mean = x.mean(0)
    _, _, vh = torch.linalg.svd(x - mean, full_matrices=False)
    comps = vh[:k]
    # fix the sign of each component (largest entry positive) so the basis is reproducible
    sign = torch.sign(comps.gather(1, comps.abs().argmax(1, keepdim=True)))
    return mean.to(data.dtype), (comps * sign).to(data.dtype)


def check_linear_basis(mean: Tensor, components: Tensor) -> None:
    if not isinstance(components, Tensor) or components.ndim != 2:
        raise ShapeError(f"components must be a tensor [K, L]; got {getattr(components, 'shape', components)}")
    if not isinstance(mean, Tensor) or mean.shape != components.shape[1:]:
        raise ShapeError(
            f"mean must have shape [L] = [{components.shape[1]}] to match components {list(components.shape)}; "
            f"got {getattr(mean, 'shape', type(mean).__name__)}"
        )


def reflectance_from_coefficients(
    coefficients: Tensor, mean: Tensor, components: Tensor, *, space: str = "linear"
) -> Tensor:
    """Reflectance spectra from basis coefficients.

    ``linear``: ``clamp(mean + c @ components, 0, 1)``; ``logit``: ``sigmoid(mean + c @ components)``.

    Args:
        coefficients: ``c``. Shape ``[..., K]``.
        mean: Shape ``[L]``.
        components: Shape ``[K, L]``.
        space: ``"linear"`` or ``"logit"`` (the space the basis was fitted in).

    Returns:
        Reflectance in [0, 1]. Shape ``[..., L]``.

    Raises:
        ShapeError: ``coefficients`` not ``[..., K]``, ``mean`` not ``[L]``.

    Example:
        >>> from torch_interreflect.spectral import reflectance_from_coefficients
        >>> reflectance_from_coefficients(torch.zeros(2, 1), torch.full((4,), 0.5), torch.ones(1, 4)).shape
        torch.Size([2, 4])
    """
    check_space(space)
    check_linear_basis(mean, components)
    if not isinstance(coefficients, Tensor) or coefficients.ndim < 1 or coefficients.shape[-1] != components.shape[0]:
        got = list(coefficients.shape) if isinstance(coefficients, Tensor) else type(coefficients).__name__
        raise ShapeError(f"coefficients must be [..., K] with K = {components.shape[0]}; got {got}")
    dtype = torch.promote_types(coefficients.dtype, components.dtype)
    c = coefficients.to(dtype)
    x = mean.to(device=c.device, dtype=dtype) + c @ components.to(device=c.device, dtype=dtype)
    return x.clamp(0.0, 1.0) if space == "linear" else torch.sigmoid(x)


def coefficients_from_reflectance(
    reflectance: Tensor, mean: Tensor, components: Tensor, *, space: str = "linear"
) -> Tensor:
    """Least-squares basis coefficients of reflectance spectra (in the basis's space).

    Args:
        reflectance: Shape ``[..., L]``, in [0, 1].
        mean: Shape ``[L]``.
        components: Shape ``[K, L]`` (any full-rank basis; orthonormal rows make this a projection).

    Returns:
        Coefficients. Shape ``[..., K]``.

    Example:
        >>> from torch_interreflect.spectral import coefficients_from_reflectance
        >>> coefficients_from_reflectance(torch.full((4,), 0.7), torch.full((4,), 0.5), torch.ones(1, 4) / 2)
        tensor([0.4000])
    """
    check_space(space)
    check_linear_basis(mean, components)
    if not isinstance(reflectance, Tensor) or reflectance.ndim < 1 or reflectance.shape[-1] != mean.shape[0]:
        got = list(reflectance.shape) if isinstance(reflectance, Tensor) else type(reflectance).__name__
        raise ShapeError(f"reflectance must be [..., L] with L = {mean.shape[0]}; got {got}")
    dtype = torch.promote_types(reflectance.dtype, components.dtype)
    r = reflectance.to(dtype)
    x = _logit(r) if space == "logit" else r
    p = components.to(device=r.device, dtype=dtype)
    y = x - mean.to(device=r.device, dtype=dtype)
    # c = y Pᵀ (P Pᵀ)⁻¹
    return torch.linalg.solve(p @ p.T, (y @ p.T).unsqueeze(-1)).squeeze(-1)


@functools.lru_cache(maxsize=16)
def _mallett_np(grid: tuple[float, ...]) -> np.ndarray:
    from colour.recovery import MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019 as basis

    out = np.ascontiguousarray(sample_spd(basis, np.asarray(grid), "constant", "Mallett 2019 basis").T)
    out.setflags(write=False)
    return out


def mallett2019_basis(wavelengths: Tensor | Sequence[float] | np.ndarray) -> Tensor:
    """The three sRGB basis spectra of Mallett & Yuksel (2019) on a grid (data 380–780 nm, extended flat).

    Args:
        wavelengths: Strictly increasing grid in nm. Shape ``[L]``.

    Returns:
        ``b_R, b_G, b_B``, each in [0, 1], summing to ≈ 1 at every wavelength. Shape ``[3, L]``.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import mallett2019_basis
        >>> b = mallett2019_basis(spectral.wavelengths())
        >>> bool((b.sum(0) - 1).abs().max() < 1e-3)
        True
    """
    return cached_on_grid(_mallett_np, wavelengths)


def rgb_to_spectrum(rgb: Tensor, basis: Tensor) -> Tensor:
    """Reflectance spectrum of linear sRGB values (Mallett & Yuksel 2019): ``r(λ) = rgb @ basis``.

    Linear, hence differentiable everywhere; values in [0, 1] when ``rgb`` is in [0, 1]³.

    Args:
        rgb: Linear sRGB. Shape ``[..., 3]``.
        basis: From :func:`mallett2019_basis`. Shape ``[3, L]``.

    Returns:
        Reflectance. Shape ``[..., L]``.

    Raises:
        ShapeError: ``rgb`` not ``[..., 3]`` or ``basis`` not ``[3, L]``.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import mallett2019_basis, rgb_to_spectrum
        >>> r = rgb_to_spectrum(torch.tensor([0.5, 0.5, 0.5]), mallett2019_basis(spectral.wavelengths()))
        >>> bool((r - 0.5).abs().max() < 1e-3)
        True
    """
    if not isinstance(basis, Tensor) or basis.ndim != 2 or basis.shape[0] != 3:
        raise ShapeError(f"basis must be a tensor [3, L]; got {getattr(basis, 'shape', type(basis).__name__)}")
    if not isinstance(rgb, Tensor) or rgb.ndim < 1 or rgb.shape[-1] != 3:
        raise ShapeError(f"rgb must be a tensor [..., 3]; got {getattr(rgb, 'shape', type(rgb).__name__)}")
    dtype = torch.promote_types(rgb.dtype, basis.dtype) if rgb.is_floating_point() else basis.dtype
    return rgb.to(dtype) @ basis.to(device=rgb.device, dtype=dtype)
