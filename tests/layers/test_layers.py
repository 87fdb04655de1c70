"""Tests for the layers: module == functional, gradients, buffers and dtypes, colour-science oracles, errors."""

from __future__ import annotations

import math

import colour
import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.camera import facet_rgb
from torch_interreflect.errors import ShapeError, ValueRangeError
from torch_interreflect.layers import IlluminantBasis, Interreflection, ReflectanceBasis, RGBToSpectrum
from torch_interreflect.lights import light_geometry
from torch_interreflect.spectral.illuminants import (
    cct_to_daylight_coefficients,
    daylight,
    daylight_basis,
    daylight_from_cct,
    planck,
)
from torch_interreflect.spectral.reflectances import reflectance_from_coefficients, rgb_to_spectrum

DTYPES = [torch.float32, torch.float64]
RTOL = {torch.float32: 1e-5, torch.float64: 1e-12}


@pytest.fixture(scope="module")
def groove():
    scene = ti.scenes.v_groove(60.0, divisions=2, dtype=torch.float64)
    return scene, ti.form_factors(scene)


def _wl(dtype):
    return ti.spectral.wavelengths(dtype=dtype)


# ----------------------------------------------------------------------------------------------- illuminant
@pytest.mark.parametrize("cct", [4000.0, 5003.0, 6504.0, 7000.0, 9300.0, 25000.0])
def test_daylight_from_cct_matches_colour(cct):
    wl = _wl(torch.float64)
    xy = colour.temperature.CCT_to_xy_CIE_D(cct)
    sd = colour.sd_CIE_illuminant_D_series(xy, M1_M2_rounding=False)
    expected = np.asarray(sd[wl.numpy()])
    got = daylight_from_cct(torch.tensor(cct, dtype=torch.float64), daylight_basis(wl))
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-10, atol=1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
def test_planck_matches_spectral_blackbody(dtype):
    wl = _wl(dtype)
    for T in (2000.0, 2856.0, 6500.0):
        torch.testing.assert_close(planck(torch.tensor(T, dtype=dtype), wl), ti.spectral.blackbody(T, wl),
                                   rtol=RTOL[dtype] * 10, atol=0.0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_illuminant_module_equals_functional(dtype):
    wl = _wl(dtype)
    basis = daylight_basis(wl)
    m = torch.tensor([[-0.3, -0.7], [0.1, 0.2]], dtype=dtype)
    T = torch.tensor([4500.0, 8000.0], dtype=dtype)
    torch.testing.assert_close(IlluminantBasis(wl)(m), daylight(m, basis))
    torch.testing.assert_close(IlluminantBasis(wl, model="cct")(T), daylight_from_cct(T, basis))
    torch.testing.assert_close(IlluminantBasis(wl, model="blackbody")(T, scale=2.0), 2.0 * planck(T, wl))
    assert IlluminantBasis(wl)(m).dtype == dtype


def test_illuminant_gradients_gradcheck():
    wl = _wl(torch.float64)
    basis = daylight_basis(wl)
    T = torch.tensor([4500.0, 6500.0, 12000.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: daylight_from_cct(t, basis), (T,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda t: planck(t, wl), (T,), fast_mode=True)
    m = torch.tensor([-0.3, -0.7], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: daylight(c, basis), (m,), fast_mode=True)


def test_illuminant_errors():
    wl = _wl(torch.float64)
    with pytest.raises(ValueRangeError, match="4000"):
        cct_to_daylight_coefficients(3000.0)
    with pytest.raises(ValueRangeError, match="> 0"):
        planck(-5.0, wl)
    with pytest.raises(ShapeError, match=r"\[\.\.\., 2\]"):
        daylight(torch.zeros(3), daylight_basis(wl))
    with pytest.raises(ValueError, match="model must be one of"):
        IlluminantBasis(wl, model="led")


# ---------------------------------------------------------------------------------------------- reflectance
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("space", ["linear", "logit"])
def test_reflectance_basis_module_equals_functional(dtype, space):
    wl = _wl(dtype)
    b = ReflectanceBasis(wl, 5, space=space)
    c = torch.randn(4, 7, 5, dtype=dtype, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(b(c), reflectance_from_coefficients(c, b.mean, b.components, space=space))
    out = b(c)
    assert out.shape == (4, 7, 31) and out.dtype == dtype
    assert float(out.min()) >= 0 and float(out.max()) <= 1


def test_reflectance_basis_is_orthonormal_and_encodes():
    wl = _wl(torch.float64)
    b = ReflectanceBasis(wl, 6)
    torch.testing.assert_close(b.components @ b.components.T, torch.eye(6, dtype=torch.float64))
    c = torch.randn(10, 6, dtype=torch.float64) * 0.05  # small: stays inside [0, 1], no clamping
    torch.testing.assert_close(b.encode(b(c)), c)
    cc = ti.spectral.colorchecker(wl)[0]
    err = (b(b.encode(cc)) - cc).pow(2).mean().sqrt()
    assert float(err) < 0.02  # 6 components represent the ColorChecker to 2 % RMS


@pytest.mark.parametrize("dtype", DTYPES)
def test_rgb_to_spectrum_module_equals_functional(dtype):
    wl = _wl(dtype)
    up = RGBToSpectrum(wl)
    rgb = torch.rand(5, 3, dtype=dtype)
    torch.testing.assert_close(up(rgb), rgb_to_spectrum(rgb, up.basis))
    grey = up(torch.full((3,), 0.4, dtype=dtype))
    assert float((grey - 0.4).abs().max()) < 1e-3  # the Mallett basis sums to one
    r = up(torch.rand(100, 3, dtype=dtype))
    assert float(r.min()) >= -1e-6 and float(r.max()) <= 1 + 1e-6


def test_reflectance_errors():
    wl = _wl(torch.float64)
    b = ReflectanceBasis(wl, 3)
    with pytest.raises(ShapeError, match="K = 3"):
        b(torch.zeros(4, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="num_components"):
        ReflectanceBasis(wl, 0)
    with pytest.raises(ValueError, match="space"):
        ReflectanceBasis(wl, 3, space="log")
    with pytest.raises(ShapeError, match=r"\[\.\.\., 3\]"):
        RGBToSpectrum(wl)(torch.zeros(4, 2))


# -------------------------------------------------------------------------------------------------- layer
@pytest.mark.parametrize("dtype", DTYPES)
def test_interreflection_module_equals_functional(groove, dtype):
    scene, ff = groove
    wl = _wl(dtype)
    layer = Interreflection((scene, ff), wl, light=[0.2, 0.0, -1.0]).to(dtype)
    r = ti.spectral.colorchecker(wl)[0][:8].expand(2, -1, -1)
    spd = torch.stack([ti.spectral.illuminant("D65", wl), ti.spectral.illuminant("A", wl)])
    E0 = ti.lights.directional(scene, torch.tensor([0.2, 0.0, -1.0]), spd).to(dtype)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
    expected = facet_rgb(ff.to(dtype), r, E0, cam)
    got = layer(r, spd)
    assert got.shape == (2, 8, 3) and got.dtype == dtype
    torch.testing.assert_close(got, expected, rtol=RTOL[dtype] * 10, atol=0.0)
    torch.testing.assert_close(layer(r, E0=E0), expected, rtol=RTOL[dtype] * 10, atol=0.0)


def test_interreflection_float32_matches_float64(groove):
    scene, ff = groove
    wl = _wl(torch.float64)
    layer = Interreflection((scene, ff), wl)
    r = ti.spectral.colorchecker(wl)[0][8:16]
    D65 = ti.spectral.illuminant("D65", wl)
    out64 = layer(r, D65)
    layer32 = layer.to(torch.float32)
    assert layer32.matrix.dtype == torch.float32 and layer32.camera.sensitivities.dtype == torch.float32
    out32 = layer32(r.float(), D65.float())
    torch.testing.assert_close(out32.double(), out64, rtol=1e-5, atol=0.0)


def test_gradients_reach_basis_coefficients_and_illuminant(groove):
    scene, ff = groove
    wl = _wl(torch.float64)
    basis = ReflectanceBasis(wl, 3, space="logit")
    layer = Interreflection((scene, ff), wl, reflectance_model=basis, per_material=True, method="dense")
    gen = torch.Generator().manual_seed(1)
    coeff = torch.randn(2, 3, dtype=torch.float64, generator=gen).requires_grad_(True)  # per material
    T = torch.tensor(5500.0, dtype=torch.float64, requires_grad=True)
    spd = IlluminantBasis(wl, model="cct")(T)
    rgb = layer(coeff, spd)
    rgb[..., 0].sum().backward()
    assert coeff.grad is not None and bool((coeff.grad != 0).all())
    assert T.grad is not None and float(T.grad) != 0.0
    # gradcheck through the whole layer (adjoint solve) w.r.t. the coefficients
    c = coeff.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: layer(x, spd.detach()), (c,), atol=1e-7, rtol=1e-5, fast_mode=True)


def test_interreflection_infinite_vs_bounces(groove):
    scene, ff = groove
    wl = _wl(torch.float64)
    r = torch.full((8, 31), 0.7, dtype=torch.float64)
    D65 = ti.spectral.illuminant("D65", wl)
    one = Interreflection((scene, ff), wl, bounces=1)(r, D65)
    inf = Interreflection((scene, ff), wl)(r, D65)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
    torch.testing.assert_close(one, cam(r * D65 / math.pi))  # direct light only
    assert bool((inf > one).all())


def test_light_geometry(groove):
    scene, ff = groove
    torch.testing.assert_close(light_geometry(None, ff, "uniform"), torch.ones(8, dtype=torch.float64))
    sky = ti.lights.sky(scene, ff, torch.ones(1, dtype=torch.float64))[:, 0]
    torch.testing.assert_close(light_geometry(None, ff, "sky"), sky)
    d = torch.tensor([0.0, 0.0, -1.0])
    g = light_geometry(scene, ff, d)  # plate B shades part of plate A
    torch.testing.assert_close(g, ti.lights.directional(scene, d, torch.ones(1, dtype=torch.float64))[:, 0])
    assert float(g[:4].max()) == 1.0 and float(g[:4].min()) < 1.0
    mask = scene.material == 0
    torch.testing.assert_close(light_geometry(None, ff, mask), math.pi * ff.to_dense()[:, mask].sum(1))
    torch.testing.assert_close(light_geometry(scene, ff, "plate_a"), light_geometry(None, ff, mask))


def test_per_material_and_projection(groove):
    scene, ff = groove
    wl = _wl(torch.float64)
    proj = ti.camera.project(scene, ([0.05, 0.03, 0.12], [0.03, 0.03, 0.0]), 12, 10, supersample=1)
    layer = Interreflection((scene, ff), wl, per_material=True, projection=proj)
    rm = torch.stack([ti.spectral.reflectance("red", wl), ti.spectral.reflectance("blue", wl)])
    rgb, img = layer(rm[None], ti.spectral.illuminant("D65", wl)[None])
    assert rgb.shape == (1, 8, 3) and img.shape == (1, 3, 12, 10)
    plain = Interreflection((scene, ff), wl)(rm[scene.material][None], ti.spectral.illuminant("D65", wl)[None])
    torch.testing.assert_close(rgb, plain)
    torch.testing.assert_close(img, proj(rgb))


def test_interreflection_errors(groove):
    scene, ff = groove
    wl = _wl(torch.float64)
    layer = Interreflection((scene, ff), wl)
    D65 = ti.spectral.illuminant("D65", wl)
    r = torch.full((8, 31), 0.5, dtype=torch.float64)
    with pytest.raises(ShapeError, match=r"\[\.\.\., 8, 31\]"):
        layer(torch.full((7, 31), 0.5, dtype=torch.float64), D65)
    with pytest.raises(ShapeError, match="L = 31"):
        layer(r, D65[:30])
    with pytest.raises(ValueError, match="exactly one"):
        layer(r)
    with pytest.raises(ValueRangeError, match=r"\[0, 1\]"):
        layer(r * 3, D65)
    with pytest.raises(ValueError, match="light must be"):
        Interreflection((scene, ff), wl, light="sun")
    with pytest.raises(ValueError, match="needs the scene"):
        Interreflection(ff, wl, light=[0.0, 0.0, -1.0])
    with pytest.raises(TypeError, match="Scene, a FormFactors"):
        Interreflection(torch.eye(3), wl)
    with pytest.raises(ValueError, match="bounces"):
        Interreflection((scene, ff), wl, bounces=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_layer_with_a_view_gathers_per_pixel(dtype):
    """``Interreflection(..., view=)``: the image equals render_view of the solved facets (the functional path),
    gradients reach the reflectance, the n-bounce image gathers the (n - 1)-bounce irradiance, and flat shading
    equals the coverage of the facet colours."""
    from torch_interreflect.camera import View, render_view

    wl = ti.spectral.wavelengths(dtype=dtype)
    scene = ti.scenes.v_groove(60.0, divisions=3).to(dtype)
    view = View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=12, width=12)
    S = ti.spectral.illuminant("D65", wl)
    r = torch.full((2, scene.num_facets, wl.numel()), 0.6, dtype=dtype, requires_grad=True)
    layer = Interreflection(scene, wl, light="sky", view=view)
    rgb, image = layer(r, S)
    assert rgb.shape == (2, scene.num_facets, 3) and image.shape == (2, 3, 12, 12) and image.dtype == dtype
    K = ti.form_factors(scene)
    E = ti.solve(K, r[0].detach(), light_geometry(scene, K, "sky")[:, None] * S)
    ref = render_view(scene, r[0].detach(), E, S, layer.camera, view, "sky")
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert float((image[0].detach() - ref).abs().max()) <= tol * float(ref.abs().max())
    image.sum().backward()
    assert r.grad is not None and bool((r.grad[0] != 0).any())
    one = Interreflection(scene, wl, light="sky", view=view, bounces=1)(r.detach()[0], S)[1]
    direct = render_view(scene, r[0].detach(), torch.zeros_like(E), S, layer.camera, view, "sky")
    assert float((one - direct).abs().max()) <= tol * float(direct.abs().max())
    flat = Interreflection(scene, wl, light="sky", view=view, shading="flat")(r.detach()[0], S)[1]
    ref_flat = render_view(scene, r[0].detach(), E, S, layer.camera, view, "sky", shading="flat")
    assert float((flat - ref_flat).abs().max()) <= tol * float(ref_flat.abs().max())


def test_layer_view_errors():
    from torch_interreflect.camera import View

    wl = ti.spectral.wavelengths()
    scene = ti.scenes.v_groove(60.0, divisions=2)
    view = View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=4, width=4)
    with pytest.raises(ValueError, match="view= needs a Scene"):
        Interreflection(ti.form_factors(scene), wl, view=view)
    with pytest.raises(ValueError, match="shading must be"):
        Interreflection(scene, wl, view=view, shading="smooth")
    layer = Interreflection(scene, wl, view=view)
    with pytest.raises(ValueError, match="needs illuminant="):
        layer(torch.full((8, 31), 0.5), E0=torch.ones(8, 31))


def test_layer_view_passes_image_gradients_to_the_angle():
    """The layer's flat image of a groove whose angle requires grad is the rendered coverage times the facets' RGB:
    its gradient is the rendered coverage times the RGB's differences plus the RGB times the exact coverage's
    differences (measured 1.7e-10 relative)."""
    from tests.oracles import polygon_pixel_areas
    from torch_interreflect.camera import View, gather_operator

    wl = ti.spectral.wavelengths(dtype=torch.float64)
    view = View((0.08, 0.045, 0.05), (0.02, 0.045, 0.01), up=(0, 1, 0), fov_deg=60, height=12, width=12)
    r = torch.linspace(0.3, 0.9, 8, dtype=torch.float64)[:, None].expand(8, 31)
    d65 = ti.spectral.illuminant("D65", wl)
    w = torch.rand(3, 12, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    angle = torch.tensor(60.0, dtype=torch.float64, requires_grad=True)
    scene = ti.scenes.v_groove(angle, divisions=2)
    _, image = Interreflection(scene, wl, view=view, shading="flat")(r, d65)
    (g,) = torch.autograd.grad((image * w).sum(), angle)
    rendered = gather_operator(scene, view, shading="flat").coverage.to_dense().T.reshape(8, 12, 12)
    pin = view.pinhole()

    def parts(x: float) -> tuple[torch.Tensor, torch.Tensor]:
        moved = ti.scenes.v_groove(x, divisions=2, dtype=torch.float64)
        with torch.no_grad():
            facet_rgb = Interreflection(moved, wl)(r, d65)  # [8, 3]
        return facet_rgb, torch.stack([polygon_pixel_areas(pin.project(q), 12, 12) for q in moved.corners])

    h = 1e-4
    (rp, cp), (rm, cm), (r0, _) = parts(60.0 + h), parts(60.0 - h), parts(60.0)
    fd = float((torch.einsum("fc,fhw->chw", (rp - rm) / (2 * h), rendered) * w).sum()
               + (torch.einsum("fc,fhw->chw", r0, (cp - cm) / (2 * h)) * w).sum())
    assert abs(fd) > 1e-3
    assert abs(float(g) - fd) <= 1e-9 * abs(fd), (float(g), fd)


def test_layer_view_gradient_terms_follow_double():
    """A float32 layer with a gathered view of a groove whose angle requires grad, moved to float64: the image's
    gradient terms move with it and the backward runs; it agrees with a layer built in float64 (measured 2.4e-8)."""
    from torch_interreflect.camera import View

    view = View((0.08, 0.045, 0.05), (0.02, 0.045, 0.01), up=(0, 1, 0), fov_deg=60, height=8, width=8)
    grads = []
    for build in (torch.float32, torch.float64):
        wl = ti.spectral.wavelengths(dtype=build)
        angle = torch.tensor(60.0, dtype=build, requires_grad=True)
        layer = Interreflection(ti.scenes.v_groove(angle, divisions=2), wl, view=view).double()
        assert layer.image_gradient.edge_weight.dtype == torch.float64
        _, image = layer(torch.full((8, 31), 0.5, dtype=torch.float64), ti.spectral.illuminant("D65", wl.double()))
        grads.append(float(torch.autograd.grad(image.sum(), angle)[0]))
    assert abs(grads[0] - grads[1]) <= 2e-7 * abs(grads[1]), grads
