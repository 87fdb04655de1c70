"""Inverse tools recover ground truth on synthetic data (known geometry and light), within stated tolerances."""

from __future__ import annotations

import math

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ShapeError, ValueRangeError
from torch_interreflect.inverse import (
    estimate_illuminant,
    estimate_reflectance,
    recolor,
    reflectance_from_radiance,
    remove_interreflections,
)
from torch_interreflect.layers import Interreflection, ReflectanceBasis, RGBToSpectrum
from torch_interreflect.solver import radiance, solve

DTYPES = [torch.float32, torch.float64]
#: tolerance on recovered reflectance / radiance of the exact (closed-form) tools
EXACT_TOL = {torch.float32: 1e-4, torch.float64: 1e-9}
#: tolerance on reflectance recovered from RGB by alternating least squares (solver tol 1e-6 → ~1e-6)
LSQ_TOL = {torch.float32: 2e-3, torch.float64: 1e-5}


@pytest.fixture(scope="module")
def groove():
    scene = ti.scenes.v_groove(45.0, divisions=3, dtype=torch.float64)
    return scene, ti.form_factors(scene)


@pytest.fixture(scope="module")
def wshape():
    scene = ti.scenes.w_shape(divisions=(2, 4, 2), dtype=torch.float64)
    return scene, ti.form_factors(scene)


def _truth(n, wl, seed=0):
    """Reflectances in the Mallett RGB basis (so the basis can represent them exactly), in [0.05, 0.95]."""
    g = torch.Generator().manual_seed(seed)
    rgb = 0.05 + 0.9 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    return RGBToSpectrum(wl)(rgb.to(wl.dtype))


# --------------------------------------------------------------------------------------------- spectral exact
@pytest.mark.parametrize("dtype", DTYPES)
def test_reflectance_from_radiance_exact(wshape, dtype):
    scene, ff = wshape
    wl = ti.spectral.wavelengths(dtype=dtype)
    ff = ff.to(dtype)
    r = ti.spectral.colorchecker(wl)[0][torch.arange(scene.num_facets) % 24]
    E0 = ti.lights.directional(scene, torch.tensor([0.3, 0.2, -1.0]), ti.spectral.illuminant("D65", wl))
    L = radiance(solve(ff, r, E0, tol=1e-12 if dtype == torch.float64 else 1e-6), r)
    lit = (E0[:, 0] > 0) | (ff.matmul(math.pi * L)[:, 0] > 0)
    got = reflectance_from_radiance(ff, L, E0)
    torch.testing.assert_close(got[lit], r[lit], rtol=0, atol=EXACT_TOL[dtype])
    est = estimate_reflectance(ff, L, E0=E0)
    torch.testing.assert_close(est.reflectance, got)


@pytest.mark.parametrize("dtype", DTYPES)
def test_remove_interreflections_spectral_exact(wshape, dtype):
    scene, ff = wshape
    wl = ti.spectral.wavelengths(dtype=dtype)
    ff = ff.to(dtype)
    r = _truth(scene.num_facets, wl, seed=1)
    E0 = ti.lights.directional(scene, torch.tensor([0.3, 0.2, -1.0]), ti.spectral.illuminant("D65", wl))
    L = radiance(solve(ff, r, E0, tol=1e-12 if dtype == torch.float64 else 1e-6), r)
    direct = remove_interreflections(ff, L, E0)
    expected = radiance(E0, r)
    scale = float(expected.abs().max())
    torch.testing.assert_close(direct / scale, expected / scale, rtol=0, atol=EXACT_TOL[dtype])
    assert float((L - expected).abs().max()) / scale > 0.05  # the observed image does contain interreflection


# ------------------------------------------------------------------------------------------------ RGB inverse
@pytest.mark.parametrize("dtype", DTYPES)
def test_estimate_reflectance_alternating_recovers_truth(groove, dtype):
    scene, ff = groove
    wl = ti.spectral.wavelengths(dtype=dtype)
    layer = Interreflection((scene, ff), wl).to(dtype)
    r = _truth(scene.num_facets, wl)
    D65 = ti.spectral.illuminant("D65", wl)
    obs = layer(r, D65)
    est = estimate_reflectance(layer, obs, D65)
    assert est.converged and est.coefficients.shape == (scene.num_facets, 3)
    torch.testing.assert_close(est.reflectance, r, rtol=0, atol=LSQ_TOL[dtype])
    # ignoring interreflection (bounces=1) over-estimates the reflectance by much more
    naive = estimate_reflectance(layer, obs, D65, bounces=1)
    assert float((naive.reflectance - r).abs().max()) > 100 * LSQ_TOL[dtype]
    assert bool((naive.reflectance.mean(-1) >= r.mean(-1) - 1e-6).all())


def test_estimate_reflectance_gradient_with_logit_basis(groove):
    scene, ff = groove
    wl = ti.spectral.wavelengths(dtype=torch.float64)
    basis = ReflectanceBasis(wl, 3, space="logit")
    layer = Interreflection((scene, ff), wl)
    g = torch.Generator().manual_seed(3)
    c_true = 0.5 * torch.randn(scene.num_facets, 3, generator=g, dtype=torch.float64)
    r = basis(c_true)
    D65 = ti.spectral.illuminant("D65", wl)
    obs = layer(r, D65)
    est = estimate_reflectance(layer, obs, D65, basis=basis, method="gradient", steps=200)
    assert est.residual < 1e-6
    torch.testing.assert_close(est.reflectance, r, rtol=0, atol=1e-4)


@pytest.mark.parametrize("dtype", DTYPES)
def test_remove_interreflections_rgb(wshape, dtype):
    scene, ff = wshape
    wl = ti.spectral.wavelengths(dtype=dtype)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
    ff = ff.to(dtype)
    r = _truth(scene.num_facets, wl, seed=2)
    E0 = ti.lights.directional(scene, torch.tensor([0.3, 0.2, -1.0]), ti.spectral.illuminant("D65", wl))
    obs = cam(radiance(solve(ff, r, E0), r))
    truth = cam(radiance(E0, r))
    scale = float(truth.max())
    # exact in the basis
    got = remove_interreflections(ff, obs, E0, camera=cam, basis=RGBToSpectrum(wl))
    torch.testing.assert_close(got / scale, truth / scale, rtol=0, atol=LSQ_TOL[dtype])
    # per-channel approximation: much closer than the observation, not exact
    approx = remove_interreflections(ff, obs, E0, camera=cam)
    err_obs = float((obs - truth).abs().max()) / scale
    err_approx = float((approx - truth).abs().max()) / scale
    assert err_approx < 0.25 * err_obs


@pytest.mark.parametrize("parametrisation, true_param", [("cct", 5000.0), ("coefficients", 6500.0),
                                                         ("blackbody", 3200.0)])
def test_estimate_illuminant(groove, parametrisation, true_param):
    scene, ff = groove
    wl = ti.spectral.wavelengths(dtype=torch.float64)
    layer = Interreflection((scene, ff), wl)
    r = ti.spectral.colorchecker(wl)[0][torch.arange(scene.num_facets) % 24]
    if parametrisation == "blackbody":
        spd = 3.0 * ti.spectral.blackbody(true_param, wl)
    else:
        spd = 3.0 * ti.spectral.illuminant(true_param, wl)
    obs = layer(r, spd)
    est = estimate_illuminant(layer, r, obs, parametrisation=parametrisation, init=5500.0)
    assert est.residual < 1e-5  # the renderer solves to 1e-6
    assert abs(float(est.scale) - 3.0) < 3e-3
    assert abs(float(est.cct) - true_param) < 0.005 * true_param
    torch.testing.assert_close(est.spectrum, spd, rtol=1e-3, atol=0.0)


def test_recolor_matches_full_rerender_and_bleeds(groove):
    scene, ff = groove
    wl = ti.spectral.wavelengths(dtype=torch.float64)
    layer = Interreflection((scene, ff), wl)
    grey = ti.spectral.reflectance("grey", wl).expand(scene.num_facets, -1)
    red = ti.spectral.reflectance("red", wl)
    D65 = ti.spectral.illuminant("D65", wl)
    out = recolor(layer, grey, "plate_a", red, D65)
    on_a = scene.material == 0
    r_new = torch.where(on_a[:, None], red, grey)
    torch.testing.assert_close(out.reflectance, r_new)
    torch.testing.assert_close(out.rgb, layer(r_new, D65))
    # plate B (unchanged) turns redder: its red channel rises relative to blue
    before = layer(grey, D65)
    ratio_before = before[~on_a, 0] / before[~on_a, 2]
    ratio_after = out.rgb[~on_a, 0] / out.rgb[~on_a, 2]
    assert bool((ratio_after > ratio_before * 1.01).all())
    # observed + change
    obs = before * 1.1
    out2 = recolor(layer, grey, on_a, red, D65, observed=obs)
    torch.testing.assert_close(out2.rgb, obs + out.change)


def test_inverse_errors(groove):
    scene, ff = groove
    wl = ti.spectral.wavelengths(dtype=torch.float64)
    layer = Interreflection((scene, ff), wl)
    D65 = ti.spectral.illuminant("D65", wl)
    n = scene.num_facets
    with pytest.raises(ShapeError, match="F = 18"):
        estimate_reflectance(layer, torch.ones(5, 3, dtype=torch.float64), D65)
    with pytest.raises(ValueError, match="method"):
        estimate_reflectance(layer, torch.ones(n, 3, dtype=torch.float64), D65, method="newton")
    with pytest.raises(ValueError, match="exactly one"):
        estimate_reflectance(layer, torch.ones(n, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="needs E0"):
        estimate_reflectance(ff, torch.ones(n, 31, dtype=torch.float64))
    with pytest.raises(ValueRangeError, match="non-negative"):
        reflectance_from_radiance(ff, -torch.ones(n, 31, dtype=torch.float64), torch.ones(n, 31, dtype=torch.float64))
    with pytest.raises(TypeError, match="FormFactors"):
        remove_interreflections(ff.to_dense(), torch.ones(n, 31), torch.ones(n, 31))
    with pytest.raises(ValueError, match="parametrisation"):
        estimate_illuminant(layer, torch.full((n, 31), 0.5, dtype=torch.float64),
                            torch.ones(n, 3, dtype=torch.float64), parametrisation="led")
    with pytest.raises(ValueError, match="unknown material"):
        recolor(layer, torch.full((n, 31), 0.5, dtype=torch.float64), "wall", D65, D65)
    with pytest.raises(ShapeError, match="K = 9"):
        recolor(layer, torch.full((n, 31), 0.5, dtype=torch.float64), "plate_a",
                torch.full((3, 31), 0.5, dtype=torch.float64), D65)
