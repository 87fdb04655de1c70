"""Tests for torch_interreflect.spectral: grids, illuminants, reflectances, sensitivities.

colour-science's own tables and resampling are the oracle."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch

from torch_interreflect import spectral
from torch_interreflect.errors import ShapeError, SpectralDataError, ValueRangeError

DTYPES = [torch.float32, torch.float64]
TOL = {torch.float32: 1e-5, torch.float64: 1e-12}
CC = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]


def _table(sd, grid):
    """Values of a colour data set at grid points that lie on its native sampling (no interpolation)."""
    wl = np.asarray(sd.wavelengths)
    idx = [int(np.flatnonzero(np.isclose(wl, g))[0]) for g in grid]
    return np.asarray(sd.values)[idx]


# --- wavelength grids ------------------------------------------------------------------------------------


def test_default_grid_is_the_papers():
    wl = spectral.wavelengths()
    assert wl.shape == (31,)
    assert wl.dtype == torch.get_default_dtype()
    np.testing.assert_array_equal(wl.numpy(), np.arange(400, 701, 10))


@pytest.mark.parametrize("dtype", DTYPES)
def test_custom_grid(dtype):
    wl = spectral.wavelengths(380, 780, 5, dtype=dtype)
    assert wl.shape == (81,) and wl.dtype == dtype
    assert float(wl[-1]) == 780.0
    assert spectral.wavelengths(400, 705, 10).shape == (31,)  # stop not on the grid: ends at 700


@pytest.mark.parametrize(
    ("args", "err"),
    [((400, 700, 0), ValueRangeError), ((400, 300, 10), ValueRangeError), ((0, 700, 10), ValueRangeError),
     ((400, float("nan"), 10), ValueRangeError)],
)
def test_bad_uniform_grid(args, err):
    with pytest.raises(err):
        spectral.wavelengths(*args)


@pytest.mark.parametrize(
    ("grid", "err", "match"),
    [
        (torch.zeros(2, 3) + 500, ShapeError, "1-D"),
        (torch.tensor([]), ShapeError, "at least one"),
        (torch.tensor([400.0, 500.0, 500.0]), ValueRangeError, "strictly increasing"),
        (torch.tensor([400.0, 380.0]), ValueRangeError, "strictly increasing"),
        (torch.tensor([400.0, float("nan")]), ValueRangeError, "finite"),
        (torch.tensor([400.0, float("inf")]), ValueRangeError, "finite"),
        (torch.tensor([-10.0, 500.0]), ValueRangeError, "positive"),
    ],
)
def test_bad_grids_raise(grid, err, match):
    with pytest.raises(err, match=match):
        spectral.illuminant("D65", grid)
    with pytest.raises(err, match=match):
        spectral.check_wavelengths(grid)


def test_integration_weights():
    w = spectral.integration_weights(spectral.wavelengths(dtype=torch.float64))
    assert torch.all(w == 10.0)
    w = spectral.integration_weights(torch.tensor([400.0, 410.0, 430.0, 440.0]))
    assert w.tolist() == [10.0, 15.0, 15.0, 10.0]
    with pytest.raises(ShapeError, match="at least 2"):
        spectral.integration_weights(torch.tensor([500.0]))


# --- illuminants -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", ["D65", "d50", "A", "D55"])
def test_cie_illuminants_are_100_at_560(name, dtype):
    wl = spectral.wavelengths(dtype=dtype)
    s = spectral.illuminant(name, wl)
    assert s.dtype == dtype and s.shape == (31,)
    assert float(s[16]) == pytest.approx(100.0, abs=1e-5)


def test_named_illuminant_matches_colour_table():
    wl = spectral.wavelengths(dtype=torch.float64)
    for name in ["D65", "A", "FL2", "LED-B1"]:
        s = spectral.illuminant(name, wl)
        np.testing.assert_allclose(s.numpy(), _table(colour.SDS_ILLUMINANTS[name], wl.numpy()), rtol=1e-12)


def test_fluorescent_alias():
    wl = spectral.wavelengths()
    torch.testing.assert_close(spectral.illuminant("F11", wl), spectral.illuminant("FL11", wl))


def test_d_series_by_cct_matches_tables():
    wl = spectral.wavelengths(dtype=torch.float64)
    # D65's nominal CCT on the current c2 is 6500 * 1.4388 / 1.4380 ≈ 6504 K.
    d = spectral.illuminant(6504, wl)
    assert float(d[16]) == pytest.approx(100.0, abs=1e-9)
    assert float((d - spectral.illuminant("D65", wl)).abs().max()) < 0.2
    d50 = spectral.illuminant(5003.0, wl)
    assert float((d50 - spectral.illuminant("D50", wl)).abs().max()) < 0.1


@pytest.mark.parametrize("cct", [3000, 30000, float("nan")])
def test_d_series_cct_out_of_range(cct):
    with pytest.raises(ValueRangeError, match="CCT"):
        spectral.illuminant(cct, spectral.wavelengths())


def test_d_series_grid_outside_basis_raises():
    with pytest.raises(SpectralDataError, match="300"):
        spectral.illuminant(5000, spectral.wavelengths(280, 700, 10))


@pytest.mark.parametrize("temperature", [2856.0, 5500.0, 10000.0])
def test_blackbody_matches_planck(temperature):
    wl = torch.tensor([380.0, 413.3, 500.0, 560.0, 621.0, 780.0, 1500.0], dtype=torch.float64)
    lam = wl.numpy() * 1e-9
    c2 = 1.4388e-2  # m·K, CIE value used by colour
    planck = lam**-5 / np.expm1(c2 / (lam * temperature))
    planck_560 = (560e-9) ** -5 / np.expm1(c2 / (560e-9 * temperature))
    b = spectral.blackbody(temperature, wl)
    np.testing.assert_allclose(b.numpy(), 100 * planck / planck_560, rtol=1e-10)
    torch.testing.assert_close(spectral.illuminant(f"blackbody:{temperature:g}", wl), b)


def test_blackbody_2856_close_to_illuminant_a():
    wl = spectral.wavelengths(dtype=torch.float64)
    a, b = spectral.illuminant("A", wl), spectral.illuminant("Blackbody: 2856 K", wl)
    assert float((a / b - 1).abs().max()) < 2e-3


def test_blackbody_bad_temperature():
    with pytest.raises(ValueRangeError, match="temperature"):
        spectral.blackbody(-5, spectral.wavelengths())
    with pytest.raises(ValueRangeError, match="temperature"):
        spectral.illuminant("blackbody:0", spectral.wavelengths())


def test_unknown_illuminant_lists_close_matches():
    with pytest.raises(SpectralDataError, match="D65") as info:
        spectral.illuminant("D66", spectral.wavelengths())
    assert "Available" in str(info.value)
    with pytest.raises(TypeError):
        spectral.illuminant(None, spectral.wavelengths())  # type: ignore[arg-type]


# --- range handling ----------------------------------------------------------------------------------------


def test_outside_range_raises_by_default_and_extrapolates_on_request():
    wl = torch.tensor([360.0, 380.0, 500.0, 800.0], dtype=torch.float64)
    with pytest.raises(SpectralDataError, match="380–780"):
        spectral.colorchecker(wl)
    const, _ = spectral.colorchecker(wl, extrapolate="constant")
    zero, _ = spectral.colorchecker(wl, extrapolate="zero")
    torch.testing.assert_close(const[:, 0], const[:, 1])
    torch.testing.assert_close(zero[:, 1:3], const[:, 1:3])
    assert torch.all(zero[:, [0, 3]] == 0)
    with pytest.raises(ValueRangeError, match="extrapolate"):
        spectral.colorchecker(wl, extrapolate="linear")  # type: ignore[arg-type]


def test_sigma_range_is_400_680():
    wl = spectral.wavelengths()
    with pytest.raises(SpectralDataError, match="400–680"):
        spectral.camera_sensitivities("Sigma SDMerill (NPL)", wl)
    s = spectral.camera_sensitivities("Sigma SDMerill (NPL)", wl, extrapolate="zero")
    assert torch.all(s[:, -2:] == 0) and torch.all(s[:, -3] > 0)


# --- reflectances ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_colorchecker(dtype):
    wl = spectral.wavelengths(dtype=dtype)
    r, names = spectral.colorchecker(wl)
    assert r.shape == (24, 31) and r.dtype == dtype
    assert names == list(CC.keys()) and len(names) == 24
    assert torch.all((r >= 0) & (r <= 1))
    # Known values of the Ohta data: red at 650 nm, white at 550 nm, blue at 450 nm.
    assert float(r[names.index("red"), 25]) == pytest.approx(0.686, abs=TOL[dtype])
    assert float(r[names.index("white 9.5 (.05 D)"), 15]) == pytest.approx(0.886, abs=TOL[dtype])
    assert float(r[names.index("blue"), 5]) == pytest.approx(0.335, abs=TOL[dtype])
    expected = np.stack([_table(CC[n], wl.double().numpy()) for n in names])
    np.testing.assert_allclose(r.double().numpy(), expected, rtol=TOL[dtype])


def test_reflectance_by_name_and_alias():
    wl = spectral.wavelengths(dtype=torch.float64)
    r, names = spectral.colorchecker(wl)
    for name, row in [("RED", "red"), ("orange", "orange"), ("Blue", "blue"), ("cyan", "cyan"),
                      ("grey", "neutral 5 (.70 D)"), ("gray", "neutral 5 (.70 D)"),
                      ("neutral 5 (.70 D)", "neutral 5 (.70 D)"), ("neutral 8", "neutral 8 (.23 D)"),
                      ("white", "white 9.5 (.05 D)"), ("black", "black 2 (1.5 D)")]:
        torch.testing.assert_close(spectral.reflectance(name, wl), r[names.index(row)], msg=name)
    with pytest.raises(SpectralDataError, match="'red'"):
        spectral.reflectance("redd", wl)


# --- camera sensitivities ----------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_camera_sensitivities_match_colour(dtype):
    wl = spectral.wavelengths(dtype=dtype)
    nikon = spectral.camera_sensitivities("nikon 5100 (npl)", wl)
    assert nikon.shape == (3, 31) and nikon.dtype == dtype
    np.testing.assert_allclose(
        nikon.double().numpy(),
        _table(colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"], wl.double().numpy()).T,
        rtol=TOL[dtype], atol=TOL[dtype],
    )
    xyz = spectral.camera_sensitivities("CIE 1931", wl)
    torch.testing.assert_close(xyz, spectral.camera_sensitivities("CIE 1931 2 Degree Standard Observer", wl))
    np.testing.assert_allclose(
        xyz.double().numpy(),
        _table(colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"], wl.double().numpy()).T,
        rtol=TOL[dtype], atol=TOL[dtype],
    )


def test_unknown_camera():
    with pytest.raises(SpectralDataError, match="Nikon 5100"):
        spectral.camera_sensitivities("Nikon 5000", spectral.wavelengths())


# --- non-uniform grids, dtype/device, caching --------------------------------------------------------------


def test_non_uniform_grid():
    grid = np.array([400.0, 403.7, 455.0, 560.0, 612.5, 650.0, 700.0])
    wl = torch.tensor(grid, dtype=torch.float64)
    # D65 is linearly interpolated by colour (CIE recommendation): np.interp on the table is the oracle.
    d65 = colour.SDS_ILLUMINANTS["D65"]
    np.testing.assert_allclose(
        spectral.illuminant("D65", wl).numpy(), np.interp(grid, d65.wavelengths, d65.values), rtol=1e-12
    )
    # The ColorChecker is Sprague-interpolated: colour's own resampling to 0.1 nm is the oracle.
    fine = colour.colorimetry.reshape_sd(CC["red"], colour.SpectralShape(400, 700, 0.1), method="Interpolate")
    r = spectral.reflectance("red", wl)
    np.testing.assert_allclose(r.numpy(), _table(fine, grid), rtol=1e-9)
    assert spectral.camera_sensitivities("Nikon 5100 (NPL)", wl).shape == (3, 7)
    assert spectral.colorchecker(wl)[0].shape == (24, 7)


@pytest.mark.parametrize("dtype", DTYPES)
def test_dtype_follows_grid_and_float32_matches_float64(dtype):
    wl64 = spectral.wavelengths(dtype=torch.float64)
    for fn in (lambda w: spectral.illuminant("D65", w), lambda w: spectral.colorchecker(w)[0],
               lambda w: spectral.camera_sensitivities("Nikon 5100 (NPL)", w),
               lambda w: spectral.blackbody(3000, w)):
        out = fn(wl64.to(dtype))
        assert out.dtype == dtype and out.device == wl64.device
        torch.testing.assert_close(out.double(), fn(wl64), rtol=1e-6, atol=1e-6)
    # Lists and integer tensors give the default dtype.
    assert spectral.illuminant("D65", [400, 500, 600]).dtype == torch.get_default_dtype()
    assert spectral.illuminant("D65", torch.arange(400, 701, 10)).dtype == torch.get_default_dtype()


def test_cache_returns_fresh_equal_tensors_and_leaves_colour_untouched():
    shapes = (colour.SDS_ILLUMINANTS["D65"].shape, CC["red"].shape,
              colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"].shape,
              colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].shape)
    values = colour.SDS_ILLUMINANTS["D65"].values.copy()
    wl = spectral.wavelengths(400, 700, 7.5)
    a = spectral.illuminant("D65", wl)
    a += 1  # mutating a result must not leak into the cache
    b = spectral.illuminant("D65", wl)
    torch.testing.assert_close(b, a - 1)
    spectral.colorchecker(wl)
    spectral.camera_sensitivities("Nikon 5100 (NPL)", wl)
    spectral.camera_sensitivities("CIE 1931", torch.tensor([400.0, 401.5, 600.0]))
    assert (colour.SDS_ILLUMINANTS["D65"].shape, CC["red"].shape,
            colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"].shape,
            colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].shape) == shapes
    np.testing.assert_array_equal(colour.SDS_ILLUMINANTS["D65"].values, values)
