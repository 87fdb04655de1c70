"""row_variance: the binomial bound on the variance of each facet's row sum from the moments' ray-cast visibility,
against the variance measured over replicas."""

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.formfactors.moment_noise import row_variance
from torch_interreflect.formfactors.moments import MomentFormFactors, mean_moments, resample_visibility
from torch_interreflect.geometry import split_at_contacts

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
D = torch.float64


def test_zero_without_rays():
    K = moment_form_factors(ti.scenes.v_groove(60.0, divisions=2, dtype=D), 2)
    assert K.info["occluded_pairs"] == 0 and torch.equal(row_variance(K), torch.zeros(8, dtype=D))


def test_against_the_variance_of_replicas():
    """The Cornell box split at its contacts (50 pieces, every one with a ray-cast pair): over 24 replicas of the
    visibility the bound is 0.94 times the measured variance of the row sums (geometric mean over the facets; 0.06 to
    3.5 between the 10th and 90th percentiles: it counts samples, not the kernel's spread over them). The mean of two
    replicas has about half the variance (measured 0.62 of the bound of one)."""
    scene = split_at_contacts(ti.scenes.cornell_box(light=False, dtype=D))[0]
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
    F, nb = scene.num_facets, K.size

    def rows(M):
        return M.matrix.reshape(F, nb, F, nb)[:, 0, :, 0].sum(1)

    measured = torch.stack([rows(resample_visibility(K, seed=s)) for s in range(1, 25)]).var(0)
    bound = row_variance(K)
    occ = K.info["occluded_facets"]
    assert bool(occ.all()) and bool((bound > 0).all())
    ratio = (bound / measured).numpy()
    assert 0.5 < float(np.exp(np.log(ratio).mean())) < 2.0
    halved = row_variance(mean_moments(K, resample_visibility(K, seed=99))) / bound
    assert 0.4 < float(halved.mean()) < 0.8
    assert row_variance(MomentFormFactors(K.matrix, K.areas, K.basis, {})) is None  # no pairs' sums: unknown
