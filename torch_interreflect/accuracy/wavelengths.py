"""Spectra for :func:`~torch_interreflect.accuracy.plan`: the grid, the validated inputs, and the nested
wavelength subsets on which the interreflection gain is solved and linearly interpolated in between."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from .. import spectral
from .._checks import broadcast_shapes
from ..camera.sensor import Camera
from ..errors import ShapeError, ValueRangeError

__all__ = ["grid_of", "interp_matrix", "nested_subsets", "spectra"]


def grid_of(camera: Camera | None, wavelengths: Tensor | None, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The wavelength grid ``[L]``: the camera's, else ``wavelengths``, else the default 400–700 nm by 10 nm."""
    if camera is not None:
        return camera.wavelengths.to(dtype=dtype, device=device)
    if wavelengths is not None:
        return spectral.check_wavelengths(wavelengths).to(dtype=dtype, device=device)
    return spectral.wavelengths(dtype=dtype, device=device)


def spectra(grid: Tensor, illuminant: Any, reflectance: Any, F: int) -> tuple[Tensor, Tensor]:
    """Illuminant ``[..., L]`` and reflectance ``[..., F, L]`` on ``grid``, validated."""
    dtype, dev, L = grid.dtype, grid.device, grid.numel()
    if isinstance(illuminant, (str, int, float)) and not isinstance(illuminant, bool):
        S = spectral.illuminant(illuminant, grid).to(dtype=dtype, device=dev)
    else:
        S = torch.as_tensor(illuminant).to(device=dev)
        S = S.to(torch.promote_types(S.dtype, dtype)) if S.is_floating_point() else S.to(dtype)
    if S.ndim == 0 or S.shape[-1] != L:
        raise ShapeError(f"illuminant must be [..., L] with L = {L} (the grid); got {list(S.shape)}")
    r = torch.as_tensor(reflectance, device=dev)
    r = r.to(torch.promote_types(r.dtype, dtype)) if r.is_floating_point() else r.to(dtype)
    if r.ndim >= 2 and r.shape[-2] == F and r.shape[-1] == L:
        pass
    elif r.ndim >= 1 and r.shape[-1] == F:
        r = r[..., None].expand(*r.shape, L)
    else:
        raise ShapeError(f"reflectance must be [..., F, L] or [..., F] with F = {F}, L = {L}; got {list(r.shape)}")
    if r.numel() and (bool((r.detach() < 0).any()) or bool((r.detach() > 1).any())):
        raise ValueRangeError(f"reflectance must lie in [0, 1]; got [{float(r.min()):.3g}, {float(r.max()):.3g}]")
    broadcast_shapes(r.shape[:-2], S.shape[:-1])  # raises on batch shapes that do not broadcast
    return S, r


def interp_matrix(nodes: Tensor, grid: Tensor) -> Tensor:
    """Linear interpolation from ``nodes`` (a subset of ``grid``) to ``grid`` as a matrix ``[L', L]``."""
    i = torch.searchsorted(nodes, grid, right=True).clamp(1, nodes.numel() - 1)
    a, b = nodes[i - 1], nodes[i]
    t = ((grid - a) / (b - a)).clamp(0, 1)
    m = grid.new_zeros(nodes.numel(), grid.numel())
    cols = torch.arange(grid.numel(), device=grid.device)
    m[i - 1, cols] += 1 - t
    m[i, cols] += t
    return m


def nested_subsets(n: int) -> list[Tensor]:
    """Index subsets of a grid of ``n`` samples, coarsest first: every ``2^j``-th sample plus the last."""
    out: list[Tensor] = []
    step = 1
    while step < n:
        step *= 2
    while step >= 1:
        idx = torch.unique(torch.cat([torch.arange(0, n, step), torch.tensor([n - 1])]))
        if idx.numel() >= 2 and (not out or idx.numel() > out[-1].numel()):
            out.append(idx)
        step //= 2
    return out
