"""Colour-constancy losses and metrics: the recovery angular error and the summaries papers report.

The recovery angular error between an estimated illuminant colour ``ê`` and the true one ``e`` (camera RGB) is
``arccos(ê·e / (|ê| |e|))`` in degrees; it ignores the intensity. Summaries over a test set
(:func:`summarize`) follow FFCC (Barron & Tsai 2017, ``ErrorMetrics.m``): percentiles by MATLAB's ``prctile``
(the ``(k − ½)/n`` plotting positions with linear interpolation, numpy's ``method="hazen"``), then

- ``mean``, ``median`` (50th percentile), ``trimean = (P25 + 2 P50 + P75) / 4``,
- ``best25``: the mean of the errors ``≤ P25``; ``worst25``: the mean of the errors ``≥ P75``;
  ``worst5``: the mean of the errors ``≥ P95``; ``max``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import ShapeError

__all__ = ["SUMMARY_KEYS", "angular_error", "angular_loss", "format_table", "summarize"]

#: Keys of :func:`summarize`, in the order tables show them.
SUMMARY_KEYS: tuple[str, ...] = ("mean", "median", "trimean", "best25", "worst25", "worst5", "max")


def angular_error(estimate: Tensor, target: Tensor, *, eps: float = 1e-9) -> Tensor:
    """Recovery angular error in degrees between illuminant colours (scale-invariant).

    Computed as ``atan2(|ê × e|, ê·e)`` (accurate near 0°, where ``arccos`` loses half the digits); differentiable,
    with a finite gradient at 0°.

    Args:
        estimate: Estimated illuminant RGB. Shape ``[..., 3]``.
        target: True illuminant RGB. Shape ``[..., 3]`` (broadcastable).
        eps: Guards the norms of all-zero vectors.

    Returns:
        Angles in degrees. Shape ``[...]``.

    Raises:
        ShapeError: last dimension not 3.

    Example:
        >>> import torch
        >>> from torch_interreflect.training.metrics import angular_error
        >>> round(float(angular_error(torch.tensor([1.0, 0.0, 0.0]), torch.tensor([1.0, 1.0, 0.0]))), 4)
        45.0
    """
    if estimate.shape[-1] != 3 or target.shape[-1] != 3:
        raise ShapeError(f"estimate and target must be [..., 3]; got {list(estimate.shape)} and {list(target.shape)}")
    e = estimate / estimate.norm(dim=-1, keepdim=True).clamp_min(eps)
    t = target.to(e) / target.to(e).norm(dim=-1, keepdim=True).clamp_min(eps)
    e, t = torch.broadcast_tensors(e, t)
    sin = torch.linalg.vector_norm(torch.linalg.cross(e, t, dim=-1), dim=-1)
    return torch.rad2deg(torch.atan2(sin, (e * t).sum(-1)))


def angular_loss(estimate: Tensor, target: Tensor) -> Tensor:
    """Mean recovery angular error in degrees (a training loss). Shapes as :func:`angular_error`; returns ``[]``."""
    return angular_error(estimate, target).mean()


def summarize(errors: Tensor | np.ndarray | Sequence[float]) -> dict[str, float]:
    """Summary statistics of angular errors as colour-constancy papers report them (FFCC's definitions).

    Args:
        errors: Angular errors in degrees. Shape ``[N]``, ``N ≥ 1``.

    Returns:
        ``{"mean", "median", "trimean", "best25", "worst25", "worst5", "max"}`` in degrees (see the module
        docstring).

    Raises:
        ShapeError: empty input.

    Example:
        >>> from torch_interreflect.training.metrics import summarize
        >>> s = summarize([1.0, 2.0, 3.0, 4.0])
        >>> s["median"], s["trimean"], s["best25"], s["worst25"]
        (2.5, 2.5, 1.0, 4.0)
    """
    e = np.asarray(errors.detach().cpu() if isinstance(errors, Tensor) else errors, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise ShapeError("summarize needs at least one error; got none")
    p25, p50, p75, p95 = np.percentile(e, [25, 50, 75, 95], method="hazen")
    return {
        "mean": float(e.mean()),
        "median": float(p50),
        "trimean": float((p25 + 2 * p50 + p75) / 4),
        "best25": float(e[e <= p25].mean()),
        "worst25": float(e[e >= p75].mean()),
        "worst5": float(e[e >= p95].mean()),
        "max": float(e.max()),
    }


def format_table(rows: dict[str, dict[str, float]], *, keys: Sequence[str] = SUMMARY_KEYS[:5]) -> str:
    """A Markdown table of summaries: one row per method, one column per statistic (degrees)."""
    head = "| method | " + " | ".join(keys) + " |"
    sep = "|---|" + "---:|" * len(keys)
    lines = [head, sep]
    for name, s in rows.items():
        lines.append(f"| {name} | " + " | ".join(f"{s[k]:.2f}" if math.isfinite(s[k]) else "–" for k in keys) + " |")
    return "\n".join(lines)



