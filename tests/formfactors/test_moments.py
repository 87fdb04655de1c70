"""Galerkin moments on a polynomial basis per facet: the basis, the compiled inner integral, the moments against
exact references (Howell, closure, refinement identities, brute-force quadrature), visibility, the light's moments
and the solve."""

import itertools
import math

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from tests.oracles import HOWELL_C11, HOWELL_C14_SQUARES, HOWELL_C16
from torch_interreflect.accuracy.leaves import Leaves, split
from torch_interreflect.errors import ShapeError, ValueRangeError
from torch_interreflect.formfactors import facet_basis, moment_form_factors, point_polygon_factor
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.formfactors.rules import quadrature_rule
from torch_interreflect.geometry import split_at_contacts, subdivide_to
from torch_interreflect.geometry._polygon import bilinear, clip_polygons
from torch_interreflect.geometry.raycast import RayCaster
from torch_interreflect.light_moments import light_is_rough, light_moments
from torch_interreflect.solver.moments import facet_averages, solve_moments

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
F64 = torch.float64


def scene_of(polys, dtype=F64):
    return ti.Scene.from_polygons(torch.tensor(polys, dtype=dtype))


def square(z=0.0, flip=False):
    s = [[-0.5, -0.5, z], [0.5, -0.5, z], [0.5, 0.5, z], [-0.5, 0.5, z]]
    return s[::-1] if flip else s


def hinge(phi_deg, n=1, dtype=F64):
    phi = math.radians(phi_deg)
    d = [math.cos(phi), 0.0, math.sin(phi)]
    a = ti.scenes.grid_quads([0, 0, 0], [1, 0, 0], [0, 1, 0], n, n).tolist()
    b = ti.scenes.grid_quads([0, 0, 0], [0, 1, 0], d, n, n).tolist()
    return scene_of(a + b, dtype), n * n


def gauss_points(scene, facet, n):
    u, v, w = quadrature_rule("plain", n, F64, torch.device("cpu"))
    x, jac = bilinear(scene.corners.double()[facet][None], u, v)
    return x[0], (w * jac[0])


def brute_moments(scene, basis, i, j, n=24):
    """``(1/A_i) ∫_i ψ_a ∫_j k ψ_b`` by a product Gauss rule of order ``n`` on both facets (far pairs only)."""
    xi, wi = gauss_points(scene, i, n)
    yj, wj = gauss_points(scene, j, n)
    ni, nj = scene.normals.double()[i], scene.normals.double()[j]
    r = yj[None] - xi[:, None]
    d2 = (r * r).sum(-1)
    k = (r @ ni).clamp_min(0) * (-(r @ nj)).clamp_min(0) / (math.pi * d2 * d2)
    pa = basis.evaluate(torch.full((xi.shape[0],), i), xi)
    pb = basis.evaluate(torch.full((yj.shape[0],), j), yj)
    return torch.einsum("p,pa,pq,q,qb->ab", wi, pa, k, wj, pb) / float(scene.areas.double()[i])


# --------------------------------------------------------------------------------------------------- basis
@pytest.mark.parametrize("degree", [0, 1, 2])
@pytest.mark.parametrize("shape", ["quad", "triangle"])
def test_basis_is_orthonormal_and_hierarchical(degree, shape):
    quad = [[0, 0, 0], [1.0, 0, 0], [1.3, 0.8, 0], [0.1, 1.1, 0]]  # not a parallelogram
    tri = [[0, 0, 1.0], [1.0, 0, 1.0], [0.2, 0.9, 1.0]]
    scene = scene_of([quad]) if shape == "quad" else scene_of([tri])
    b = facet_basis(scene, degree)
    for f in range(scene.num_facets):
        x, w = gauss_points(scene, f, 10)
        psi = b.evaluate(torch.full((x.shape[0],), f), x)
        gram = torch.einsum("q,qa,qb->ab", w / w.sum(), psi, psi)
        assert torch.allclose(gram, torch.eye(b.size, dtype=F64), atol=1e-12)
        assert torch.allclose(psi[:, 0], torch.ones_like(psi[:, 0]), atol=1e-12)
    if degree == 2:
        assert torch.allclose(facet_basis(scene, 1).transform, b.transform[:, :3, :3], atol=1e-14)


def test_basis_rejects_bad_input():
    scene = scene_of([square()])
    with pytest.raises(ValueRangeError, match="degree must be 0, 1 or 2"):
        facet_basis(scene, 3)
    b = facet_basis(scene, 1)
    with pytest.raises(ShapeError, match="points must have shape"):
        b.evaluate(torch.tensor([0]), torch.zeros(3))
    with pytest.raises(ValueRangeError, match="facet must lie in"):
        b.evaluate(torch.tensor([1]), torch.zeros(1, 3))
    with pytest.raises(ShapeError, match=r"facets \[k\] and points \[k, Q, 3\] must agree"):
        b.evaluate_on(torch.tensor([0, 0]), torch.zeros(1, 4, 3))
    with pytest.raises(ValueRangeError, match="facets must lie in"):
        b.evaluate_on(torch.tensor([2]), torch.zeros(1, 4, 3))


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_basis_on_points_grouped_by_facet_is_the_pointwise_basis(degree):
    box = ti.scenes.cornell_box(light=False, dtype=F64)
    b = facet_basis(box, degree)
    facets = torch.tensor([3, 0, 7, 3])
    gen = torch.Generator().manual_seed(0)
    pts = b.centroids[facets][:, None] + 0.1 * torch.randn(4, 5, 3, dtype=F64, generator=gen)
    psi = b.evaluate_on(facets, pts)
    assert psi.shape == (4, 5, b.size)
    ref = b.evaluate(facets.repeat_interleave(5), pts.reshape(-1, 3)).reshape(4, 5, -1)
    torch.testing.assert_close(psi, ref, rtol=0, atol=1e-15)


# ------------------------------------------------------------------------------------------- the inner integral
def test_inner_integral_of_one_is_lamberts_formula():
    """The radial-exact / angular-Gauss integral of the constant equals Lambert's contour formula, also for a
    point 1e-3 above the target whose horizon cuts it (measured: 9e-12 with 8 points per panel; one panel per edge
    left 2e-3)."""
    kern = loops("moments")
    target = torch.tensor([[0, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0], [0, 1.0, 0]], dtype=F64)
    n_t = torch.tensor([0, 0, 1.0], dtype=F64)
    gx, gw = np.polynomial.legendre.leggauss(8)
    cases = [([0.3, 0.4, 0.7], [0, 0, -1.0]), ([1.5, -0.2, 0.05], [-0.6, 0.2, -0.77]), ([0.2, 0.2, 1e-3],
                                                                                         [0.0, 0.6, -0.8])]
    for x, nx in cases:
        x = torch.tensor(x, dtype=F64)
        nx = torch.tensor(nx, dtype=F64)
        nx = nx / nx.norm()
        mom = np.zeros(1)
        kern.inner_exact(x.numpy(), nx.numpy(), target.numpy(), 4, n_t.numpy(), np.array([0.5, 0.5, 0.0]),
                         np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 1.0, 0, gx, gw, 2.0, np.empty((8, 3)), mom)
        clipped = clip_polygons(target[None], x[None], nx[None], 1e-15)
        exact = float(point_polygon_factor(x[None, None], nx[None], clipped))
        assert mom[0] == pytest.approx(exact, rel=1e-10, abs=1e-13)


def test_inner_integral_of_monomials_against_brute_force():
    """Moments of ``1, p, q, p², pq, q²`` over a target from an off-plane point: against a 200 × 200 Gauss rule of
    the point kernel (smooth here)."""
    kern = loops("moments")
    target = torch.tensor([[0, 0, 0], [1.0, 0, 0], [1.2, 0.9, 0], [0, 1.0, 0]], dtype=F64)
    x, nx = np.array([0.4, 0.3, 0.8]), np.array([0.1, 0.0, -1.0]) / math.hypot(0.1, 1.0)
    c, e1, e2, inv_l = np.array([0.5, 0.5, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 1.0 / 1.05
    gx, gw = np.polynomial.legendre.leggauss(20)
    mom = np.zeros(6)
    kern.inner_exact(x, nx, target.numpy(), 4, np.array([0, 0, 1.0]), c, e1, e2, inv_l, 2, gx, gw, 2.0,
                     np.empty((8, 3)), mom)
    u, v, w = quadrature_rule("plain", 200, F64, torch.device("cpu"))
    y, jac = bilinear(target[None], u, v)
    y, wy = y[0].numpy(), (w * jac[0]).numpy()
    r = y - x
    d2 = (r * r).sum(-1)
    k = (r @ nx).clip(0) * (-r[:, 2]).clip(0) / (math.pi * d2 * d2)  # cos θ_y from the target's normal +z
    p, q = (y[:, 0] - c[0]) * inv_l, (y[:, 1] - c[1]) * inv_l
    ref = [(k * wy * m).sum() for m in (np.ones_like(p), p, q, p * p, p * q, q * q)]
    np.testing.assert_allclose(mom, ref, rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------------------------------------ the moments
@pytest.mark.parametrize(("phi", "ref"), [c for c in HOWELL_C16 if c[0] <= 90])
def test_constant_block_is_howells_hinge(phi, ref):
    """Degree 2, its constant block: unit squares sharing an edge (Howell C-16; 7 digits)."""
    scene, _ = hinge(phi)
    G = moment_form_factors(scene, 2, quadrature_tol=1e-8)
    assert G.matrix.shape == (12, 12)
    assert float(G.constant().matrix[0, 1]) == pytest.approx(ref, abs=2e-6)


@pytest.mark.parametrize(("gap", "ref"), HOWELL_C11)
def test_constant_block_is_howells_opposed_squares(gap, ref):
    scene = scene_of([square(), square(gap, flip=True)])
    G = moment_form_factors(scene, 1, quadrature_tol=1e-8)
    assert float(G.constant().matrix[0, 1]) == pytest.approx(ref, abs=2e-6)


def test_far_pair_moments_against_product_gauss(dtype):
    """Every moment of a far pair (opposed squares 3 apart, tilted) against a 24-point product rule; float32 keeps
    its own precision."""
    b = [[-0.5, -0.4, 3.0], [-0.5, 0.6, 3.2], [0.5, 0.6, 3.2], [0.5, -0.4, 3.0]]
    scene = scene_of([square(), b], dtype)
    G = moment_form_factors(scene, 2, quadrature_tol=1e-8)
    assert G.dtype == dtype
    s64 = scene_of([square(), b])
    ref = brute_moments(s64, facet_basis(s64, 2), 0, 1)
    tol = 1e-9 if dtype == F64 else 1e-6
    assert torch.allclose(G.matrix.double().reshape(2, 6, 2, 6)[0, :, 1, :], ref, atol=tol * float(ref.abs().max()))


def test_closed_box_moments_close_for_every_basis_function():
    """In a closed box every point sees the whole enclosure: ``Σ_j G[(i, a), (j, 0)] = mean_i(ψ_a) = δ_a0``
    (measured 6.8e-6 at tol 1e-6; the higher moments test the whole rule, edges and corners included)."""
    box = ti.scenes.closed_box(divisions=2, dtype=F64)
    G = moment_form_factors(box, 2, quadrature_tol=1e-6)
    F, nb = box.num_facets, G.size
    rows = G.matrix.reshape(F, nb, F, nb)[:, :, :, 0].sum(2)
    expect = torch.zeros(F, nb, dtype=F64)
    expect[:, 0] = 1.0
    assert float((rows - expect).abs().max()) < 1e-5


def test_both_directions_of_a_pair_against_product_gauss():
    """Each unordered pair is integrated once and the other direction comes from reciprocity: both blocks against
    their own brute-force rule, so a wrong orientation of the reciprocal block (transposed, other area) fails."""
    b = [[-0.5, -0.4, 3.0], [-0.5, 0.9, 3.4], [0.7, 0.9, 3.4], [0.7, -0.4, 3.0]]  # larger than the floor: the floor
    scene = scene_of([square(), b])  # is the integration domain, the other block is reciprocal
    G = moment_form_factors(scene, 2, quadrature_tol=1e-10).matrix.reshape(2, 6, 2, 6)
    basis = facet_basis(scene, 2)
    for i, j in ((0, 1), (1, 0)):  # measured 1.1e-11 of the largest entry both ways (6.1e-8 at tol 1e-8)
        ref = brute_moments(scene, basis, i, j)
        assert torch.allclose(G[i, :, j, :], ref, atol=5e-11 * float(ref.abs().max()))


def test_radial_integrals_against_mpmath():
    """``h² J0, h J1, h J2, h J3`` from the closed forms and, for a target small against its height, the series
    (the closed form of ``h J3`` lost every digit at ``R/h = 1e-4``); measured under 2e-12 relative everywhere."""
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 40
    from torch_interreflect.formfactors import _numba_contour

    radial = _numba_contour._radial
    h = 0.7
    for x in (1e-5, 1e-3, 0.05, 0.0999, 0.1001, 0.7, 30.0):
        R = x * h
        got = radial(h, h * h, 1.0 / h, R)  # h² and 1 / h as inner_exact hands them over
        for n, scale in enumerate((h * h, h, h, h)):
            ref = scale * mpmath.quad(lambda r, n=n: r ** (n + 1) / (h * h + r * r) ** 2, [0, R])
            assert got[n] == pytest.approx(float(ref), rel=2e-12)


def test_t_junctions_add_up_to_their_parent():
    """Leaves of unequal refinement (one plate's hinge facets split in four): the children's rows and columns of
    the constant block add up to the parent's, ``Σ_c A_c F_cj = A_p F_pj`` (the contact along half an edge gets the
    graded rule; measured 4e-8 at tol 1e-8)."""
    scene, n = hinge(30.0, n=2)
    lv = split(Leaves(scene, torch.arange(scene.num_facets)), torch.tensor([True, True, False, False] + [False] * n))
    F0 = moment_form_factors(scene, 2, quadrature_tol=1e-8).constant().matrix
    F1 = moment_form_factors(lv.scene, 2, quadrature_tol=1e-8).constant().matrix
    A1 = lv.scene.areas.double()
    user = lv.user
    rows = torch.zeros(scene.num_facets, lv.scene.num_facets, dtype=F64).index_add_(0, user, A1[:, None] * F1)
    agg = torch.zeros(scene.num_facets, scene.num_facets, dtype=F64).index_add_(1, user, rows)
    assert torch.allclose(agg / scene.areas.double()[:, None], F0, atol=2e-7)


def _floor_and_wall(floor: list[tuple[float, float]], wall: list[tuple[float, float]]) -> ti.Scene:
    """Unit-deep floor pieces (z = 0, x from a to b) and 0.6 m high wall pieces (y = 0, facing the floor)."""
    quads = [[[a, 0, 0], [b, 0, 0], [b, 1, 0], [a, 1, 0]] for a, b in floor]
    quads += [[[a, 0, 0], [a, 0, 0.6], [b, 0, 0.6], [b, 0, 0]] for a, b in wall]
    return ti.Scene.from_polygons(torch.tensor(quads, dtype=F64))


@pytest.mark.parametrize("basis", ["moments", "constant"])
@pytest.mark.parametrize("wall", [(0.5, 1.5), (0.0, 1.5), (0.25, 0.75), (0.0, 0.6)])
def test_partly_shared_edges_converge_as_their_conforming_split(wall, basis):
    """A floor from x = 0 to 1 and a wall along its edge over ``wall``: their edges share a segment (without a
    shared corner, from a shared corner, inside the floor's edge). The exchange ``A_i F_ij`` against the same plates
    cut at each other's ends (every contact a whole edge or a corner) at tol 1e-9, on both bases (``moments``: the
    degree-0 block of :func:`moment_form_factors`; ``constant``: :func:`ti.form_factors`). Measured: moments
    ≤ 4.1e-5 at tol 1e-3 and ≤ 4.4e-9 at 1e-6, constant ≤ 9.5e-8 and ≤ 2.3e-9. Before the shared segments were
    graded: moments 2.1e-2 / 2.8e-3 without the shared corner and 2.5e-2 / 4.0e-3 from it, constant 2.5e-2 / 4.0e-3
    from it."""
    a, b = wall
    ends = sorted({0.0, 1.0, a, b})
    cut = lambda lo, hi: [(x, y) for x, y in itertools.pairwise(ends) if lo <= x and y <= hi]  # noqa: E731

    def exchange(scene: ti.Scene, tol: float, n_floor: int) -> float:
        if basis == "moments":
            F = moment_form_factors(scene, 1, quadrature_tol=tol, occlusion=False).constant().matrix
        else:
            F = ti.form_factors(scene, quadrature_tol=tol).matrix
        return float((scene.areas[:n_floor, None] * F[:n_floor, n_floor:]).sum())

    floor_cut = cut(0.0, 1.0)
    ref = exchange(_floor_and_wall(floor_cut, cut(a, b)), 1e-9, len(floor_cut))
    whole = _floor_and_wall([(0.0, 1.0)], [wall])
    assert exchange(whole, 1e-3, 1) == pytest.approx(ref, rel=1e-4 if basis == "moments" else 2e-7)
    assert exchange(whole, 1e-6, 1) == pytest.approx(ref, rel=1e-8)


def test_a_short_edge_nearly_on_a_long_one():
    """The wall over x = 0.25 to 0.75 along a floor turned by 4e-7 rad about z at x = 0.5: the wall's edge ends lie
    1e-7 m from the floor edge's line, within the contact tolerance (1e-7 of the floor's 1.41 m diameter), but the
    floor edge's ends lie 2e-7 m from the wall edge's line, so only one side sees a shared segment. The pair is then
    a corner contact on the wall (graded toward both of its corner's edges, the whole contact edge one of them), and
    the exchange at tol 1e-3 is the untilted one's: measured 1.8e-7 off (8.4e-8 at tol 1e-6). Taking the one-sided
    segment as an edge contact on the floor, cut at the wall's ends, was 2.0e-3 off (5.1e-3 at 1e-6)."""
    eps = 4e-7
    c, s = math.cos(eps), math.sin(eps)

    def scene(turn: bool) -> ti.Scene:
        quads = torch.tensor([[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]],
                              [[0.25, 0, 0], [0.25, 0, 0.6], [0.75, 0, 0.6], [0.75, 0, 0]]], dtype=F64)
        if turn:
            x, y = quads[0, :, 0] - 0.5, quads[0, :, 1]
            quads[0, :, 0], quads[0, :, 1] = 0.5 + c * x - s * y, s * x + c * y
        return ti.Scene.from_polygons(quads)

    def exchange(sc: ti.Scene, tol: float) -> float:
        F = moment_form_factors(sc, 1, quadrature_tol=tol, occlusion=False).constant().matrix
        return float(sc.areas[0] * F[0, 1])

    assert exchange(scene(True), 1e-3) == pytest.approx(exchange(scene(False), 1e-9), rel=1e-6)


@pytest.mark.parametrize("degree", [0, 1])
def test_far_pairs_keep_three_points_per_side_at_every_degree(degree):
    """The Cornell box split at its contacts and cut to 0.4 m (65 pieces, no occlusion), every piece emitting,
    r = 0.9: the pieces' averages at quadrature tol 1e-3 against tol 1e-9. Measured 9.0e-4 (degree 0) and 1.0e-3
    (degree 1); with ``degree + 1`` points per side on far pairs, 0.34 and 1.1e-2."""
    box = subdivide_to(split_at_contacts(ti.scenes.cornell_box(light=False, dtype=F64))[0], 0.4)[0]

    def averages(tol: float) -> torch.Tensor:
        K = moment_form_factors(box, degree, quadrature_tol=tol, occlusion=False)
        e0 = torch.zeros(box.num_facets, K.size, 1, dtype=F64)
        e0[:, 0] = 1.0
        return facet_averages(solve_moments(K, torch.full((box.num_facets, 1), 0.9, dtype=F64), e0)).reshape(-1)

    ref = averages(1e-9)
    assert float(((averages(1e-3) - ref).abs() / ref).max()) <= 2e-3


def test_visibility_converges_to_the_brute_force_value():
    """Two opposed squares with a plate between them covering part of the view: the constant block approaches a
    brute-force visible form factor (64² × 64² segments) as the rays grow, without a bias (the blocked part is an
    unbiased estimate: the mean over 8 seeds at 3 × 3 rays is within 3 standard errors)."""
    blocker = [[-0.8, -0.8, 0.5], [0.1, -0.8, 0.5], [0.1, 0.3, 0.5], [-0.8, 0.3, 0.5]]
    scene = scene_of([square(), square(1.0, flip=True), blocker, blocker[::-1]])
    sc = scene.to(F64)
    n = 64
    xi, wi = gauss_points(sc, 0, n)
    yj, wj = gauss_points(sc, 1, n)
    X = xi[:, None].expand(-1, n * n, -1).reshape(-1, 3)
    Y = yj[None].expand(n * n, -1, -1).reshape(-1, 3)
    r = Y - X
    d2 = (r * r).sum(-1)
    k = (r @ sc.normals[0]).clamp_min(0) * (-(r @ sc.normals[1])).clamp_min(0) / (math.pi * d2 * d2)
    w = (wi[:, None] * wj[None]).reshape(-1)
    vis = ~torch.from_numpy(RayCaster(sc).segments_blocked(X.numpy(), Y.numpy()))
    ref = float((k * w * vis).sum()) / float(sc.areas[0])
    free = float((k * w).sum()) / float(sc.areas[0])
    assert 0.3 * free < ref < 0.9 * free  # partly blocked
    seeds = [float(moment_form_factors(scene, 0, visibility_samples=3, seed=s).matrix[0, 1]) for s in range(8)]
    mean, se = np.mean(seeds), np.std(seeds, ddof=1) / math.sqrt(len(seeds))
    assert abs(mean - ref) < 3 * se + 1e-4
    fine = float(moment_form_factors(scene, 0, visibility_samples=24).matrix[0, 1])
    assert fine == pytest.approx(ref, rel=3e-3)
    G = moment_form_factors(scene, 2)
    assert G.info["occluded_pairs"] > 0 and bool(G.info["occluded_facets"][:2].all())


def test_moments_reject_bad_options():
    scene = scene_of([square(), square(1.0, flip=True)])
    with pytest.raises(ValueRangeError, match="quadrature_tol"):
        moment_form_factors(scene, 2, quadrature_tol=0.0)
    with pytest.raises(ValueRangeError, match="occlusion"):
        moment_form_factors(scene, 2, occlusion="yes")
    with pytest.raises(ValueRangeError, match="visibility_samples"):
        moment_form_factors(scene, 2, visibility_samples=0)


# ------------------------------------------------------------------------------------------------- the light
def test_sky_and_area_light_moments_come_from_the_constant_column():
    scene, _ = hinge(90.0)
    G = moment_form_factors(scene, 2, quadrature_tol=1e-8)
    sky = light_moments(scene, G, "sky")
    assert float(sky[0, 0]) / math.pi == pytest.approx(1 - HOWELL_C14_SQUARES, abs=2e-6)
    area = light_moments(scene, G, torch.tensor([False, True]))
    assert float(area[0, 0]) / math.pi == pytest.approx(HOWELL_C14_SQUARES, abs=2e-6)
    assert torch.allclose(sky[0, 1:], -area[0, 1:], atol=1e-12)  # facet 0 sees only facet 1: open = −covered
    uni = light_moments(scene, G, "uniform")
    assert uni[:, 0].tolist() == [1.0, 1.0] and not bool(uni[:, 1:].any())


def test_sun_moments_with_a_shadow_edge_across_the_facet():
    """A wall along ``x = 0`` shades the half ``x > 0`` of a unit floor from a sun travelling ``+x``: lit fraction 1/2
    and the first moment of the lit part, ``mean(ψ_1 · lit) = √3 ∫_0^½ (2u − 1) du = −√3 / 4``: the 16 × 16
    Gauss points fall 8 on either side of the edge, so the lit fraction is exact and the moment 3.0e-3 off (the
    rule integrates a step)."""
    floor = square()
    wall = [[0.0, -2.0, 0.0], [0.0, 2.0, 0.0], [0.0, 2.0, 3.0], [0.0, -2.0, 3.0]]
    scene = scene_of([floor, wall])
    G = moment_form_factors(scene, 1)
    d = torch.tensor([1.0, 0.0, -0.2], dtype=F64)
    g, rough = light_moments(scene, G, d, shadow_order=16, rough=True)
    cos = 0.2 / math.sqrt(1.04)
    assert float(g[0, 0]) == pytest.approx(0.5 * cos, rel=1e-9)
    sign = 1.0 if float(facet_basis(scene, 1).axes[0, 0, 0]) > 0 else -1.0
    assert float(g[0, 1]) == pytest.approx(-sign * math.sqrt(3) / 4 * cos, rel=4e-3)
    assert bool(rough[0]) and light_is_rough(scene, d)
    assert not light_is_rough(scene, torch.tensor([0.0, 0.0, -1.0], dtype=F64))


def test_light_moments_reject_bad_input():
    scene, _ = hinge(90.0)
    G = moment_form_factors(scene, 1)
    with pytest.raises(ValueError, match="material name"):
        light_moments(scene, G, "lamp")
    with pytest.raises(ShapeError, match="mask"):
        light_moments(scene, G, torch.tensor([True, False, True]))
    with pytest.raises(ValueRangeError, match="non-negative"):
        light_moments(scene, G, torch.tensor([-1.0, 1.0], dtype=F64))


# ------------------------------------------------------------------------------------------------- the solve
def test_closed_box_solution_is_exact(dtype):
    """Uniform r and E0 in a closed box: ``E = E0 / (1 − r)`` on every facet, no higher moments (float32 within
    its precision)."""
    box = ti.scenes.closed_box(divisions=2, dtype=dtype)
    G = moment_form_factors(box, 2)
    c = solve_moments(G, torch.full((box.num_facets,), 0.75, dtype=dtype), light_moments(box, G)[..., None].to(dtype))
    assert c.dtype == dtype and c.shape == (24, 6, 1)
    tol = 2e-5 if dtype == F64 else 1e-4
    assert torch.allclose(facet_averages(c), torch.full((24, 1), 4.0, dtype=dtype), rtol=tol)
    assert float(c[:, 1:].abs().max()) < 4 * tol


def test_two_facets_degree_zero_formula():
    """Degree 0 is the piecewise-constant model: ``E_1 = (E0_1 + F_12 r_2 E0_2) / (1 − F_12 F_21 r_1 r_2)``."""
    scene, _ = hinge(60.0)
    G = moment_form_factors(scene, 0, quadrature_tol=1e-9)
    F12, F21 = float(G.matrix[0, 1]), float(G.matrix[1, 0])
    r = torch.tensor([0.7, 0.4], dtype=F64)
    e0 = torch.tensor([[[1.0]], [[2.0]]], dtype=F64)
    E = solve_moments(G, r, e0)[:, 0, 0]
    assert float(E[0]) == pytest.approx((1 + F12 * 0.4 * 2) / (1 - F12 * F21 * 0.28), rel=1e-12)


def test_dense_and_cg_agree_and_batches_broadcast():
    scene, _ = hinge(45.0, n=3)
    G = moment_form_factors(scene, 2)
    g = light_moments(scene, G, torch.tensor([0.3, 0.1, -1.0], dtype=F64))
    r = torch.rand(4, scene.num_facets, 3, dtype=F64, generator=torch.Generator().manual_seed(0)) * 0.9
    e0 = g[:, :, None] * torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    a = solve_moments(G, r, e0, method="dense")
    b = solve_moments(G, r, e0, method="cg", tol=1e-12)
    assert a.shape == (4, scene.num_facets, 6, 3)
    assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)


def test_solve_gradcheck():
    scene, _ = hinge(50.0)
    G = moment_form_factors(scene, 1)
    g = light_moments(scene, G, torch.tensor([0.2, 0.1, -1.0], dtype=F64))
    r = torch.tensor([[0.6, 0.3], [0.5, 0.8]], dtype=F64, requires_grad=True)
    e0 = (g[:, :, None] * torch.tensor([1.0, 0.5], dtype=F64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda r_, e_: solve_moments(G, r_, e_), (r, e0))


def test_solve_rejects_bad_input():
    scene, _ = hinge(50.0)
    G = moment_form_factors(scene, 1)
    with pytest.raises(ShapeError, match=r"\[\.\.\., F, nb, L\]"):
        solve_moments(G, torch.full((2,), 0.5, dtype=F64), torch.ones(2, 6, 1, dtype=F64))
    with pytest.raises(ValueRangeError, match="reflectance must lie in"):
        solve_moments(G, torch.full((2,), 1.5, dtype=F64), torch.ones(2, 3, 1, dtype=F64))
    with pytest.raises(ValueError, match="max_iter"):
        solve_moments(G, torch.full((2,), 0.5, dtype=F64), torch.ones(2, 3, 1, dtype=F64), max_iter=0)
    with pytest.raises(TypeError, match="MomentFormFactors"):
        solve_moments(ti.form_factors(scene), torch.full((2,), 0.5, dtype=F64), torch.ones(2, 3, 1, dtype=F64))


def test_degree_convergence_on_a_groove():
    """The 30° V-groove (4 × 4 facets per plate, r = 0.9, uniform light): facet averages against degree 2 on the
    scene subdivided 4 ×. Measured: see the asserts (each degree at least 3 × better than the last)."""
    scene = ti.scenes.v_groove(30.0, divisions=4, dtype=F64)
    d = "uniform"
    fine, parent = scene.subdivide(4)
    Gf = moment_form_factors(fine, 2)
    cf = solve_moments(Gf, torch.full((fine.num_facets,), 0.9, dtype=F64), light_moments(fine, Gf, d)[..., None])
    ref = ti.geometry.area_average(facet_averages(cf), parent, fine.areas, scene.num_facets)[:, 0]
    G = moment_form_factors(scene, 2)
    g = light_moments(scene, G, d)
    err = []
    for degree in (0, 1, 2):
        Gd = G.truncate(degree)
        E = facet_averages(solve_moments(Gd, torch.full((32,), 0.9, dtype=F64), g[:, : Gd.size, None]))[:, 0]
        err.append(float(((E - ref) / ref).square().mean().sqrt()))
    assert err[0] > 3 * err[1] > 9 * err[2]
    assert err[2] < 2e-3


def test_resampled_visibility_changes_only_the_occluded_pairs():
    """Drawing the occluded pairs' rays again keeps every other pair's moments bit for bit, and the same seed gives
    the same matrix as a fresh call."""
    from torch_interreflect.formfactors.moments import resample_visibility

    blocker = [[-0.8, -0.8, 0.5], [0.1, -0.8, 0.5], [0.1, 0.3, 0.5], [-0.8, 0.3, 0.5]]
    side = [[0.7, -0.5, 0.0], [0.7, 0.5, 0.0], [0.7, 0.5, 1.0], [0.7, -0.5, 1.0]]  # sees the floor, unblocked
    scene = scene_of([square(), square(1.0, flip=True), blocker, blocker[::-1], side])
    G = moment_form_factors(scene, 2, seed=0)
    H = resample_visibility(G, seed=1)
    again = resample_visibility(H, seed=0)
    assert torch.equal(again.matrix, G.matrix)
    assert not torch.equal(H.matrix, G.matrix)
    blocks = (H.matrix - G.matrix).reshape(5, 6, 5, 6).abs().amax((1, 3)) > 0
    assert not bool(blocks[0, 4]) and not bool(blocks[4, 0])  # floor–side pair: never blocked, never resampled
    assert torch.equal(resample_visibility(G, seed=3, visibility_samples=6).matrix,
                       moment_form_factors(scene, 2, seed=3, visibility_samples=6).matrix)
    with pytest.raises(ValueError, match="resample_visibility needs"):
        resample_visibility(G.truncate(1), seed=1)


@pytest.mark.parametrize("threads", [1, 2])
def test_moments_and_sky_keep_torch_threads_and_bits(threads, monkeypatch):
    """``moment_form_factors`` and ``light_moments`` run their torch glue on one thread and their compiled loops and
    rays on the caller's (``_threads.compiled_work``): torch has one thread while their loops launch, its count comes
    back as it was, and the moments and the sky's ray-cast moments (occluded pairs, escaping rays) are the same bits
    at 1 and 2 threads."""
    from torch_interreflect._threads import work_threads
    from torch_interreflect.formfactors import compiled, hemisphere, moments

    seen = []

    def spy(kernel, *args):
        seen.append((torch.get_num_threads(), work_threads()))
        return compiled.launch(kernel, *args)

    monkeypatch.setattr(moments, "launch", spy)
    monkeypatch.setattr(hemisphere, "launch", spy)
    scene = ti.geometry.split_at_contacts(ti.scenes.cornell_box(divisions=1, light=False, dtype=torch.float64))[0]
    prev = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        K1 = moment_form_factors(scene, 2, quadrature_tol=1e-4)
        g1 = light_moments(scene, K1, "sky", sky_samples=4, sky_points=4)
        torch.set_num_threads(threads)
        seen.clear()
        K = moment_form_factors(scene, 2, quadrature_tol=1e-4)
        assert torch.get_num_threads() == threads
        g = light_moments(scene, K, "sky", sky_samples=4, sky_points=4)
        assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(prev)
    assert len(seen) >= 4 and set(seen) == {(1, threads)}  # the pairs' loops, the rays' set-up, the sky's rays
    assert K.info["occluded_pairs"] > 0 and torch.equal(K.matrix, K1.matrix) and torch.equal(g, g1)


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
    as_list = moment_form_factors(scene, 1, across=mask.tolist()).matrix.reshape(F, 3, F, 3)  # a list is a mask too
    assert torch.equal(as_list, part)
    with pytest.raises(ShapeError, match="across"):
        moment_form_factors(scene, 1, across=mask[:-1].tolist())
