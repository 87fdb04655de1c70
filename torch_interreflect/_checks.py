"""Shared validators used by every stage: each raises a typed error from :mod:`.errors` naming what was
expected and what came."""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .errors import DeviceError, ShapeError, ValueRangeError

__all__ = [
    "as_float_tensor",
    "as_real_tensor",
    "broadcast_shapes",
    "check_count",
    "check_finite",
    "check_indices",
    "check_nonnegative",
    "check_reflectance",
    "check_same_device",
    "describe_index",
]


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """:func:`torch.broadcast_shapes` of sizes (sequences of non-negative ints) without the import of sympy that its
    first call makes (0.26 s per process): numpy's broadcasting rule.

    Raises:
        ShapeError: The shapes do not broadcast (a ``ValueError``; :func:`torch.broadcast_shapes` raises a
            ``RuntimeError``).

    Example:
        >>> from torch_interreflect._checks import broadcast_shapes
        >>> broadcast_shapes((2, 1, 3), (4, 3))
        torch.Size([2, 4, 3])
    """
    try:
        return torch.Size(np.broadcast_shapes(*(tuple(int(d) for d in s) for s in shapes)))
    except ValueError as exc:
        raise ShapeError(f"shapes {[list(s) for s in shapes]} do not broadcast") from exc


def check_count(value: Any, name: str, *, minimum: int = 1, optional: bool = False, note: str = "") -> int | None:
    """``value`` as an ``int >= minimum`` (a count: samples, rays per side, a stride); ``None`` passes when
    ``optional``.

    Anything but an integer (Python or numpy; not a bool, not a float, even a whole one: callers may use the value
    as given), or one below ``minimum``, is a :class:`ValueRangeError` (a ``ValueError``) naming ``name`` (and
    ``note``, e.g. the unit).

    Example:
        >>> import numpy as np
        >>> check_count(4, "samples"), check_count(np.int64(2), "k"), check_count(None, "edge", optional=True)
        (4, 2, None)
    """
    if optional and value is None:
        return None
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool) and int(value) >= minimum
    if not ok:
        raise ValueRangeError(f"{name} must be {'None or ' if optional else ''}an integer >= {minimum}{note}; got "
                              f"{value!r}")
    return int(value)



def as_float_tensor(x: Tensor | float, name: str, like: Tensor | None = None) -> Tensor:
    if isinstance(x, Tensor):
        if not x.is_floating_point():
            x = x.to(torch.get_default_dtype() if like is None else like.dtype)
        return x
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise TypeError(f"{name} must be a number or a floating tensor; got {type(x).__name__}")
    if like is not None:
        return torch.tensor(float(x), dtype=like.dtype, device=like.device)
    return torch.tensor(float(x), dtype=torch.get_default_dtype())


def as_real_tensor(x: Any, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        try:
            x = torch.as_tensor(np.asarray(x))
        except Exception as exc:
            raise TypeError(f"{name} must be a tensor; got {type(x).__name__}") from exc
    if x.is_complex():
        raise TypeError(f"{name} must be real; got dtype {x.dtype}")
    return x


def describe_index(t: Tensor, flat_index: int, facet_dim: int) -> str:
    coord = np.unravel_index(flat_index, tuple(t.shape))
    facet = int(coord[facet_dim])
    rest = [int(c) for i, c in enumerate(coord) if i != facet_dim % t.ndim]
    return f"facet {facet}" + (f" (other indices {rest})" if any(rest) else "")


def check_finite(t: Tensor, name: str, facet_dim: int) -> None:
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        k = int(torch.nonzero(bad.reshape(-1))[0])
        raise ValueRangeError(
            f"{name} must be finite; got {float(t.reshape(-1)[k])} at {describe_index(t, k, facet_dim)} "
            f"({int(bad.sum())} non-finite values)"
        )


def check_reflectance(r: Tensor) -> None:
    """``r`` is ``[..., F, L]``."""
    check_finite(r, "reflectance", -2)
    if r.numel() == 0:
        return
    flat = r.detach().reshape(-1)
    hi, lo = int(flat.argmax()), int(flat.argmin())
    if float(flat[hi]) > 1:
        raise ValueRangeError(
            f"reflectance must lie in [0, 1]; got max {float(flat[hi]):.6g} at {describe_index(r, hi, -2)}"
        )
    if float(flat[lo]) < 0:
        raise ValueRangeError(
            f"reflectance must lie in [0, 1]; got min {float(flat[lo]):.6g} at {describe_index(r, lo, -2)}"
        )


def check_nonnegative(t: Tensor, name: str, facet_dim: int, what: str = "irradiance") -> None:
    """Finite and ``>= 0`` everywhere (light: irradiance, spectra); the message names the first offending facet."""
    check_finite(t, name, facet_dim)
    if t.numel() == 0:
        return
    flat = t.detach().reshape(-1)
    lo = int(flat.argmin())
    if float(flat[lo]) < 0:
        raise ValueRangeError(
            f"{name} must be >= 0 ({what} cannot be negative); got {float(flat[lo]):.6g} at "
            f"{describe_index(t, lo, facet_dim)} ({int((flat < 0).sum())} negative values)"
        )


def check_same_device(device: torch.device, owner: str, **tensors: Tensor) -> None:
    """Every tensor on ``device`` (the device of ``owner``); nothing is moved between devices silently."""
    for name, t in tensors.items():
        if t.device != device:
            raise DeviceError(
                f"{name} is on {t.device}; expected {device}, the device of {owner} (nothing is moved between "
                f"devices silently): move one of them, e.g. {name}.to({str(device)!r})"
            )


def check_indices(idx: Any, size: int, name: str) -> Tensor:
    """``idx`` as int64 indices ``[k]`` in ``[0, size)`` on the CPU; :class:`ShapeError` for anything but a 1-D
    integer tensor (a bool mask included), :class:`ValueRangeError` for an index out of range."""
    if (not isinstance(idx, Tensor) or idx.ndim != 1 or idx.dtype == torch.bool or idx.is_floating_point()
            or idx.is_complex()):
        got = f"{idx.dtype} {list(idx.shape)}" if isinstance(idx, Tensor) else type(idx).__name__
        raise ShapeError(f"{name} must be an integer tensor [k] of indices; got {got}")
    out = idx.detach().to("cpu", torch.int64)
    if out.numel() and (int(out.min()) < 0 or int(out.max()) >= size):
        raise ValueRangeError(f"{name} must lie in [0, {size}); got [{int(out.min())}, {int(out.max())}]")
    return out
