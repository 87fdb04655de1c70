"""Wavelength grids: building, checking, and the integration weights of a grid (nm)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import ShapeError, ValueRangeError

__all__ = ["cached_on_grid", "check_wavelengths", "grid_dtype_device", "grid_numpy", "grid_tensor",
           "integration_weights", "wavelengths"]


def wavelengths(
    start: float = 400.0,
    stop: float = 700.0,
    step: float = 10.0,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """A uniform wavelength grid from ``start`` to ``stop`` (inclusive when it falls on the grid), in nm.

    The default is the paper's grid, 400–700 nm in 10 nm steps (31 samples). Any strictly increasing 1-D
    tensor of wavelengths works wherever a grid is expected, non-uniform ones included.

    Args:
        start: First wavelength in nm (> 0).
        stop: Last wavelength in nm (>= ``start``); included when ``stop - start`` is a multiple of
            ``step`` (to 1e-9 relative), else the grid ends at the last sample below it.
        step: Spacing in nm (> 0).
        dtype: Floating dtype of the result (default: ``torch.get_default_dtype()``).
        device: Device of the result (default: CPU).

    Returns:
        The grid. Shape ``[L]``, ``L = floor((stop - start) / step) + 1``.

    Raises:
        ValueRangeError: non-finite or non-positive ``start``/``step``, or ``stop < start``.

    Example:
        >>> from torch_interreflect import spectral
        >>> wl = spectral.wavelengths()
        >>> wl.shape, float(wl[0]), float(wl[-1])
        (torch.Size([31]), 400.0, 700.0)
    """
    for label, v in (("start", start), ("stop", stop), ("step", step)):
        if not math.isfinite(float(v)):
            raise ValueRangeError(f"wavelengths: {label} must be finite; got {v}")
    if start <= 0:
        raise ValueRangeError(f"wavelengths: start must be > 0 nm; got {start}")
    if step <= 0:
        raise ValueRangeError(f"wavelengths: step must be > 0 nm; got {step}")
    if stop < start:
        raise ValueRangeError(f"wavelengths: stop must be >= start; got start={start}, stop={stop}")
    n = math.floor((stop - start) / step * (1 + 1e-9) + 1e-9) + 1
    grid = float(start) + float(step) * torch.arange(n, dtype=torch.float64)
    return grid.to(dtype=dtype or torch.get_default_dtype(), device=device)


def grid_dtype_device(wl: Any) -> tuple[torch.dtype, torch.device]:
    if isinstance(wl, Tensor):
        dtype = wl.dtype if wl.is_floating_point() else torch.get_default_dtype()
        return dtype, wl.device
    return torch.get_default_dtype(), torch.device("cpu")


def grid_numpy(wl: Any, name: str = "wavelengths") -> np.ndarray:
    """Validate a wavelength grid and return it as a float64 numpy array."""
    if isinstance(wl, Tensor):
        if wl.is_complex():
            raise TypeError(f"{name} must be real; got dtype {wl.dtype}")
        arr = wl.detach().to("cpu", torch.float64).numpy()
    else:
        try:
            arr = np.asarray(wl, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise TypeError(
                f"{name} must be a 1-D tensor or sequence of numbers; got {type(wl).__name__}"
            ) from exc
    if arr.ndim != 1:
        raise ShapeError(f"{name} must be 1-D [L]; got shape {list(arr.shape)}")
    if arr.size == 0:
        raise ShapeError(f"{name} must hold at least one wavelength; got an empty grid")
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueRangeError(f"{name} must be finite; got {arr[i]} at index {i}")
    if arr[0] <= 0:
        raise ValueRangeError(f"{name} must be positive (nm); got {arr[0]} at index 0")
    if arr.size > 1:
        d = np.diff(arr)
        if (d <= 0).any():
            i = int(np.flatnonzero(d <= 0)[0])
            raise ValueRangeError(
                f"{name} must be strictly increasing; got {arr[i]} then {arr[i + 1]} at indices {i}, {i + 1}"
            )
    return arr


def check_wavelengths(wavelengths: Tensor | Sequence[float] | np.ndarray, *, min_samples: int = 1) -> Tensor:
    """Validate a wavelength grid and return it as a floating tensor.

    Args:
        wavelengths: Wavelengths in nm, strictly increasing, finite and positive. Shape ``[L]``.
        min_samples: Smallest admissible ``L``.

    Returns:
        The grid as a tensor (the input itself when it is already a floating tensor; integer tensors are
        converted to the default dtype on their device). Shape ``[L]``.

    Raises:
        ShapeError: not 1-D, or fewer than ``min_samples`` samples.
        ValueRangeError: non-finite, non-positive or not strictly increasing values.

    Example:
        >>> from torch_interreflect import spectral
        >>> spectral.check_wavelengths([400, 550, 700]).dtype == torch.get_default_dtype()
        True
    """
    arr = grid_numpy(wavelengths)
    if arr.size < min_samples:
        raise ShapeError(f"wavelengths must hold at least {min_samples} samples; got {arr.size}")
    if isinstance(wavelengths, Tensor) and wavelengths.is_floating_point():
        return wavelengths
    dtype, device = grid_dtype_device(wavelengths)
    return torch.as_tensor(arr, dtype=dtype, device=device)


def integration_weights(wavelengths: Tensor) -> Tensor:
    """Per-sample widths Δλ (nm) for the Riemann sum ``Σ_λ f(λ) Δλ`` of the camera model (eq. 61).

    Each sample gets the width of its cell, the interval between the midpoints to its neighbours:
    ``Δλ_i = (λ_{i+1} − λ_{i−1}) / 2``, with the end cells taken symmetric about the end samples
    (``Δλ_0 = λ_1 − λ_0``, ``Δλ_{L−1} = λ_{L−1} − λ_{L−2}``). On a uniform grid every weight equals the
    step, which is the plain sum of the paper and of colour-science's ``sd_to_XYZ(method="Integration")``;
    on a non-uniform grid it is the midpoint rule over cells. The weights sum to
    ``λ_{L−1} − λ_0 + (Δλ_0 + Δλ_{L−1}) / 2``.

    Args:
        wavelengths: Strictly increasing wavelengths in nm. Shape ``[L]``, ``L >= 2``.

    Returns:
        The widths in nm, on the dtype and device of ``wavelengths``. Shape ``[L]``.

    Raises:
        ShapeError: not 1-D or fewer than 2 samples.
        ValueRangeError: non-finite, non-positive or not strictly increasing wavelengths.

    Example:
        >>> from torch_interreflect import spectral
        >>> spectral.integration_weights(torch.tensor([400.0, 410.0, 430.0, 440.0])).tolist()
        [10.0, 15.0, 15.0, 10.0]
    """
    wl = check_wavelengths(wavelengths, min_samples=2)
    d = wl[1:] - wl[:-1]
    return torch.cat([d[:1], 0.5 * (d[1:] + d[:-1]), d[-1:]])


def grid_tensor(arr: np.ndarray, like: Any) -> Tensor:
    dtype, device = grid_dtype_device(like)
    return torch.tensor(arr, dtype=dtype, device=device)


def cached_on_grid(fn: Callable[..., np.ndarray], wavelengths: Any, *args: Any) -> Tensor:
    grid = grid_numpy(wavelengths)
    return grid_tensor(fn(*args, tuple(grid.tolist())), wavelengths)
