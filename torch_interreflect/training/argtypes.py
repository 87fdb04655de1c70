"""``argparse`` types of the ``generate`` and ``train-cc`` options: each checks its value and, when it is out of
range, raises :class:`argparse.ArgumentTypeError` with a one-line message (what was expected, what came)."""

from __future__ import annotations

import argparse

from .config import parse_shard

__all__ = [
    "bounce_count", "fraction", "image_size", "nonnegative_int", "positive_float", "positive_int", "shard", "workers",
]


def _int(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected {what}; got {text!r}") from exc


def positive_int(text: str) -> int:
    """An integer ≥ 1.

    Example:
        >>> from torch_interreflect.training.argtypes import positive_int
        >>> positive_int("3")
        3
    """
    v = _int(text, "an integer >= 1")
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text!r}")
    return v


def nonnegative_int(text: str) -> int:
    """An integer ≥ 0."""
    v = _int(text, "an integer >= 0")
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0; got {text!r}")
    return v


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        v = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a number > 0; got {text!r}") from exc
    if not 0.0 < v < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0; got {text!r}")
    return v


def fraction(text: str) -> float:
    """A number strictly between 0 and 1."""
    try:
        v = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1); got {text!r}") from exc
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1); got {text!r}")
    return v


def image_size(text: str) -> tuple[int, int]:
    """``"HxW"`` → ``(H, W)``, both ≥ 1.

    Example:
        >>> from torch_interreflect.training.argtypes import image_size
        >>> image_size("48x64")
        (48, 64)
    """
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected HxW with positive integers (e.g. 64x64); got {text!r}") from exc
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"expected HxW with positive integers (e.g. 64x64); got {text!r}")
    return h, w


def bounce_count(text: str) -> int | None:
    """``"inf"`` (also ``"infinite"``, ``"none"``) → ``None``; otherwise an integer ≥ 1."""
    if text.lower() in ("inf", "infinite", "none"):
        return None
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected 'inf' or an integer >= 1; got {text!r}")
    return v


def shard(text: str) -> tuple[int, int]:
    """``"i/n"`` → ``(i, n)`` with ``0 <= i < n``."""
    try:
        return parse_shard(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def workers(text: str) -> int | str:
    """``"auto"`` or an integer ≥ 1 (worker processes of ``generate``).

    Example:
        >>> from torch_interreflect.training.argtypes import workers
        >>> workers("auto"), workers("2")
        ('auto', 2)
    """
    if text.strip().lower() == "auto":
        return "auto"
    v = _int(text, "'auto' or an integer >= 1")
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer >= 1; got {text!r}")
    return v
