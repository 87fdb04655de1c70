"""Fast checks of the speed-against-error benchmark's plumbing (Mitsuba parts skip without the bench extra)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import mitsuba_ref as mr  # noqa: E402


def _square() -> tuple[np.ndarray, np.ndarray]:
    c = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]], np.float64)
    return c, np.array([False])


def test_cached_references_match_their_scenes() -> None:
    names = mr.reference_names()
    if not names:
        pytest.skip("no cached references")
    for name in names:
        ref = mr.load_reference(name)
        st = ref["settings"]
        assert np.all(np.isfinite(ref["irradiance"])) and np.all(ref["irradiance"] > 0)
        assert st["rel_noise_rms"] < 1e-3
        if "builder" in st:
            assert ref["irradiance"].shape == (st["num_facets"],)
            assert mr.build_scene(st).num_facets == st["num_facets"]


def test_time_at_error_interpolates_and_extrapolates() -> None:
    from speed_vs_error import time_at_error

    pts = [(0.04, 0.1), (0.02, 0.4), (0.01, 1.6)]
    assert time_at_error(pts, 0.02) == pytest.approx(0.4)
    assert time_at_error(pts, 0.005) == pytest.approx(6.4)  # t ∝ e⁻² beyond the curve
    assert math.isnan(time_at_error(pts, 0.08))  # above the curve: fixed costs rule, no extrapolation
    assert math.isnan(time_at_error(pts, 0.0))


@pytest.mark.skipif(not mr.available("llvm_ad_mono"), reason="Mitsuba 3 (bench extra) not installed")
def test_mitsuba_sky_on_open_square_is_pi() -> None:
    r = mr.MitsubaReference(_square(), 0.5, mr.Sky(1.0)).render(256, seed=1)
    assert r.irradiance[0] == pytest.approx(math.pi, rel=1e-5)


@pytest.mark.skipif(not mr.available("llvm_ad_mono"), reason="Mitsuba 3 (bench extra) not installed")
def test_mitsuba_perpendicular_squares_form_factor() -> None:
    floor = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    wall = np.array([[0, 0, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1]], np.float64)
    two = (np.stack([floor, wall]), np.array([False, False]))
    # sun on the wall only, floor black, wall white: E_floor = F(floor -> wall) * E_wall = 0.2000438
    r = mr.MitsubaReference(two, np.array([0.0, 1.0]), mr.Directional((-1.0, 0.0, 0.0), 1.0)).render(1 << 15, seed=2)
    assert r.irradiance[1] == pytest.approx(1.0, abs=1e-12)  # direct only, nothing reflects onto it
    assert abs(r.irradiance[0] - 0.2000438) < 5 * r.stderr[0] + 1e-4
