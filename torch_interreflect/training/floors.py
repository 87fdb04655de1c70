"""Representation floors of an illuminant model: the best camera-RGB angular error it can reach, per family.

:func:`representation_floors` fits the code of every test spectrum (:func:`~torch_interreflect.spectral.
coefficients_from_illuminant`), decodes it and measures, through the generator's :class:`~torch_interreflect.Camera`,

- ``white``: the angular error of the illuminant's camera RGB (a white diffuser: the colour-constancy target), and
- ``colorchecker``: the mean over the 24 ColorChecker patches of the angular error of their camera RGB (what a
  re-rendering through the interreflection model needs).

The test spectra are off the fitting grid: CIE daylight every 37 K on 4000–25000 K, blackbodies every 33 K on
2000–10000 K (the fit used 100 K and 50 K steps), and every tabulated family of
:func:`~torch_interreflect.spectral.illuminant_library`. :func:`daylight_floors` measures the previous model (CIE
daylight ``(M1, M2)``) on the same spectra, by the best ``(M1, M2)`` for the RGB.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import spectral
from ..camera.sensor import Camera
from .metrics import angular_error

__all__ = ["daylight_floors", "floor_test_spectra", "format_floors", "representation_floors"]


def floor_test_spectra(wavelengths: Tensor) -> tuple[Tensor, list[str]]:
    """``(spectra [N, L], families [N])``: the test spectra of the module docstring (mean 1 each)."""
    wl = wavelengths.to(torch.float64)
    specs, fams = [], []
    for t in np.arange(4000.0, 25000.0, 37.0):
        specs.append(spectral.illuminant(float(t), wl))
        fams.append("daylight")
    for t in np.arange(2000.0, 10000.0, 33.0):
        specs.append(spectral.illuminant(f"blackbody:{float(t)!r}", wl))
        fams.append("blackbody")
    lib, _, lib_fams = spectral.illuminant_library(wl, daylight_cct=(4000.0, 4000.0, 1.0),
                                                   blackbody_t=(2000.0, 2000.0, 1.0))
    keep = [i for i, f in enumerate(lib_fams) if f not in ("daylight", "blackbody")]
    x = torch.cat([torch.stack(specs), lib[keep]])
    x = x / x.mean(-1, keepdim=True)
    return x, fams + [lib_fams[i] for i in keep]


def _errors(decoded: Tensor, target: Tensor, camera: Camera, wl: Tensor) -> tuple[Tensor, Tensor]:
    refl = spectral.colorchecker(wl)[0]  # [24, L]
    white = angular_error(camera(decoded), camera(target))
    cc = angular_error(camera(decoded[:, None] * refl), camera(target[:, None] * refl)).mean(-1)
    return white, cc


def _table(white: Tensor, cc: Tensor, fams: list[str]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for f in dict.fromkeys(fams):
        m = torch.tensor([g == f for g in fams])
        out[f] = {"count": int(m.sum()), "white_mean": float(white[m].mean()), "white_max": float(white[m].max()),
                  "colorchecker_mean": float(cc[m].mean()), "colorchecker_max": float(cc[m].max())}
    return out


def representation_floors(
    wavelengths: Tensor, camera: str = "Nikon 5100 (NPL)", num_components: int = 12
) -> dict[str, dict[str, float]]:
    """Per family: ``count``, ``white_mean`` / ``white_max`` and ``colorchecker_mean`` / ``_max`` (degrees).

    Args:
        wavelengths: Grid in nm (the generator's). Shape ``[L]``.
        camera: Camera name (the generator's).
        num_components: ``K`` of :func:`~torch_interreflect.spectral.illuminant_basis`.
    """
    wl = wavelengths.to(torch.float64)
    cam = _camera(camera, wl)
    basis = spectral.illuminant_basis(wl, camera, num_components)
    x, fams = floor_test_spectra(wl)
    codes = spectral.coefficients_from_illuminant(x, basis, cam.sensitivities.to(wl), wl)
    decoded = spectral.illuminant_from_coefficients(codes, *basis)
    return _table(*_errors(decoded, x, cam, wl), fams)


def _camera(camera: str, wl: Tensor) -> Camera:
    try:
        return Camera.from_colour(camera, wl)
    except ValueError:
        return Camera.from_colour(camera, wl, extrapolate="zero")


def daylight_floors(wavelengths: Tensor, camera: str = "Nikon 5100 (NPL)") -> dict[str, dict[str, float]]:
    """As :func:`representation_floors` for the previous model: CIE daylight ``(M1, M2)`` in the box it could output
    (``M1`` in [−1.8, 3.2], ``M2`` in [−1, 3]), by a grid search for the best white."""
    wl = wavelengths.to(torch.float64)
    cam = _camera(camera, wl)
    x, fams = floor_test_spectra(wl)
    basis = spectral.daylight_basis(wl)
    m1, m2 = torch.meshgrid(torch.linspace(-1.8, 3.2, 251, dtype=torch.float64),
                            torch.linspace(-1.0, 3.0, 201, dtype=torch.float64), indexing="ij")
    cand = spectral.daylight(torch.stack([m1, m2], -1).reshape(-1, 2), basis).clamp_min(0.0)
    rgb_c = torch.nn.functional.normalize(cam(cand), dim=-1)
    rgb_x = torch.nn.functional.normalize(cam(x), dim=-1)
    best = (rgb_x @ rgb_c.T).argmax(-1)
    decoded = cand[best]
    decoded = decoded / decoded.mean(-1, keepdim=True).clamp_min(1e-12)
    return _table(*_errors(decoded, x, cam, wl), fams)


def format_floors(floors: dict[str, dict[str, Any]], title: str) -> str:
    """A markdown table of :func:`representation_floors`."""
    rows = [f"| {title} | n | white mean (°) | white max (°) | ColorChecker mean (°) | ColorChecker max (°) |",
            "|---|---:|---:|---:|---:|---:|"]
    for f, s in floors.items():
        rows.append(f"| {f} | {s['count']} | {s['white_mean']:.3f} | {s['white_max']:.3f} | "
                    f"{s['colorchecker_mean']:.3f} | {s['colorchecker_max']:.3f} |")
    return "\n".join(rows) + "\n"
