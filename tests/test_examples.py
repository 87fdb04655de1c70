"""Smoke test: every example runs at reduced size, writes its PNGs and returns sensible numbers."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    "name, argv, pngs",
    [
        ("recolor_cornell", ["--divisions", "1", "--size", "24", "--supersample", "1"],
         ["before.png", "after.png", "bleeding.png"]),
        ("reflectance_recovery", ["--divisions", "1"], ["spectra.png"]),
        ("remove_interreflections", ["--coarse", "--size", "24"],
         ["v_groove/observed.png", "w_shape/direct_basis.png"]),
        ("shape_from_interreflections", ["--divisions", "3", "--refine", "2", "--steps", "15"], ["fit.png"]),
    ],
)
def test_example_runs(tmp_path, capsys, name, argv, pngs):
    results = _load(name).main([*argv, "--out", str(tmp_path)])
    for png in pngs:
        assert (tmp_path / png).stat().st_size > 0
    assert "wrote" in capsys.readouterr().out
    if name == "recolor_cornell":
        assert results["floor_dr"] < 0 < results["floor_db"]  # the floor loses red and gains blue
    elif name == "reflectance_recovery":
        assert results["overall_modelled"] < results["overall_ignored"]
        assert results["overall_spectral"] < 1e-8
    elif name == "shape_from_interreflections":
        # measured: infinite 48.4° / 0.597 (rms 4e-3), two-bounce 51.3° / 0.656 (rms 5e-2); truth 50° / 0.6
        assert abs(results["infinite_angle"] - 50.0) < 5.0 and abs(results["infinite_reflectance"] - 0.6) < 0.01
        assert abs(results["two_bounce_reflectance"] - 0.6) > 3 * abs(results["infinite_reflectance"] - 0.6)
        assert results["infinite_rms"] < 0.3 * results["two_bounce_rms"]
    else:
        for scene in ("v_groove", "w_shape"):
            assert results[f"{scene}_spectral"] < 1e-8
            assert results[f"{scene}_basis"] < results[f"{scene}_channel"] < results[f"{scene}_observed"]


def test_shape_from_mitsuba_recovers_the_shapes():
    """Against the shipped Mitsuba renders, infinite bounces recover the shapes; two bounces do not.

    Measured (40 L-BFGS steps): groove 29.76° / 0.903 (refined leaves 29.93° / 0.901), two-bounce 41.9° / 1.000;
    W fold 43.87° / 4.025 cm / 0.906, two-bounce 54.35° / 4.016 cm / 1.000; truth 30° / 0.9 and 45° / 4 cm / 0.9."""
    r = _load("shape_from_mitsuba").main(["--steps", "40"])
    g, w = "vgroove30_sun_r9", "w_shape_sun_r9"
    assert abs(r[f"{g}/infinite/angle (°)"] - 30.0) < 0.5 and abs(r[f"{g}/infinite/reflectance"] - 0.9) < 0.01
    assert abs(r[f"{g}/refined/angle (°)"] - 30.0) < 0.15 and r[f"{g}/refined/rms"] < 0.5 * r[f"{g}/infinite/rms"]
    assert abs(r[f"{g}/two-bounce/angle (°)"] - 30.0) > 5.0
    assert abs(r[f"{w}/infinite/valley (°)"] - 45.0) < 2.0 and abs(r[f"{w}/infinite/inner (cm)"] - 4.0) < 0.05
    assert abs(r[f"{w}/two-bounce/valley (°)"] - 45.0) > 5.0
    assert r[f"{w}/infinite/rms"] < 0.2 * r[f"{w}/two-bounce/rms"]


def test_sun_from_shadows_needs_the_shadow_edges():
    """Only the table's shadow tells the sun's azimuth: with its edges in the gradient the fit finds it; with the
    cosines only the azimuth stays at its start. Measured (12 × 12 floor, 150 steps): 330.24° / 39.91° against
    290.00° / 36.75°; truth 330° / 40°."""
    r = _load("sun_from_shadows").main(["--divisions", "12", "--steps", "150"])
    edges, cosines = r["shadow edges"], r["cosines only"]
    assert abs(edges["azimuth"] % 360 - 330.0) < 1.5 and abs(edges["elevation"] - 40.0) < 1.0
    assert abs(cosines["azimuth"] - 290.0) < 1e-9
    assert edges["residual"] < 0.1 * cosines["residual"]


def test_shape_from_image_recovers_the_groove(tmp_path):
    """From the shipped 64 × 64 Mitsuba image: infinite bounces recover the angle and the reflectance; two bounces
    overestimate the reflectance; the outline alone moves the angle only through the image's edge terms.

    Measured (10 L-BFGS steps): infinite 40.01° / 0.801, two-bounce 40.30° / 0.884, outline 40.78°, outline without
    edge terms 60.00° (the start); truth 40° / 0.8."""
    r = _load("shape_from_image").main(["--steps", "10", "--out", str(tmp_path)])
    assert (tmp_path / "fit.png").stat().st_size > 0
    assert abs(r["infinite/angle"] - 40.0) < 0.1 and abs(r["infinite/reflectance"] - 0.8) < 0.005
    assert abs(r["two-bounce/reflectance"] - 0.8) > 10 * abs(r["infinite/reflectance"] - 0.8)
    assert abs(r["outline/angle"] - 40.0) < 1.5
    assert r["outline, no edge terms/angle"] == pytest.approx(60.0, abs=1e-12)
