"""The any-illuminant basis: non-negative spectra, representation floors per family against the daylight model."""

from __future__ import annotations

import pytest
import torch

from torch_interreflect import spectral
from torch_interreflect.training.floors import daylight_floors, representation_floors

WL = spectral.wavelengths(400, 700, 10, dtype=torch.float64)


@pytest.fixture(scope="module")
def floors() -> dict:
    return representation_floors(WL)


def test_every_family_is_within_half_a_degree(floors: dict) -> None:
    # measured (K = 12, Nikon 5100): white max 0.067° (measured lamps), ColorChecker-mean max 0.34°
    assert set(floors) == set(spectral.ILLUMINANT_FAMILIES)
    for fam, s in floors.items():
        assert s["white_max"] <= 0.2, (fam, s)
        assert s["colorchecker_max"] <= 1.0, (fam, s)


def test_the_daylight_model_could_not_reach_them(floors: dict) -> None:
    old = daylight_floors(WL)
    # measured: blackbody 2000–10000 K white max 5.7°, fluorescent F1–F12 2.6°, measured lamps 14°
    assert old["blackbody"]["white_max"] > 2.0 and old["F1-F12"]["white_max"] > 1.0
    assert all(floors[f]["white_max"] < 0.2 * old[f]["white_max"] for f in ("blackbody", "F1-F12", "LED", "HP"))


def test_decoded_spectra_are_non_negative_and_differentiable(dtype: torch.dtype) -> None:
    wl = WL.to(dtype)
    mean, comps, scale = spectral.illuminant_basis(wl)
    assert mean.dtype == dtype and comps.shape == (12, 31) and scale.shape == (12,)
    c = (10.0 * torch.randn(5, 12, dtype=dtype, generator=torch.Generator().manual_seed(0))).requires_grad_(True)
    s = spectral.illuminant_from_coefficients(c, mean, comps, scale)
    assert s.shape == (5, 31) and bool((s >= 0).all())
    s.sum().backward()
    assert torch.isfinite(c.grad).all()
    with pytest.raises(ValueError, match="must agree"):
        spectral.illuminant_from_coefficients(c[:, :3], mean, comps, scale)
