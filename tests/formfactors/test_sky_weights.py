"""The sky's open part on facets that are both ray cast and may see a back: the escaping rays' estimate and the rows'
estimate ``1 − Σ_j F − b`` weighted by the inverse of their variances (:func:`sky_weights`)."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.geometry import area_average, split_at_contacts, subdivide_to
from torch_interreflect.light_moments import light_moments, sky_rays, sky_weights
from torch_interreflect.solver.moments import facet_averages, solve_moments

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
D = torch.float64


def _pieces(name, size):
    """A stored converged Mitsuba reference's scene split at contacts and cut to ``size``."""
    refs = Path(__file__).resolve().parents[2] / "benchmarks" / "references"
    spec = json.loads((refs / f"{name}.json").read_text())
    scene = getattr(ti.scenes, spec["builder"])(**spec["kwargs"], dtype=D)
    reference = torch.from_numpy(np.load(refs / f"{name}.npz")["irradiance"].astype(np.float64))
    split, user = split_at_contacts(scene)
    fine, parent = subdivide_to(split, size)
    return scene, spec, reference, fine, user[parent]


def test_the_light_is_the_weighted_mean_of_the_two_estimates():
    *_, fine, _ = _pieces("cornell_sky_r9", 0.3)
    K = moment_form_factors(fine, 2, quadrature_tol=1e-4)
    rays = sky_rays(fine, K, samples=8, points=8)
    w = sky_weights(K, rays)
    ids = rays.escape_ids
    assert ids.numel() > 0 and bool(((w >= 0) & (w <= 1)).all()) and 0.05 < float(w.mean()) < 0.95
    g = light_moments(fine, K, "sky", sky=rays) / math.pi
    F, nb = fine.num_facets, K.size
    rows = -K.matrix.reshape(F, nb, F, nb)[ids, :, :, 0].sum(2) - rays.escape_back
    rows[:, 0] += 1.0
    torch.testing.assert_close(g[ids], w[:, None] * rays.escape + (1 - w[:, None]) * rows, rtol=1e-12, atol=1e-15)
    # escaping rays alone where the rows' variance is unknown (moments without their pairs' sums)
    bare = dataclasses.replace(K, info={k: v for k, v in K.info.items() if k != "_sums"})
    assert torch.equal(sky_weights(bare, rays), torch.ones(ids.numel(), dtype=D))
    # more rays per facet: more weight on the escaping ones
    assert bool((sky_weights(K, dataclasses.replace(rays, rays=4 * rays.rays)) >= w).all())


@pytest.mark.parametrize(("name", "mixed", "alone"), [("cornell_sky_r9", 5.8e-4, 2.4e-3),
                                                      ("cornell_sky_r2", 1.9e-3, 3.2e-3)])
def test_closer_to_mitsuba_than_escaping_rays_alone(name, mixed, alone):
    """The Cornell box split at contacts and cut to 0.15 m (267 pieces), 8 × 8 sky rays per axis, 3 × 3 visibility
    rays: RMS error from the converged Mitsuba reference (noise 0.02 %) measured 0.058 % / 0.19 % (r = 0.9 / 0.2)
    weighted, against 0.24 % / 0.32 % with the escaping rays alone (over 4 seeds: 0.061 % / 0.24 % against
    0.20 % / 0.29 %)."""
    scene, spec, reference, fine, user = _pieces(name, 0.15)
    K = moment_form_factors(fine, 2, quadrature_tol=1e-4)
    rays = sky_rays(fine, K, samples=8, points=8)
    refl = torch.full((fine.num_facets, 1), spec["reflectance"], dtype=D)

    def error(sky):
        c = solve_moments(K, refl, (light_moments(fine, K, "sky", sky=sky) * spec["light"]["radiance"])[..., None])
        e = area_average(facet_averages(c), user, fine.areas, scene.num_facets)[:, 0]
        return float(((e - reference) / reference).square().mean().sqrt())

    only_escape = dataclasses.replace(rays, rays=0)  # no weight known: the escaping rays alone
    assert error(rays) <= 1.1 * mixed and error(only_escape) >= 0.9 * alone
