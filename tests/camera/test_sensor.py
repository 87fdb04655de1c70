"""Tests for the spectral camera (eq. 61), with colour-science as the numpy oracle."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch

from torch_interreflect import spectral
from torch_interreflect.camera import Camera, spectral_to_rgb
from torch_interreflect.errors import ShapeError, SpectralDataError

DTYPES = [torch.float32, torch.float64]
RTOL = {torch.float32: 1e-5, torch.float64: 1e-12}
SHAPE = colour.SpectralShape(400, 700, 10)


def _colour_scene():
    """D65 x ColorChecker and the Nikon sensitivities, resampled by colour itself (not by our code)."""
    d65 = colour.colorimetry.reshape_sd(colour.SDS_ILLUMINANTS["D65"], SHAPE, method="Interpolate")
    cc = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    refl = np.stack(
        [colour.colorimetry.reshape_sd(sd, SHAPE, method="Interpolate").values for sd in cc.values()]
    )
    nikon = colour.colorimetry.reshape_msds(
        colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"], SHAPE, method="Interpolate"
    )
    return d65, refl, nikon


@pytest.mark.parametrize("dtype", DTYPES)
def test_nikon_rgb_matches_numpy_oracle(dtype):
    d65, refl, nikon = _colour_scene()
    radiance_np = d65.values[None] * refl / np.pi  # [24, 31]
    expected = radiance_np @ nikon.values * SHAPE.interval  # Σ_λ C_k L Δλ, Δλ = 10 nm

    wl = spectral.wavelengths(dtype=dtype)
    radiance = spectral.illuminant("D65", wl) * spectral.colorchecker(wl)[0] / torch.pi
    cam = Camera.from_colour("Nikon 5100 (NPL)", wl)
    rgb = cam(radiance)
    assert rgb.shape == (24, 3) and rgb.dtype == dtype
    np.testing.assert_allclose(rgb.double().numpy(), expected, rtol=RTOL[dtype] * 10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_cie_1931_matches_colour_sd_to_xyz(dtype):
    d65, _, _ = _colour_scene()
    cmfs = colour.colorimetry.reshape_msds(
        colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"], SHAPE, method="Interpolate"
    )
    wl = spectral.wavelengths(dtype=dtype)
    cam = Camera.from_colour("CIE 1931", wl)
    for patch in ["red", "cyan", "neutral 5 (.70 D)"]:
        sd = colour.colorimetry.reshape_sd(
            colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"][patch], SHAPE, method="Interpolate"
        )
        # With k given colour computes XYZ = k Σ R S x̄ Δλ / 100 (Δλ = the grid interval, our convention);
        # k = 100 undoes the percentage scaling.
        expected = colour.sd_to_XYZ(sd, cmfs, d65, k=100, method="Integration")
        radiance = spectral.illuminant("D65", wl) * spectral.reflectance(patch, wl)
        np.testing.assert_allclose(cam(radiance).double().numpy(), expected, rtol=RTOL[dtype] * 10)


def test_non_uniform_grid_uses_cell_widths():
    wl = torch.tensor([400.0, 420.0, 430.0, 470.0, 560.0, 600.0, 700.0], dtype=torch.float64)
    weights = np.array([20.0, 15.0, 25.0, 65.0, 65.0, 70.0, 100.0])
    np.testing.assert_allclose(spectral.integration_weights(wl).numpy(), weights)
    cam = Camera.from_colour("Nikon 5100 (NPL)", wl)
    radiance = torch.rand(2, 5, 7, dtype=torch.float64)
    expected = np.einsum("bfl,kl->bfk", radiance.numpy(), cam.sensitivities.numpy() * weights)
    np.testing.assert_allclose(cam(radiance).numpy(), expected, rtol=1e-12)


def test_non_uniform_fine_grid_converges_to_uniform_result():
    # A fine grid refined near 550 nm integrates a smooth spectrum like a fine uniform grid.
    uniform = spectral.wavelengths(400, 700, 1, dtype=torch.float64)
    graded = torch.cat(
        [torch.arange(400, 500, 2.0), torch.arange(500, 600, 0.5), torch.arange(600, 700.1, 2.5)]
    ).double()
    out = []
    for wl in (uniform, graded):
        radiance = spectral.illuminant("D65", wl) * spectral.reflectance("orange", wl)
        out.append(Camera.from_colour("CIE 1931", wl)(radiance))
    torch.testing.assert_close(out[1], out[0], rtol=5e-3, atol=0)


def test_shapes_broadcast():
    wl = spectral.wavelengths()
    cam = Camera.from_colour("Nikon 5100 (NPL)", wl)
    assert cam(torch.rand(4, 6, 10, 31)).shape == (4, 6, 10, 3)
    assert cam(torch.rand(31)).shape == (3,)
    x = torch.rand(2, 3, 31)
    torch.testing.assert_close(cam(x)[1, 2], cam(x[1, 2]))
    # The functional form and the module agree.
    torch.testing.assert_close(spectral_to_rgb(x, cam.sensitivities, wl), cam(x))


def test_mismatched_radiance_raises_with_both_numbers():
    cam = Camera.from_colour("Nikon 5100 (NPL)", spectral.wavelengths())
    with pytest.raises(ShapeError, match=r"L = 31.*got last dimension 30"):
        cam(torch.rand(5, 30))
    with pytest.raises(ShapeError, match="31"):
        spectral_to_rgb(torch.rand(5, 31), torch.rand(3, 30), spectral.wavelengths())
    with pytest.raises(ShapeError, match="weights"):
        spectral_to_rgb(torch.rand(5, 31), torch.rand(3, 31), spectral.wavelengths(), weights=torch.ones(30))
    with pytest.raises(TypeError, match="floating"):
        cam(torch.ones(5, 31, dtype=torch.int64))


def test_bad_camera_construction():
    wl = spectral.wavelengths()
    with pytest.raises(ShapeError, match=r"L = 31.*\[3, 30\]"):
        Camera(torch.rand(3, 30), wl)
    with pytest.raises(ShapeError, match="at least 2"):
        Camera(torch.rand(3, 1), torch.tensor([550.0]))
    with pytest.raises(SpectralDataError, match="unknown camera"):
        Camera.from_colour("Canon 5D", wl)
    with pytest.raises(SpectralDataError, match="400–680"):
        Camera.from_colour("Sigma SDMerill (NPL)", wl)
    sigma = Camera.from_colour("Sigma SDMerill (NPL)", wl, extrapolate="zero")
    assert sigma(torch.ones(31)).shape == (3,)


def test_module_buffers_move_with_to_and_dtype_follows_radiance():
    cam = Camera.from_colour("Nikon 5100 (NPL)", spectral.wavelengths(dtype=torch.float32))
    assert set(cam.state_dict()) == {"sensitivities", "wavelengths", "weights"}
    assert cam.weights.dtype == torch.float32 and torch.all(cam.weights == 10)
    cam64 = cam.to(torch.float64)
    assert cam64.sensitivities.dtype == cam64.wavelengths.dtype == cam64.weights.dtype == torch.float64
    x = torch.rand(7, 31, dtype=torch.float64)
    out = cam64(x)
    assert out.dtype == torch.float64
    # A float32 camera applied to float32 radiance agrees with float64 to float32 precision.
    cam32 = Camera.from_colour("Nikon 5100 (NPL)", spectral.wavelengths(dtype=torch.float32))
    torch.testing.assert_close(cam32(x.float()).double(), out, rtol=1e-5, atol=1e-5)
    assert "Nikon 5100 (NPL)" in repr(cam)


def test_gradcheck():
    wl = spectral.wavelengths(400, 700, 50, dtype=torch.float64)
    radiance = torch.rand(2, 3, 7, dtype=torch.float64, requires_grad=True)
    sens = torch.rand(3, 7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r, s: spectral_to_rgb(r, s, wl), (radiance, sens))
    cam = Camera(sens.detach(), wl)
    assert torch.autograd.gradcheck(cam, (radiance,))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda():
    wl = spectral.wavelengths(device="cuda")
    radiance = spectral.illuminant("D65", wl) * spectral.colorchecker(wl)[0]
    assert radiance.device.type == "cuda"
    cam = Camera.from_colour("Nikon 5100 (NPL)", spectral.wavelengths()).to("cuda")
    rgb = cam(radiance)
    assert rgb.device.type == "cuda"
    torch.testing.assert_close(rgb.cpu(), cam.cpu()(radiance.cpu()))
