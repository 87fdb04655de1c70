"""This library's side of the benchmarks: the functions they time, and the direct light of a reference."""

from __future__ import annotations

from typing import Any

import torch

import torch_interreflect as ti
from torch_interreflect.accuracy import render
from torch_interreflect.errors import AccuracyWarning
from torch_interreflect.geometry import split_at_contacts
from torch_interreflect.solver import solve

__all__ = ["DTYPE", "AccuracyWarning", "direct_light", "render", "solve", "split_and_subdivide"]

#: The benchmarks compute in float64 (the errors measured go down to 1e-5).
DTYPE = torch.float64


def direct_light(scene: Any, form_factors: Any, light: dict, dtype: torch.dtype = DTYPE) -> torch.Tensor:
    """Direct irradiance ``E0 [F, 1]`` of a reference's light (``{"type": "directional" | "sky", …}``).

    Args:
        scene: The (refined) scene.
        form_factors: Its form factors (the sky light needs their row sums).
        light: The reference's light settings: ``direction`` and ``irradiance``, or ``radiance``.
        dtype: Floating dtype.
    """
    if light["type"] == "directional":
        d = torch.tensor(light["direction"], dtype=dtype)
        return ti.lights.directional(scene, d, torch.full((1,), float(light["irradiance"]), dtype=dtype))
    if light["type"] == "sky":
        return ti.lights.sky(scene, form_factors, torch.full((1,), float(light["radiance"]), dtype=dtype))
    raise ValueError(f"unsupported light {light!r}: expected type 'directional' or 'sky'")


def split_and_subdivide(scene: Any, k: int) -> tuple[Any, torch.Tensor]:
    """The scene split at its contact lines, then ``subdivide(k)``: ``(fine, user)`` with ``user [F_fine]`` the
    facet of ``scene`` each fine facet lies in (for :func:`torch_interreflect.geometry.area_average`)."""
    pieces, piece_user = split_at_contacts(scene)
    fine, parent = pieces.subdivide(k)
    return fine, piece_user[parent]
