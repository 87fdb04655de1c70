"""Replicas of the ray-cast parts (what the quadratic planner measures its ray-cast error with, and averages): the
visibility's rays drawn with another seed (:func:`resample_visibility`, :func:`mean_moments`) and the sky's directions
with another rotation (:func:`sky_rays`, :meth:`SkyRays.mean`)."""

import math

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.formfactors.moments import mean_moments, resample_visibility
from torch_interreflect.geometry import split_at_contacts
from torch_interreflect.light_moments import light_moments, sky_rays
from torch_interreflect.solver.moments import facet_averages, solve_moments

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
D = torch.float64


@pytest.fixture(scope="module")
def cornell():
    """The Cornell box split at its contacts (50 pieces): occluded pairs, and every piece's open part ray cast."""
    scene = split_at_contacts(ti.scenes.cornell_box(light=False, dtype=D))[0]
    return scene, moment_form_factors(scene, 2)


def test_mean_of_visibility_replicas(cornell):
    """The mean of two replicas is the mean of their matrices (to rounding); the pairs without rays are the same in
    both; moments of other pairs or settings are refused."""
    scene, K = cornell
    K1 = resample_visibility(K, seed=1)
    M = mean_moments(K, K1)
    assert torch.allclose(M.matrix, 0.5 * (K.matrix + K1.matrix), rtol=0, atol=1e-15)
    assert M.info["rays"] == K.info["rays"] + K1.info["rays"]
    assert not torch.equal(K.matrix, K1.matrix)
    with pytest.raises(ValueError, match="two replicas"):
        mean_moments(K, resample_visibility(K, seed=1, visibility_samples=4))
    with pytest.raises(ValueError, match="two replicas"):
        mean_moments(K, moment_form_factors(scene, 2))


def test_a_replica_is_the_moments_made_with_its_rays(cornell):
    """Drawing the rays again evaluates only the occluded pairs' blocked part (their exact sums are kept): the same
    bits as moments made from scratch with that seed and count, and with the original's own seed its own bits;
    also after a split whose kept pairs were taken from the previous moments (exact sums included)."""
    from torch_interreflect.accuracy.leaves import Leaves, split

    scene, K = cornell
    assert torch.equal(resample_visibility(K, seed=0).matrix, K.matrix)
    for seed, ns in ((1, 3), (2, 5)):
        R = resample_visibility(K, seed=seed, visibility_samples=ns)
        assert torch.equal(R.matrix, moment_form_factors(scene, 2, seed=seed, visibility_samples=ns).matrix)
        assert R.info["rays"] > 0 and R.info["occluded_pairs"] == K.info["occluded_pairs"]
    sel = torch.zeros(scene.num_facets, dtype=torch.bool)
    sel[::5] = True
    leaves = split(Leaves(scene, torch.arange(scene.num_facets)), sel)
    new = moment_form_factors(leaves.scene, 2, reuse=(K, leaves.kept))
    assert new.info["reused_pairs"] > 0  # occluded ones among them: without their exact sums, 0.65 off
    assert torch.equal(resample_visibility(new, seed=3).matrix, moment_form_factors(leaves.scene, 2, seed=3).matrix)


def test_sky_replicas_and_their_mean(cornell):
    """Seed 0 is the light's own rotation (the same rays as before seeds existed); another seed rotates every facet's
    samples; the light of the mean of two replicas is the mean of their lights (it is affine in the rays); the mean
    of replicas on other facets is refused."""
    scene, K = cornell
    a = sky_rays(scene, K, samples=8)
    assert a.escape_ids.numel() > 0
    assert torch.equal(light_moments(scene, K, "sky", sky_samples=8), light_moments(scene, K, "sky", sky=a))
    b = sky_rays(scene, K, samples=8, seed=1)
    assert not torch.equal(a.escape, b.escape)
    ga, gb = light_moments(scene, K, "sky", sky=a), light_moments(scene, K, "sky", sky=b)
    assert torch.allclose(light_moments(scene, K, "sky", sky=a.mean(b)), 0.5 * (ga + gb), rtol=0, atol=1e-15)
    other = sky_rays(scene, moment_form_factors(scene, 2, occlusion=False), samples=8)
    with pytest.raises(ValueError, match="same facets"):
        a.mean(other)


def test_the_replicas_spread_measures_their_error(cornell):
    """Half the change between two replicas is the RMS error of their mean: on the Cornell box's pieces (8 points ×
    8 directions per axis; reference: the mean of two replicas at 23 × 23), for the pairs of seeds (0, k) that the
    planner draws, k = 1..8, measured 0.57–1.99 times the error per pair, geometric mean 1.05 on the sky's moments
    and 0.85 / 1.01 on the solved outputs at r = 0.9 / 0.2; the pieces with under 5 % of the most sky left out."""
    scene, K = cornell
    ref = 0.5 * sum(light_moments(scene, K, "sky", sky_samples=23, sky_points=23, sky_seed=k) for k in (100, 101))
    lit = ref[:, 0] > 0.05 * ref[:, 0].max()
    assert 20 < int(lit.sum()) < scene.num_facets

    def out(g, r):
        return facet_averages(solve_moments(K, torch.full((scene.num_facets,), r, dtype=D), g[..., None]))[:, 0]

    replicas = [light_moments(scene, K, "sky", sky_samples=8, sky_points=8, sky_seed=k) for k in range(9)]
    for f in (lambda g: g[:, 0], lambda g: out(g, 0.9), lambda g: out(g, 0.2)):
        R, a = f(ref)[lit], f(replicas[0])[lit]
        logs = []
        for g in replicas[1:]:
            b = f(g)[lit]
            spread = 0.5 * ((a - b) / R).square().mean().sqrt()
            logs.append(math.log(float(spread / ((0.5 * (a + b) - R) / R).square().mean().sqrt())))
        assert 0.7 < math.exp(sum(logs) / len(logs)) < 1.4


def test_seeds_rotate_every_facet_independently():
    """Seed 0 is each facet's own rotation (the samples before seeds existed); another seed draws every facet's
    rotation afresh: the shift between two seeds varies from facet to facet (a linear hash shifts all alike)."""
    from torch_interreflect.formfactors.hemisphere import _rotation
    from torch_interreflect.formfactors.sampling import pair_seeds

    f = torch.arange(500)
    assert torch.equal(_rotation(f, 0), pair_seeds(f, f))
    shift = (_rotation(f, 1) - _rotation(f, 0)) % 1.0
    assert float(shift.std(0).min()) > 0.25  # uniform on [0, 1): 0.29
    r1, r2 = _rotation(f, 1), _rotation(f, 2)
    assert float(torch.corrcoef(torch.stack([r1[:, 0], r2[:, 0]]))[0, 1].abs()) < 0.15
