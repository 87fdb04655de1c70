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


def test_accuracy_benchmark_one_tiny_case(tmp_path: Path) -> None:
    import accuracy as ab

    ref = mr.load_reference("box_corner_sun_r2")
    p = ab.problem(ref)
    finer = ab.finer_solution("box_corner_sun_r2", p, max_facets=200, cache=tmp_path)
    assert finer["levels"] == (1, 2, 3) and (tmp_path / "level_box_corner_sun_r2_k3.npz").exists()
    assert 1 <= finer["order"] <= 2
    case = ab.run_case(p, 2e-2, max_facets=400)
    m = ab.measure(case, ref, finer)
    assert case["irradiance"].shape == (48,) and case["leaves"] >= 48 and case["seconds"] > 0
    assert m["vs_finer"] <= 2e-2 and m["vs_mitsuba_debiased"] <= 2e-2  # a dark scene: easy
    curve = ab.uniform_curve("box_corner_sun_r2", p, finer, max_facets=48, cache=tmp_path)
    assert [c["k"] for c in curve] == [1]
    t, label = ab.cheapest_reaching(curve, 1.0)
    assert label == "k=1" and t == curve[0]["seconds"]
    assert ab.cheapest_reaching(curve, 0.0)[1] == "not reached"
