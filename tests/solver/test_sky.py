"""The sky with its two estimates of the open part weighed per facet: on the polynomial basis (:func:`sky_estimates`,
:func:`solve_moments_sky`, :func:`sky_weights`) and on the constant one (:func:`sky_open_parts`, :func:`solve_sky`)."""

import math

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ShapeError, ValueRangeError
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.geometry import area_average, split_at_contacts
from torch_interreflect.light_moments import light_moments, sky_estimates, sky_rays
from torch_interreflect.sky_parts import sky_open_parts
from torch_interreflect.solver import facet_averages, solve_moments, solve_moments_sky, solve_sky
from torch_interreflect.solver.sky import sky_weights

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
D = torch.float64


@pytest.fixture(scope="module")
def cornell():
    """The Cornell box under the sky split at its contacts (50 pieces, 16 user facets): its rows are ray cast and
    the floor may see the blocks' backs, so the two estimates differ on most pieces."""
    scene, user = split_at_contacts(ti.scenes.cornell_box(light=False, dtype=D))
    return scene, user


def _user(scene, user, c):
    return area_average(facet_averages(c), user, scene.areas, 16)[:, 0]


def _rms(a, b):
    return float(((a / b - 1) ** 2).mean().sqrt())


def test_no_occluded_rows_one_estimate():
    """A V-groove (nothing blocks a pair): the two estimates are the same tensor, and the weighed solve is the plain
    one."""
    scene = ti.scenes.v_groove(60.0, divisions=2, dtype=D)
    K = moment_form_factors(scene, 2)
    escape, rows = sky_estimates(scene, K, sky_samples=4, sky_points=2)
    assert torch.equal(escape, rows)
    assert torch.equal(escape, light_moments(scene, K, "sky", sky_samples=4, sky_points=2))
    r = torch.full((scene.num_facets,), 0.7, dtype=D)
    c = solve_moments_sky(K, r, escape, rows, torch.tensor([2.0], dtype=D))
    assert torch.allclose(c, solve_moments(K, r, 2.0 * escape[..., None]), rtol=1e-13, atol=0)


def test_escape_estimate_is_light_moments(cornell):
    """``escape`` is the sky of :func:`light_moments` with the same rays (its escaping rays now counted by a
    first-hit cast instead of an occlusion query: the same rays, the same answer up to rays that graze an edge), and
    ``rows`` differs from it only on the facets whose open part is counted from escaping rays."""
    scene, _ = cornell
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
    escape, rows = sky_estimates(scene, K, sky_samples=8, sky_points=4)
    plain = light_moments(scene, K, "sky", sky_samples=8, sky_points=4)
    assert torch.allclose(escape, plain, rtol=0, atol=1e-12)
    ids = sky_rays(scene, K, samples=8, points=4).escape_ids
    differ = torch.nonzero((escape - rows).abs().amax(1) > 0).reshape(-1)
    assert differ.numel() > 20
    assert set(differ.tolist()) <= set(ids.tolist())


def test_weights_are_the_seen_radiance_over_the_sky(cornell):
    """:func:`sky_weights` on a made-up solution whose interreflected part is ``π L a Σ_j F`` per facet gives back
    ``a`` (clamped to [0, 1]), per batch element and wavelength."""
    scene, _ = cornell
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
    F, nb = K.num_facets, K.size
    covered = K.matrix.reshape(F, nb, F, nb)[:, 0, :, 0].sum(1)
    L = torch.tensor([0.5, 2.0], dtype=D)
    a = torch.linspace(-0.5, 1.5, 2 * F, dtype=D).reshape(2, F)  # [batch, F]
    e0 = torch.rand(2, F, nb, 2, dtype=D, generator=torch.Generator().manual_seed(0))
    c = e0.clone()
    c[:, :, 0, :] += math.pi * L * a[..., None] * covered[:, None]
    beta = sky_weights(K, c, e0, L)
    assert beta.shape == (2, F, 1, 2)
    want = a.clamp(0, 1)[..., None, None].expand(2, F, 1, 2)
    seen = covered > 0
    assert torch.allclose(beta[:, seen], want[:, seen], rtol=0, atol=1e-12)
    assert bool((beta[:, ~seen] == 0).all())


def test_black_surroundings_keep_the_escape_estimate(cornell):
    """Reflectance 0: nothing is interreflected, the weights are 0 and the answer is the escape estimate's."""
    scene, _ = cornell
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
    escape, rows = sky_estimates(scene, K, sky_samples=8, sky_points=4)
    zero = torch.zeros(scene.num_facets, dtype=D)
    L = torch.tensor([1.5], dtype=D)
    c = solve_moments_sky(K, zero, escape, rows, L)
    assert torch.allclose(c, 1.5 * escape[..., None], rtol=0, atol=1e-13)


@pytest.fixture(scope="module")
def converged(cornell):
    """The split box with 8 × 8 visibility rays and 24² sky directions from 12² points (tol 1e-4): the reference."""
    scene, _ = cornell
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4, visibility_samples=8)
    return (K, *sky_estimates(scene, K, sky_samples=24, sky_points=12))


@pytest.mark.parametrize(("r", "most"), [(0.9, 0.6), (0.2, 1.05)])
def test_weighing_lowers_the_rays_error(cornell, converged, r, most):
    """At 3 × 3 visibility rays and 8² directions from 8² points, over four draws, the RMS error of the 16 user
    facets against the converged solution: bright (r = 0.9) 0.92 % with the escape estimate, 0.43 % weighed (0.47
    of it); dark (r = 0.2) 1.88 % and 1.84 % (0.98). At the converged counts the two answers agree to 0.19 % (bright)
    and 0.04 % (dark): both estimate the same light."""
    scene, user = cornell
    Kh, eh, rh = converged
    refl = torch.full((scene.num_facets,), r, dtype=D)
    L = torch.tensor([1.0], dtype=D)
    ref = _user(scene, user, solve_moments_sky(Kh, refl, eh, rh, L))
    agree = _rms(_user(scene, user, solve_moments(Kh, refl, eh[..., None])), ref)
    assert agree < (0.003 if r > 0.5 else 0.0006)
    esc, bal = [], []
    for seed in range(4):
        K = moment_form_factors(scene, 2, quadrature_tol=1e-4, seed=seed)
        e, rw = sky_estimates(scene, K, sky_samples=8, sky_points=8, sky_seed=seed)
        esc.append(_rms(_user(scene, user, solve_moments(K, refl, e[..., None])), ref))
        bal.append(_rms(_user(scene, user, solve_moments_sky(K, refl, e, rw, L)), ref))
    q_esc = math.sqrt(sum(v * v for v in esc) / 4)
    q_bal = math.sqrt(sum(v * v for v in bal) / 4)
    assert q_bal < most * q_esc, (esc, bal)


def test_batch_and_spectrum_shapes(cornell):
    """Reflectance variants ``[V, F, L]`` and a sky spectrum ``[L]``: ``[V, F, nb, L]``, each variant and wavelength
    its own solve (its own weights)."""
    scene, _ = cornell
    K = moment_form_factors(scene, 2, quadrature_tol=1e-3)
    escape, rows = sky_estimates(scene, K, sky_samples=4, sky_points=4)
    F = scene.num_facets
    refl = torch.rand(3, F, 2, dtype=D, generator=torch.Generator().manual_seed(1)) * 0.8 + 0.1
    L = torch.tensor([0.5, 2.0], dtype=D)
    c = solve_moments_sky(K, refl, escape, rows, L, method="dense")
    assert c.shape == (3, F, K.size, 2)
    for v in range(3):
        for w in range(2):
            one = solve_moments_sky(K, refl[v, :, w], escape, rows, L[w : w + 1], method="dense")
            assert torch.allclose(c[v, :, :, w : w + 1], one, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_float32_and_float64(dtype):
    """The unsplit box (16 facets) in either dtype: float32 within 5e-6 of float64 (measured 5.8e-7)."""
    scene = ti.scenes.cornell_box(light=False, dtype=dtype)
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
    escape, rows = sky_estimates(scene, K, sky_samples=4, sky_points=4)
    refl = torch.full((16,), 0.8, dtype=dtype)
    c = solve_moments_sky(K, refl, escape, rows, torch.tensor([1.0], dtype=dtype))
    assert c.dtype == dtype
    K64 = moment_form_factors(scene.to(D), 2, quadrature_tol=1e-4)
    c64 = solve_moments_sky(K64, refl.to(D), escape, rows, torch.tensor([1.0], dtype=D))
    assert torch.allclose(c[:, 0].to(D), c64[:, 0], rtol=5e-6, atol=0)


def test_gradients_through_both_solves_and_the_weights():
    """float64 gradcheck in the reflectance and the sky's radiance, on the unsplit box (16 facets, where the two
    estimates differ on 10)."""
    scene = ti.scenes.cornell_box(light=False, dtype=D)
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
    escape, rows = sky_estimates(scene, K, sky_samples=4, sky_points=4)
    assert not torch.equal(escape, rows)
    refl = torch.full((16,), 0.6, dtype=D).requires_grad_()
    L = torch.tensor([0.7], dtype=D, requires_grad=True)

    def f(r, radiance):
        return facet_averages(solve_moments_sky(K, r, escape, rows, radiance))

    assert torch.autograd.gradcheck(f, (refl, L), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_bad_inputs(cornell):
    scene, _ = cornell
    K = moment_form_factors(scene, 2, quadrature_tol=1e-3)
    escape, rows = sky_estimates(scene, K, sky_samples=4, sky_points=2)
    r = torch.full((scene.num_facets,), 0.5, dtype=D)
    L = torch.tensor([1.0], dtype=D)
    with pytest.raises(ShapeError, match=r"rows must have shape \[F, nb\]"):
        solve_moments_sky(K, r, escape, rows[:-1], L)
    with pytest.raises(ValueRangeError, match="radiance must be finite and non-negative"):
        solve_moments_sky(K, r, escape, rows, torch.tensor([-1.0], dtype=D))
    with pytest.raises(TypeError, match="MomentFormFactors"):
        solve_moments_sky(K.matrix, r, escape, rows, L)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rows=True"):
        sky_estimates(scene, K, sky=sky_rays(scene, K, samples=4, points=2))
    with pytest.raises(ShapeError, match="facets"):
        sky_estimates(ti.scenes.v_groove(60.0, dtype=D), K)
    with pytest.raises(ValueError, match="backfaces"):
        sky_estimates(scene, K, backfaces="sometimes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cast alike"):
        sky_rays(scene, K, samples=4, points=2).mean(sky_rays(scene, K, samples=4, points=2, rows=True))
    with pytest.raises(ShapeError, match=r"\[\.\.\., F, nb, L\]"):
        sky_weights(K, escape[None], escape[None], L)


# ---------------------------------------------------------------------------------------------- the constant basis


@pytest.fixture(scope="module")
def box16():
    """The unsplit Cornell box (16 facets) with the default kernel and with 30 × 30 visibility rays on every pair
    (100× the default's rays: the visibility reference)."""
    box = ti.scenes.cornell_box(light=False, dtype=D)
    return box, ti.form_factors(box), ti.form_factors(box, visibility_samples=30, visibility_angle=None)


def test_constant_escape_part_is_the_sky_of_lights(box16):
    """``escape`` is the open part of :func:`ti.lights.sky` (the same rays; measured 1.1e-16 apart), and ``rows``
    differs from it only on facets whose rows are ray cast."""
    box, K, _ = box16
    escape, rows = sky_open_parts(box, K)
    assert torch.allclose(escape, ti.lights.sky(box, K, torch.ones(1, dtype=D))[:, 0] / math.pi, rtol=0, atol=1e-14)
    differ = torch.nonzero(escape != rows).reshape(-1)
    occ = torch.nonzero(K.info["occluded_facets"]).reshape(-1)
    assert differ.numel() > 5 and set(differ.tolist()) <= set(occ.tolist())


def test_constant_black_surroundings_and_no_occlusion():
    """Reflectance 0 keeps the escape estimate (``E = π L escape``); a V-groove has one estimate, and the weighed
    solve is the plain one."""
    box = ti.scenes.cornell_box(light=False, dtype=D)
    K = ti.form_factors(box)
    escape, rows = sky_open_parts(box, K, sky_samples=4)
    L = torch.tensor([0.5, 2.0], dtype=D)
    E = solve_sky(K, torch.zeros(16, dtype=D), escape, rows, L)
    assert torch.allclose(E, math.pi * escape[:, None] * L, rtol=0, atol=1e-14)
    groove = ti.scenes.v_groove(60.0, divisions=2, dtype=D)
    Kg = ti.form_factors(groove)
    e, rw = sky_open_parts(groove, Kg, sky_samples=4)
    assert torch.equal(e, rw)
    r = torch.full((8,), 0.7, dtype=D)
    assert torch.allclose(solve_sky(Kg, r, e, rw, L), ti.solve(Kg, r, math.pi * e[:, None] * L), rtol=1e-13, atol=0)


@pytest.mark.parametrize(("r", "most"), [(0.9, 0.2), (0.2, 0.6)])
def test_constant_weighing_lowers_the_visibility_part(box16, r, most):
    """The visibility's part of the error, each estimate against itself with 100× the visibility rays (the
    visibility benchmark's measure): r = 0.9 1.82 % with the escape count, 0.18 % weighed (0.10 of it); r = 0.2
    0.37 % and 0.17 % (0.46)."""
    box, K, Kref = box16
    refl = torch.full((16,), r, dtype=D)
    L = torch.ones(1, dtype=D)
    e, rw = sky_open_parts(box, K)
    e_ref, rw_ref = sky_open_parts(box, Kref)
    part_esc = _rms(ti.solve(K, refl, math.pi * e[:, None]), ti.solve(Kref, refl, math.pi * e_ref[:, None]))
    part_bal = _rms(solve_sky(K, refl, e, rw, L), solve_sky(Kref, refl, e_ref, rw_ref, L))
    assert part_bal < most * part_esc, (part_esc, part_bal)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_dtypes_gradients_and_bad_inputs(box16, dtype):
    """float32 within 1e-4 of float64 (measured 2.7e-5, the float32 kernel's own difference: 2.8e-5 in its entries);
    float64 gradcheck in the reflectance and the radiance; the shapes checked."""
    box, K64, _ = box16
    e, rw = sky_open_parts(box, K64, sky_samples=4)
    K = ti.form_factors(box.to(dtype))
    refl = torch.full((2, 16), 0.8, dtype=dtype)
    E = solve_sky(K, refl, e, rw, torch.tensor([1.0, 0.5], dtype=dtype))
    assert E.shape == (2, 16, 2) and E.dtype == dtype
    E64 = solve_sky(K64, refl.to(D), e, rw, torch.tensor([1.0, 0.5], dtype=D))
    assert torch.allclose(E.to(D), E64, rtol=1e-4 if dtype == torch.float32 else 1e-13, atol=0)
    if dtype == torch.float64:
        r = torch.full((16,), 0.6, dtype=D, requires_grad=True)
        L = torch.tensor([0.7], dtype=D, requires_grad=True)
        assert torch.autograd.gradcheck(lambda a, b: solve_sky(K64, a, e, rw, b), (r, L), eps=1e-6, atol=1e-7)
    with pytest.raises(ShapeError, match=r"escape must have shape \[F\]"):
        solve_sky(K, refl, e[:-1], rw, torch.ones(1, dtype=dtype))
    with pytest.raises(ShapeError, match="facets"):
        sky_open_parts(ti.scenes.v_groove(60.0, dtype=D), K)


def test_constant_geometry_gradient_as_lights_sky():
    """A V-groove whose angle requires grad (no occluded rows: the two estimates agree): ``solve_sky`` passes the
    gradient of ``1 − Σ_j F_ij`` to the geometry as ``lights.sky`` does (measured: the same bits)."""
    angle = torch.tensor(50.0, dtype=D, requires_grad=True)
    groove = ti.scenes.v_groove(angle, divisions=2, dtype=D)
    K = ti.form_factors(groove)
    e, rw = sky_open_parts(groove, K, sky_samples=4)
    r, L = torch.full((8,), 0.7, dtype=D), torch.ones(1, dtype=D)
    (g1,) = torch.autograd.grad(solve_sky(K, r, e, rw, L).mean(), angle, retain_graph=True)
    (g2,) = torch.autograd.grad(ti.solve(K, r, ti.lights.sky(groove, K, L)).mean(), angle)
    assert float(g1) != 0.0 and torch.allclose(g1, g2, rtol=1e-12, atol=0)
