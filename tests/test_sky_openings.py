"""The sky through the openings (:func:`torch_interreflect.sky_openings.sky_through_openings`)."""

from __future__ import annotations

import pytest
import torch

import torch_interreflect as ti
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


def test_a_float32_scene_gives_the_same_light_in_float64():
    """Computed in float64 from the scene's corners: a float32 scene moves it by its own rounding of the corners
    (measured 3.8e-4 of 2.3, the largest entry, on the Cornell box at degree 2; the same rays)."""
    scene = ti.scenes.cornell_box(light=False, dtype=torch.float64)
    g = sky_through_openings(scene, 2, visibility_samples=4)
    g32 = sky_through_openings(scene.to(torch.float32), 2, visibility_samples=4)
    assert g32.dtype == torch.float64
    assert float((g32 - g).abs().max()) < 3e-4 * float(g.abs().max())


def test_sky_rays_take_the_openings_where_they_are_told():
    """``sky_rays(..., openings=True)``: the open part of every facet from the openings (the light equals
    :func:`sky_through_openings` bit for bit with the same rays, :data:`OPENING_SAMPLES` of the count), the back
    coverage for the rows' estimate where a back may be in view; where the openings cannot be told, the escaping rays
    as before."""
    from torch_interreflect.geometry._polygon import facing_any
    from torch_interreflect.light_moments import OPENING_SAMPLES, sky_rays

    box = ti.scenes.cornell_box(light=False, dtype=torch.float64)
    K = moment_form_factors(box, 2, quadrature_tol=1e-4)
    sky = sky_rays(box, K, samples=8, points=4, openings=True, rows=True)
    assert torch.equal(sky.escape_ids, torch.arange(box.num_facets)) and sky.back_ids.numel() == 0
    assert sky.opening_rays is not None and sky.opening_rays > 0
    g = light_moments(box, K, "sky", sky=sky)
    n = round(8 * OPENING_SAMPLES)  # rays per side of the opening for 8 sky directions per axis
    assert torch.equal(g, sky_through_openings(box, 2, quadrature_tol=1e-4, visibility_samples=n))
    back = sky.escape_back.abs().sum(1) > 0
    assert bool(back.any()) and not bool((back & ~facing_any(box, one_way=True)).any())
    assert bool((sky.escape_back[:, 0] <= 1.0 + 1e-12).all())
    w = ti.scenes.w_shape(dtype=torch.float64)
    assert sky_rays(w, moment_form_factors(w, 0), samples=4, points=2, openings=True).opening_rays is None


def test_sky_rays_leave_the_openings_where_the_rows_are_exact(monkeypatch):
    """No pair ray cast and no back in view (a V-groove): ``1 − Σ_j F`` is the open part with no rays, so
    ``sky_rays(..., openings=True)`` neither computes the openings' moments nor casts a ray, and the light is the
    rows' (the same as without openings). Moments made without occlusion still go to the openings."""
    import torch_interreflect.light_moments as lm

    groove = ti.scenes.v_groove(30.0, divisions=3, dtype=torch.float64)
    K = moment_form_factors(groove, 2, quadrature_tol=1e-8)
    calls = []
    monkeypatch.setattr(lm, "sky_through_openings", lambda *a, **k: calls.append(a))
    sky = lm.sky_rays(groove, K, samples=8, points=4, openings=True)
    assert calls == [] and sky.opening_rays is None
    assert sky.escape_ids.numel() == 0 and sky.back_ids.numel() == 0
    assert torch.equal(light_moments(groove, K, "sky", sky=sky), light_moments(groove, K, "sky"))
    # moments without occlusion mark no pair as ray cast whatever blocks: their rows are not known exact there
    lm.sky_rays(groove, moment_form_factors(groove, 2, occlusion=False), samples=8, points=4, openings=True)
    assert len(calls) == 1


def test_a_facet_facing_out_of_the_scene_sees_all_of_the_sky():
    """The open room's cabinet back, against the wall and facing out: the escaping rays count all of its view (the
    Mitsuba reference lights it so); the openings alone would give 0."""
    from torch_interreflect.geometry.openings import facing_out

    room = ti.scenes.room(1.0, lamp=False, ceiling=False, dtype=torch.float64)
    out = facing_out(room)
    g = sky_through_openings(room, 1, quadrature_tol=1e-3, visibility_samples=2)
    expected = torch.zeros(int(out.sum()), 3, dtype=torch.float64)
    expected[:, 0] = torch.pi
    assert torch.equal(g[out], expected)
    K = moment_form_factors(room, 0, quadrature_tol=1e-3, visibility_samples=2)
    esc = light_moments(room, K, "sky", sky_samples=8, sky_points=4)[:, 0]
    assert torch.allclose(esc[out], torch.full_like(esc[out], torch.pi))
