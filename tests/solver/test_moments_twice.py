"""Two solves of one moment system on one factorisation (:func:`solve_moments_twice`): the same answers and
gradients as two :func:`solve_moments`, and the second solve factors nothing."""

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.light_moments import light_moments
from torch_interreflect.solver import solve_moments, solve_moments_twice

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
D = torch.float64


@pytest.fixture(scope="module")
def groove():
    scene = ti.scenes.v_groove(40.0, divisions=3, dtype=D)
    K = moment_form_factors(scene, 2, quadrature_tol=1e-6)
    return scene, K, light_moments(scene, K)[..., None]


def _then(e0):
    """A second light made from the first answer, as the sky's weighing does (per facet, non-linear)."""
    return lambda c: e0 + 0.3 * torch.tanh(c[..., :1, :]) * e0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("method", ["dense", "cg"])
def test_same_answers_as_two_solves(groove, dtype, method):
    """Batch of 3 reflectance variants × 2 wavelengths, four facets black in the first (dropped from its system):
    both answers are two separate solves' bits (the same factors, the same operations)."""
    scene, _, e0 = groove
    Kd = moment_form_factors(scene.to(dtype), 2, quadrature_tol=1e-6)
    refl = (torch.rand(3, scene.num_facets, 2, generator=torch.Generator().manual_seed(0), dtype=D) * 0.8 + 0.1)
    refl[0, :4] = 0.0
    refl, e = refl.to(dtype), e0.to(dtype).expand(-1, -1, 2)
    then = _then(e)
    c1, c2 = solve_moments_twice(Kd, refl, e, then, method=method)
    a1 = solve_moments(Kd, refl, e, method=method)
    a2 = solve_moments(Kd, refl, then(a1), method=method)
    assert c1.shape == c2.shape == (3, scene.num_facets, Kd.size, 2) and c2.dtype == dtype
    assert torch.equal(c1, a1) and torch.equal(c2, a2)
    assert not torch.allclose(c2, c1, rtol=1e-2)  # the second light differs


def test_one_factorisation(groove, monkeypatch):
    """The dense path factors once for both solves (twice with two ``solve_moments``)."""
    scene, K, e0 = groove
    calls = []
    real = torch.linalg.cholesky_ex
    monkeypatch.setattr(torch.linalg, "cholesky_ex", lambda *a, **k: calls.append(1) or real(*a, **k))
    refl = torch.full((scene.num_facets,), 0.8, dtype=D)
    solve_moments_twice(K, refl, e0, _then(e0), method="dense")
    assert len(calls) == 1
    solve_moments(K, refl, _then(e0)(solve_moments(K, refl, e0, method="dense")), method="dense")
    assert len(calls) == 3


def test_gradients_through_both_solves(groove):
    """float64 gradcheck in the reflectance and the light, through both solves and ``then``."""
    scene, K, e0 = groove
    refl = torch.full((scene.num_facets,), 0.7, dtype=D).requires_grad_()
    e = e0.clone().requires_grad_()

    def f(r, light):
        c1, c2 = solve_moments_twice(K, r, light, _then(light), method="dense")
        return c1[..., 0, :], c2[..., 0, :]

    assert torch.autograd.gradcheck(f, (refl, e), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_a_light_of_another_shape_is_solved_afresh(groove):
    """``then`` may broadcast to a batch the first solve did not have: solved without the kept factors."""
    scene, K, e0 = groove
    refl = torch.full((scene.num_facets,), 0.6, dtype=D)
    scales = torch.tensor([1.0, 2.0], dtype=D)[:, None, None, None]
    c1, c2 = solve_moments_twice(K, refl, e0, lambda c: c * scales, method="dense")
    assert c2.shape == (2, *c1.shape)
    assert torch.equal(c2, solve_moments(K, refl, c1 * scales, method="dense"))


def test_a_wider_light_and_a_light_with_a_graph(groove):
    """A float32 system whose second light is float64 is solved afresh in float64 (as two ``solve_moments`` would);
    a second light that carries a graph while the inputs do not gets its gradient through the second solve (the
    same as two separate solves)."""
    scene, K, e0 = groove
    K32 = moment_form_factors(scene.to(torch.float32), 2, quadrature_tol=1e-6)
    r32, e32 = torch.full((scene.num_facets,), 0.6), e0.to(torch.float32)
    c1, c2 = solve_moments_twice(K32, r32, e32, lambda c: c.to(D) * 0.5, method="dense")
    assert c1.dtype == torch.float32 and c2.dtype == D
    assert torch.equal(c2, solve_moments(K32, r32, c1.to(D) * 0.5, method="dense"))
    refl = torch.full((scene.num_facets,), 0.6, dtype=D)
    w = torch.tensor(0.3, dtype=D, requires_grad=True)
    _, c2 = solve_moments_twice(K, refl, e0, lambda c: e0 + w * c, method="dense")
    (g,) = torch.autograd.grad(c2[..., 0, :].sum(), w)
    w2 = w.detach().clone().requires_grad_()
    a2 = solve_moments(K, refl, e0 + w2 * solve_moments(K, refl, e0, method="dense"), method="dense")
    (g2,) = torch.autograd.grad(a2[..., 0, :].sum(), w2)
    assert float(g) != 0.0 and torch.allclose(g, g2, rtol=1e-12, atol=0)
