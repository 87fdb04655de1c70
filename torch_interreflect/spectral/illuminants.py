"""Differentiable illuminant parametrisations: CIE daylight (S0, S1, S2 basis, by M1/M2 or by CCT) and Planck.

Functions, differentiable in every tensor argument (the module :class:`~torch_interreflect.layers.IlluminantBasis`
holds a basis and calls them):

- :func:`daylight_basis` — the CIE D-series basis ``S0, S1, S2`` from colour-science, sampled on a grid.
- :func:`daylight` — ``S(λ) = S0 + M1 S1 + M2 S2`` from the two coefficients.
- :func:`cct_to_daylight_coefficients` — CCT → chromaticity ``x_D, y_D`` on the CIE daylight locus → ``M1, M2``
  (CIE 15:2004 eq. 3.3–3.6, the formulas of ``colour.temperature.CCT_to_xy_CIE_D`` and
  ``colour.sd_CIE_illuminant_D_series``, without rounding ``M1, M2``), valid on 4000–25000 K.
- :func:`daylight_from_cct` — the two composed.
- :func:`planck` — blackbody spectrum ``100 · B(λ, T) / B(560 nm, T)`` (the CIE normalisation of
  :func:`torch_interreflect.spectral.blackbody`), differentiable in the temperature.

Units: wavelengths in nm, temperatures in K. The spectra are relative (100 at 560 nm); multiply by a scale to get
irradiance in W·m⁻²·nm⁻¹.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .._checks import as_float_tensor
from ..errors import ShapeError, ValueRangeError
from .data import sample_spd
from .grid import cached_on_grid

__all__ = [
    "CCT_RANGE",
    "cct_to_daylight_coefficients",
    "check_daylight_basis",
    "daylight",
    "daylight_basis",
    "daylight_from_cct",
    "planck",
]

#: Second radiation constant (m·K) used by colour-science (CIE definition of illuminant A).
_C2 = 1.4388e-2


#: Range of correlated colour temperatures (K) on which the CIE daylight locus is defined.
CCT_RANGE = (4000.0, 25000.0)


@functools.lru_cache(maxsize=32)
def _daylight_basis_np(grid: tuple[float, ...]) -> np.ndarray:
    from colour.colorimetry import SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES as basis

    g = np.asarray(grid)
    out = np.stack([sample_spd(basis[k], g, "error", f"CIE daylight basis {k}") for k in ("S0", "S1", "S2")])
    out.setflags(write=False)
    return out


def daylight_basis(wavelengths: Tensor | Sequence[float] | np.ndarray) -> Tensor:
    """The CIE daylight basis functions ``S0, S1, S2`` sampled at ``wavelengths`` (300–830 nm).

    Values from ``colour.colorimetry.SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES`` (5 nm table), evaluated with
    colour's interpolator on a copy.

    Args:
        wavelengths: Strictly increasing grid in nm. Shape ``[L]``.

    Returns:
        The basis on the dtype/device of ``wavelengths``. Shape ``[3, L]``.

    Raises:
        SpectralDataError: grid outside 300–830 nm.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import daylight_basis
        >>> daylight_basis(spectral.wavelengths()).shape
        torch.Size([3, 31])
    """
    return cached_on_grid(_daylight_basis_np, wavelengths)


def check_daylight_basis(basis: Tensor) -> None:
    if not isinstance(basis, Tensor) or basis.ndim != 2 or basis.shape[0] != 3:
        got = list(basis.shape) if isinstance(basis, Tensor) else type(basis).__name__
        raise ShapeError(f"daylight basis must be a tensor [3, L] (S0, S1, S2); got {got}")


def daylight(coefficients: Tensor, basis: Tensor) -> Tensor:
    """CIE daylight spectrum ``S0 + M1 S1 + M2 S2`` from the coefficients ``(M1, M2)``.

    Differentiable (linear) in ``coefficients`` and ``basis``.

    Args:
        coefficients: ``(M1, M2)``. Shape ``[..., 2]``.
        basis: ``S0, S1, S2`` from :func:`daylight_basis`. Shape ``[3, L]``.

    Returns:
        Relative spectrum (100 at 560 nm for every M1, M2). Shape ``[..., L]``.

    Raises:
        ShapeError: ``coefficients`` not ``[..., 2]`` or ``basis`` not ``[3, L]``.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import daylight, daylight_basis
        >>> S = daylight(torch.tensor([0.0, 0.0]), daylight_basis(spectral.wavelengths()))  # S0 alone
        >>> S.shape
        torch.Size([31])
    """
    check_daylight_basis(basis)
    if not isinstance(coefficients, Tensor) or coefficients.ndim < 1 or coefficients.shape[-1] != 2:
        got = list(coefficients.shape) if isinstance(coefficients, Tensor) else type(coefficients).__name__
        raise ShapeError(f"daylight coefficients must be [..., 2] (M1, M2); got {got}")
    basis = basis.to(device=coefficients.device, dtype=torch.promote_types(basis.dtype, coefficients.dtype))
    return basis[0] + coefficients.to(basis.dtype) @ basis[1:]


def cct_to_daylight_coefficients(cct: Tensor | float) -> Tensor:
    """``(M1, M2)`` of the CIE daylight at correlated colour temperature ``cct`` (differentiable).

    ``x_D = a/T³ + b/T² + c/T + d`` (two sets of constants, below and above 7000 K), ``y_D = −3 x_D² + 2.87 x_D
    − 0.275``, ``M = 0.0241 + 0.2562 x_D − 0.7341 y_D``, ``M1 = (−1.3515 − 1.7703 x_D + 5.9114 y_D) / M``,
    ``M2 = (0.0300 − 31.4424 x_D + 30.0717 y_D) / M`` (CIE 15:2004; as ``colour.temperature.CCT_to_xy_CIE_D``
    and ``colour.sd_CIE_illuminant_D_series`` without rounding). No ``c2`` rescaling: 6504 K gives D65.

    Args:
        cct: Temperature in K, in [4000, 25000]. Shape ``[...]`` (or a number).

    Returns:
        ``(M1, M2)``. Shape ``[..., 2]``.

    Raises:
        ValueRangeError: a temperature outside [4000, 25000] K or not finite.

    Example:
        >>> from torch_interreflect.spectral import cct_to_daylight_coefficients
        >>> [round(v, 3) for v in cct_to_daylight_coefficients(6504.0).tolist()]
        [-0.294, -0.689]
    """
    T = as_float_tensor(cct, "cct")
    t = T.detach()
    if t.numel() and not (bool(torch.isfinite(t).all()) and float(t.min()) >= CCT_RANGE[0]
                          and float(t.max()) <= CCT_RANGE[1]):
        raise ValueRangeError(
            f"cct must lie in [{CCT_RANGE[0]:g}, {CCT_RANGE[1]:g}] K (the CIE daylight locus); got values in "
            f"[{float(t.min()):g}, {float(t.max()):g}]"
        )
    u = 1.0 / T
    x_low = -4.6070e9 * u**3 + 2.9678e6 * u**2 + 0.09911e3 * u + 0.244063
    x_high = -2.0064e9 * u**3 + 1.9018e6 * u**2 + 0.24748e3 * u + 0.237040
    x = torch.where(T <= 7000.0, x_low, x_high)
    y = -3.0 * x**2 + 2.870 * x - 0.275
    m = 0.0241 + 0.2562 * x - 0.7341 * y
    m1 = (-1.3515 - 1.7703 * x + 5.9114 * y) / m
    m2 = (0.0300 - 31.4424 * x + 30.0717 * y) / m
    return torch.stack([m1, m2], dim=-1)


def daylight_from_cct(cct: Tensor | float, basis: Tensor) -> Tensor:
    """CIE daylight spectrum at temperature ``cct`` (K), differentiable in ``cct``.

    Args:
        cct: Temperature in K, in [4000, 25000]. Shape ``[...]``.
        basis: ``S0, S1, S2`` from :func:`daylight_basis`. Shape ``[3, L]``.

    Returns:
        Relative spectrum, 100 at 560 nm. Shape ``[..., L]``.

    Example:
        >>> from torch_interreflect import spectral
        >>> from torch_interreflect.spectral import daylight_basis, daylight_from_cct
        >>> wl = spectral.wavelengths(dtype=torch.float64)
        >>> S = daylight_from_cct(torch.tensor(6504.0, dtype=torch.float64), daylight_basis(wl))
        >>> bool((S - spectral.illuminant("D65", wl)).abs().max() < 0.2)
        True
    """
    check_daylight_basis(basis)
    T = as_float_tensor(cct, "cct", basis)
    return daylight(cct_to_daylight_coefficients(T).to(basis.device), basis)


def planck(temperature: Tensor | float, wavelengths: Tensor) -> Tensor:
    """Blackbody spectrum ``100 · B(λ, T) / B(560 nm, T)``, differentiable in the temperature.

    ``B(λ, T) ∝ λ⁻⁵ / (exp(c2 / (λ T)) − 1)`` with ``c2 = 1.4388e-2 m·K`` (colour-science's constant), so the
    values equal :func:`torch_interreflect.spectral.blackbody`.

    Args:
        temperature: Temperature in K (> 0). Shape ``[...]`` (or a number).
        wavelengths: Wavelengths in nm. Shape ``[L]``.

    Returns:
        Relative spectrum, 100 at 560 nm. Shape ``[..., L]``.

    Raises:
        ValueRangeError: a non-positive or non-finite temperature.

    Example:
        >>> from torch_interreflect.spectral import planck
        >>> float(planck(2856.0, torch.tensor([560.0])))
        100.0
    """
    if not isinstance(wavelengths, Tensor) or wavelengths.ndim != 1:
        raise ShapeError("wavelengths must be a 1-D tensor [L] in nm")
    wl = wavelengths if wavelengths.is_floating_point() else wavelengths.to(torch.get_default_dtype())
    T = as_float_tensor(temperature, "temperature", wl)
    t = T.detach()
    if t.numel() and not (bool(torch.isfinite(t).all()) and float(t.min()) > 0):
        raise ValueRangeError(f"temperature must be finite and > 0 K; got min {float(t.min()):g}")
    dtype = torch.promote_types(T.dtype, wl.dtype)
    T = T.to(device=wl.device, dtype=dtype)[..., None]
    lam = wl.to(dtype) * 1e-9
    ref = 560e-9
    return 100.0 * (ref / lam) ** 5 * torch.expm1(_C2 / (ref * T)) / torch.expm1(_C2 / (lam * T))
