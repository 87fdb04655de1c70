"""The sky through the openings (:func:`torch_interreflect.sky_openings.sky_through_openings`)."""

from __future__ import annotations

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ShapeError
from torch_interreflect.formfactors.moments import moment_form_factors
from torch_interreflect.light_moments import light_moments
from torch_interreflect.sky_openings import sky_through_openings


@pytest.mark.parametrize("build", [lambda: ti.scenes.v_groove(30.0, divisions=3, dtype=torch.float64),
                                   lambda: ti.scenes.box_corner(divisions=2, dtype=torch.float64)])
@pytest.mark.parametrize("degree", [0, 2])
def test_unoccluded_it_is_one_minus_the_row_sums(build, degree):
    """Nothing blocks: the open part is 1 − Σ_j F exactly, so the two quadratures agree (measured 3e-7 of the
    largest entry at tol 1e-8)."""
    scene = build()
    via_openings = sky_through_openings(scene, degree, quadrature_tol=1e-8)
    rows = light_moments(scene, moment_form_factors(scene, degree, quadrature_tol=1e-8), "sky")
    assert via_openings.shape == rows.shape == (scene.num_facets, (1, 3, 6)[degree])
    assert float((via_openings - rows).abs().max()) < 1e-6 * float(rows.abs().max())


def test_occluded_it_agrees_with_the_escaping_rays():
    """The Cornell box (its blocks hide the opening from parts of the floor and walls; the floor under them sees
    nothing): both estimates are unbiased, so they agree within their sampling errors (RMS difference of the facet
    averages measured 5.7e-4 to 7.2e-4 of π over three seeds, with 8² rays per point against 32² directions from 16²
    points)."""
    scene = ti.scenes.cornell_box(light=False, dtype=torch.float64)
    g = sky_through_openings(scene, 0, quadrature_tol=1e-6, visibility_samples=8)[:, 0]
    K = moment_form_factors(scene, 0, quadrature_tol=1e-6, visibility_samples=8)
    esc = light_moments(scene, K, "sky", sky_samples=32, sky_points=16)[:, 0]
    assert float((g - esc).square().mean().sqrt()) < 1.5e-3 * torch.pi
    assert float(esc.min()) == 0.0 and float(g.abs().min()) < 1e-3  # a covered piece of floor


def test_none_where_the_openings_cannot_be_told():
    assert sky_through_openings(ti.scenes.w_shape(dtype=torch.float64)) is None


def test_moments_across_a_mask_are_the_full_moments_on_those_pairs():
    scene = ti.scenes.box_corner(divisions=2, dtype=torch.float64)
    F = scene.num_facets
    mask = torch.arange(F) < 4
    full = moment_form_factors(scene, 1).matrix.reshape(F, 3, F, 3)
    part = moment_form_factors(scene, 1, across=mask).matrix.reshape(F, 3, F, 3)
    cross = mask[:, None] != mask[None, :]
    assert torch.allclose(part[cross[:, None, :, None].expand_as(part)],
                          full[cross[:, None, :, None].expand_as(full)], rtol=0, atol=1e-15)
    assert float(part[~cross[:, None, :, None].expand_as(part)].abs().max()) == 0.0
    with pytest.raises(ShapeError, match="across"):
        moment_form_factors(scene, 1, across=mask[:-1])


def test_a_float32_scene_gives_the_same_light_in_float64():
    """Computed in float64 from the scene's corners: a float32 scene moves it by its own rounding of the corners
    (measured 3.8e-4 of 2.3, the largest entry, on the Cornell box at degree 2; the same rays)."""
    scene = ti.scenes.cornell_box(light=False, dtype=torch.float64)
    g = sky_through_openings(scene, 2, visibility_samples=4)
    g32 = sky_through_openings(scene.to(torch.float32), 2, visibility_samples=4)
    assert g32.dtype == torch.float64
    assert float((g32 - g).abs().max()) < 1e-3 * float(g.abs().max())
