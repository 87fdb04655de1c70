"""Tests for facets → images (pinhole projection, coverage) and the kornia image operations."""

from __future__ import annotations

import math

import kornia
import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.camera import (
    Projection,
    add_noise,
    blur,
    delta_e,
    look_at,
    project,
    render_image,
    to_lab,
    to_srgb,
    white_balance,
)
from torch_interreflect.errors import ShapeError, ValueRangeError
from torch_interreflect.geometry.scenes import grid_quads

DTYPES = [torch.float32, torch.float64]


def _plane(xs, ys, dtype):
    """A fronto-parallel plane in z = 0 (normal +z) cut into rectangles at the given x and y edges."""
    quads = []
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            quads.append(grid_quads([xs[i], ys[j], 0.0], [xs[i + 1] - xs[i], 0, 0], [0, ys[j + 1] - ys[j], 0], 1, 1)[0])
    return ti.Scene.from_polygons(torch.tensor(np.array(quads), dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("supersample", [1, 3])
def test_fronto_parallel_plane_is_exact(dtype, supersample):
    """Pixel counts × pixel footprint = facet areas exactly, for facet edges on pixel boundaries."""
    d, h, w, fov = 2.0, 12, 16, 30.0
    pix = d * math.tan(math.radians(fov) / 2) / (h / 2)  # footprint of one pixel on the plane (m)
    # the image spans x in [-8, 8] and y in [-6, 6] pixels; the plane covers x in [-6, 5], y in [-4, 6] pixels
    xs = [v * pix for v in (-6, -1, 2, 5)]
    ys = [v * pix for v in (-4, 0, 3, 6)]
    scene = _plane(xs, ys, dtype)
    proj = project(scene, ([0.0, 0.0, d], [0.0, 0.0, 0.0]), h, w, fov_deg=fov, supersample=supersample)
    assert isinstance(proj, Projection) and proj.coverage.layout == torch.sparse_csr
    counts = proj.pixel_counts()
    rtol = 1e-12 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(counts * pix**2, scene.areas, rtol=rtol, atol=0.0)
    assert float(counts.sum()) == pytest.approx(11 * 10, rel=1e-12)
    assert float(proj.background.sum()) == pytest.approx(h * w - 110, rel=1e-12)
    # every pixel is either fully one facet or fully background
    bg = proj.background
    assert bool(((bg == 0) | (bg == 1)).all())
    assert bool(((proj.facet_index >= 0) == (bg == 0)).all())


def test_partial_pixels_are_antialiased():
    """A plane edge through the middle of a pixel column gives coverage ½ there (supersample 2)."""
    d, h, w, fov = 1.0, 4, 4, 60.0
    pix = d * math.tan(math.radians(fov) / 2) / (h / 2)
    scene = _plane([-2 * pix, 0.5 * pix], [-2 * pix, 2 * pix], torch.float64)
    proj = project(scene, ([0.0, 0.0, d], [0.0, 0.0, 0.0]), h, w, fov_deg=fov, supersample=2)
    img = proj(torch.ones(1, 1, dtype=torch.float64))[0, 0]
    # seen from +z with y up, world +x is to the right of the image
    torch.testing.assert_close(img[0], torch.tensor([1.0, 1.0, 0.5, 0.0], dtype=torch.float64))
    torch.testing.assert_close(img + proj.background, torch.ones(h, w, dtype=torch.float64))


def test_back_faces_are_neither_facet_nor_background():
    scene = _plane([-1.0, 1.0], [-1.0, 1.0], torch.float64)
    proj = project(scene, ([0.0, 0.0, -3.0], [0.0, 0.0, 0.0]), 8, 8, supersample=1)  # behind the plane
    assert float(proj.pixel_counts().sum()) == 0.0
    assert float(proj.background.sum()) < 64  # the plane blocks part of the view


@pytest.mark.parametrize("dtype", DTYPES)
def test_render_is_linear_and_differentiable(dtype):
    scene = ti.scenes.v_groove(90.0, divisions=2, dtype=dtype)
    proj = project(scene, ([0.06, 0.03, 0.08], [0.02, 0.03, 0.02]), 10, 12, supersample=2)
    vals = torch.rand(2, scene.num_facets, 3, dtype=dtype, requires_grad=True)
    img = proj(vals)
    assert img.shape == (2, 3, 10, 12) and img.dtype == dtype
    img.sum().backward()
    torch.testing.assert_close(vals.grad[0, :, 0], proj.pixel_counts().to(dtype))
    dense = proj.coverage.to_dense()
    torch.testing.assert_close(img[1, 2].reshape(-1), dense @ vals[1, :, 2].detach())
    back, seen = proj.to_facets(img.detach())
    torch.testing.assert_close(back[:, seen], vals.detach()[:, seen])  # exact inverse on the seen facets
    back, seen = proj.to_facets(proj(torch.ones(scene.num_facets, 3, dtype=dtype)), method="mean")
    assert float(back[0, seen].max()) <= 1.0 + 1e-6 and float(back[0, seen].min()) > 0.9
    # background value
    img_bg = proj(vals.detach(), background_value=torch.tensor([1.0, 0.0, 0.0], dtype=dtype))
    torch.testing.assert_close(img_bg[:, 0] - img[:, 0].detach(), proj.background.expand(2, -1, -1))


def test_projection_moves_with_to():
    scene = ti.scenes.v_groove(90.0, divisions=1)
    proj = project(scene, ([0.05, 0.03, 0.1], [0.03, 0.03, 0.0]), 6, 6, supersample=1).to(torch.float64)
    assert proj.coverage.dtype == torch.float64 and proj.background.dtype == torch.float64
    assert "coverage" not in proj.state_dict()


def test_look_at_conventions():
    cam = look_at([1.0, 2.0, -3.0], [1.0, 2.0, 0.0], 20, 30, fov_deg=50.0)
    assert isinstance(cam, kornia.geometry.camera.PinholeCamera)
    p = cam.project(torch.tensor([[1.0, 2.0, 5.0], [1.0, 3.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(p[0], torch.tensor([14.5, 9.5], dtype=torch.float64))
    assert float(p[1, 1]) < 9.5  # world up is image up (smaller row)
    focal = 10 / math.tan(math.radians(25))
    torch.testing.assert_close(cam.fx[0], torch.tensor(focal, dtype=torch.float64))


def test_projection_errors():
    scene = ti.scenes.v_groove(90.0, divisions=1)
    with pytest.raises(ValueError, match="height"):
        project(scene, ([0, 0, 1], [0, 0, 0]), None, 4)
    with pytest.raises(ValueError, match="supersample"):
        project(scene, ([0, 0, 1], [0, 0, 0]), 4, 4, supersample=0)
    with pytest.raises(ValueRangeError, match="differ"):
        look_at([0, 0, 0], [0, 0, 0], 4, 4)
    with pytest.raises(ValueRangeError, match="parallel"):
        look_at([0, 1, 0], [0, 0, 0], 4, 4)
    with pytest.raises(TypeError, match="PinholeCamera"):
        project(scene, "front", 4, 4)
    proj = project(scene, ([0.05, 0.03, 0.1], [0.03, 0.03, 0.0]), 4, 4, supersample=1)
    with pytest.raises(ShapeError, match="coverage has 2"):
        proj(torch.ones(3, 3))
    with pytest.raises(ShapeError, match="coverage"):
        render_image(torch.ones(5, 2), torch.ones(2, 3), 2, 2)


# ------------------------------------------------------------------------------------------ image operations
@pytest.mark.parametrize("dtype", DTYPES)
def test_image_ops_use_kornia(dtype):
    img = torch.rand(2, 3, 9, 9, dtype=dtype, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(to_srgb(img), kornia.color.linear_rgb_to_rgb(img))
    torch.testing.assert_close(to_lab(img), kornia.color.rgb_to_lab(kornia.color.linear_rgb_to_rgb(img)))
    const = torch.full((1, 3, 9, 9), 0.3, dtype=dtype)
    torch.testing.assert_close(blur(const, 1.5), const)
    torch.testing.assert_close(blur(img, 1.0), kornia.filters.gaussian_blur2d(img, (7, 7), (1.0, 1.0),
                                                                               border_type="reflect"))
    assert float(delta_e(img, img).max()) == 0.0
    assert delta_e(img, img * 0.5).shape == (2, 9, 9)


def test_white_balance_makes_a_grey_surface_neutral():
    wl = ti.spectral.wavelengths(dtype=torch.float64)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
    A = ti.spectral.illuminant("A", wl)
    grey = ti.spectral.reflectance("grey", wl)
    white = cam(A[None] / math.pi)[0]
    # a spectrally flat grey: exactly neutral after balancing
    rgb = cam((0.4 * A)[None] / math.pi)[0].reshape(1, 3, 1, 1)
    out = white_balance(rgb, white).flatten()
    torch.testing.assert_close(out, out[1].expand(3))
    # the ColorChecker grey: near neutral
    rgb = cam((grey * A)[None] / math.pi)[0].reshape(1, 3, 1, 1)
    out = white_balance(rgb, white).flatten()
    assert float((out / out[1] - 1).abs().max()) < 0.05
    with pytest.raises(ValueRangeError, match="positive"):
        white_balance(rgb, torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64))


def test_noise_model_statistics():
    img = torch.full((1, 3, 200, 200), 0.5, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    noisy = add_noise(img, shot=0.01, read=0.02, generator=g)
    var = float((noisy - img).var())
    assert abs(var - (0.01 * 0.5 + 0.02**2)) / (0.01 * 0.5 + 0.02**2) < 0.03
    assert abs(float((noisy - img).mean())) < 3e-3
    torch.testing.assert_close(add_noise(img), img)
    with pytest.raises(ValueRangeError, match="shot"):
        add_noise(img, shot=-1.0)
