"""Error metrics, number formats, the machine line and result writing shared by the benchmark reports."""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["debias", "fmt_e", "fmt_t", "loadavg", "machine", "rel_errors", "write_lines"]


def rel_errors(values: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Relative RMS and max error of ``values`` against ``ref`` (per element, relative to ``|ref|``)."""
    rel = (np.asarray(values, np.float64).reshape(ref.shape) - ref) / np.abs(ref)
    return float(np.sqrt(np.mean(rel**2))), float(np.abs(rel).max())


def debias(rmse: float, noise: float) -> float:
    """An RMS error with the reference's own RMS noise removed in quadrature (0 when the noise explains it)."""
    return math.sqrt(max(rmse**2 - noise**2, 0.0))


def fmt_t(t: float) -> str:
    """Seconds for a table: ``"–"`` when not finite, ms below a second, whole seconds from 100 s."""
    if not math.isfinite(t):
        return "–"
    return f"{t * 1e3:.0f} ms" if t < 1 else f"{t:.2f} s" if t < 100 else f"{t:.0f} s"


def fmt_e(e: float) -> str:
    """A relative error in percent for a table (three decimals below 1 %)."""
    return f"{100 * e:.3f} %" if e < 0.01 else f"{100 * e:.2f} %"


def loadavg() -> str:
    """The 1/5/15-minute load averages (``"?"`` where unknown)."""
    try:
        return " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "?"


def machine() -> str:
    """One line naming the machine: node, processor, cores, Python and torch versions."""
    import torch

    return (f"{platform.node() or 'this machine'}, {platform.processor() or platform.machine() or 'CPU'}, "
            f"{os.cpu_count()} cores, Python {platform.python_version()}, torch {torch.__version__}")


def write_lines(path: Path, lines: Sequence[str]) -> Path:
    """Write a report (its folder created), say so on stdout, return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines).rstrip("\n") + "\n")
    print(f"wrote {path}")
    return path
