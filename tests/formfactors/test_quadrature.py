"""Form factors against exact references (Howell's catalogue, closure, reciprocity, clipping, occlusion)."""

import math

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from tests.oracles import HOWELL_C16, reference_tolerance
from torch_interreflect.formfactors import point_polygon_factor


def rect(o, a, b, na=1, nb=1):
    return ti.scenes.grid_quads(o, a, b, na, nb).tolist()


def plate_ff(P, Q, dtype=torch.float64, **kw):
    """Area-weighted form factor from the union of polygons P to the union of Q."""
    scene = ti.Scene.from_polygons(torch.tensor(P + Q, dtype=dtype))
    K = ti.form_factors(scene, **kw)
    F = K.to_dense().double()
    A = scene.areas.double()
    n = len(P)
    return float((A[:n, None] * F[:n, n:]).sum() / A[:n].sum()), K


def hinge(phi_deg, n=1, **kw):
    phi = math.radians(phi_deg)
    d = [math.cos(phi), 0.0, math.sin(phi)]
    return plate_ff(rect([0, 0, 0], [1, 0, 0], [0, 1, 0], n, n), rect([0, 0, 0], [0, 1, 0], d, n, n), **kw)


def c14(l, w, h):
    """Howell C-14: perpendicular rectangles with a common edge of length l, from width w to width h."""
    H, W = h / l, w / l
    s = H * H + W * W
    log = (
        math.log((1 + W * W) * (1 + H * H) / (1 + s))
        + W * W * math.log(W * W * (1 + s) / ((1 + W * W) * s))
        + H * H * math.log(H * H * (1 + s) / ((1 + H * H) * s))
    )
    return (W * math.atan(1 / W) + H * math.atan(1 / H) - math.sqrt(s) * math.atan(1 / math.sqrt(s)) + log / 4) / (
        math.pi * W
    )


def c11(a, b, c):
    """Howell C-11: directly opposed parallel rectangles a × b at distance c."""
    X, Y = a / c, b / c
    return (2 / (math.pi * X * Y)) * (
        0.5 * math.log((1 + X * X) * (1 + Y * Y) / (1 + X * X + Y * Y))
        + X * math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))
        + Y * math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
        - X * math.atan(X)
        - Y * math.atan(Y)
    )


# DESIGN.md's table (tests/oracles.py); the reference has 5-7 significant digits, so the tolerance is the larger
# of 1e-6 relative and half a unit in the reference's last digit. Measured: |error| <= 3.4e-7 (n = 1 and 6), i.e.
# within the reference's rounding; C-14 and C-11 are checked against their closed forms (full precision) below.
tolerance = reference_tolerance


@pytest.mark.parametrize(("angle", "ref"), HOWELL_C16)
def test_howell_c16_hinged_squares(angle, ref):
    value, _ = hinge(angle)
    assert abs(value - ref) <= tolerance(ref, 1e-6), (value, ref)


@pytest.mark.parametrize(("angle", "ref"), HOWELL_C16)
def test_howell_c16_subdivided_6x6(angle, ref):
    value, _ = hinge(angle, n=6)
    assert abs(value - ref) <= tolerance(ref, 1e-6), (value, ref)


# relative errors against the closed forms, measured at the default quadrature_tol = 1e-6: C-14 2.0e-7 (n = 1),
# 3.3e-8 (n = 6); C-11 4.1e-11 (n = 1), 5.5e-9 (n = 6). Bounds ~3x.
C14_RTOL = {1: 6e-7, 6: 1e-7}
C11_RTOL = {1: 2e-10, 6: 2e-8}


@pytest.mark.parametrize("n", [1, 6])
def test_howell_c14_perpendicular(n):
    value, _ = plate_ff(rect([0, 0, 0], [1, 0, 0], [0, 1, 0], n, n), rect([0, 0, 0], [0, 1, 0], [0, 0, 1], n, n))
    exact = c14(1, 1, 1)
    assert abs(value - exact) <= C14_RTOL[n] * exact
    # unequal widths: from w=1 to h=2 along a common edge of length 1
    value, _ = plate_ff(rect([0, 0, 0], [1, 0, 0], [0, 1, 0], n, n), rect([0, 0, 0], [0, 1, 0], [0, 0, 2], n, n))
    exact = c14(1, 1, 2)
    assert abs(value - exact) <= C14_RTOL[n] * exact
    assert abs(c14(1, 1, 2) - 0.2328526) < 1e-7  # the oracle itself against the catalogue
    assert abs(c14(1, 1, 1) - 0.2000438) < 1e-7


@pytest.mark.parametrize(("gap", "ref"), [(1.0, 0.1998249), (0.5, 0.4152533), (2.0, 0.0685896)])
@pytest.mark.parametrize("n", [1, 6])
def test_howell_c11_opposed_squares(gap, ref, n):
    value, _ = plate_ff(rect([0, 0, 0], [1, 0, 0], [0, 1, 0], n, n), rect([0, 0, gap], [0, 1, 0], [1, 0, 0], n, n))
    exact = c11(1, 1, gap)
    assert abs(value - exact) <= C11_RTOL[n] * exact
    assert abs(exact - ref) < 1e-7  # the oracle itself against the catalogue


def test_differential_area_under_a_square():
    sq = torch.tensor([[[-0.5, -0.5, 1.0], [-0.5, 0.5, 1.0], [0.5, 0.5, 1.0], [0.5, -0.5, 1.0]]], dtype=torch.float64)
    x = torch.zeros(1, 1, 3, dtype=torch.float64)
    f = point_polygon_factor(x, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), sq)
    assert abs(float(f) - 0.2394565) < 5e-8


@pytest.mark.parametrize("divisions", [1, 3])
def test_closure_of_a_closed_box(divisions):
    K = ti.form_factors(ti.scenes.closed_box(size=(1.0, 1.5, 0.7), divisions=divisions, dtype=torch.float64))
    assert float((K.row_sums() - 1).abs().max()) < 1e-6
    assert K.info["rays"] == 0  # a convex enclosure: nothing can block anything


@pytest.mark.parametrize("builder", [lambda: ti.scenes.box_corner(divisions=3),
                                     lambda: ti.scenes.cornell_box(divisions=1),
                                     lambda: ti.scenes.w_shape(divisions=(2, 3, 2))])
def test_reciprocity(builder):
    s = builder().to(torch.float64)
    K = ti.form_factors(s)
    AF = s.areas[:, None] * K.to_dense()
    torch.testing.assert_close(AF, AF.T, rtol=0, atol=1e-15)
    assert float(K.to_dense().diagonal().abs().max()) == 0.0


def test_children_of_a_subdivided_facet_sum_to_the_parent():
    coarse = ti.scenes.v_groove(40.0, size=(0.09, 0.06), divisions=(3, 2), dtype=torch.float64)
    fine, parent = coarse.subdivide(3)
    Fc = ti.form_factors(coarse).to_dense()
    Ff = ti.form_factors(fine).to_dense()
    Af = fine.areas
    # A_P F_PQ = Σ_{c∈P} Σ_{d∈Q} A_c F_cd
    P = torch.zeros(coarse.num_facets, fine.num_facets, dtype=torch.float64)
    P[parent, torch.arange(fine.num_facets)] = 1.0
    agg = P @ (Af[:, None] * Ff) @ P.T / coarse.areas[:, None]
    torch.testing.assert_close(agg, Fc, rtol=1e-5, atol=1e-8)


def test_straddling_pairs_are_clipped_at_the_horizon():
    # A: unit square in z=0 facing up. B: unit square in the plane x=0.5 facing +x, standing on A (so A
    # crosses B's plane): only A's half x>0.5 sees B, along a shared line of length 1.
    A = rect([0, 0, 0], [1, 0, 0], [0, 1, 0])
    B = rect([0.5, 0, 0], [0, 1, 0], [0, 0, 1])
    value, _ = plate_ff(A, B)
    assert abs(value - 0.5 * c14(1.0, 0.5, 1.0)) < 1e-6
    # B2 also crosses A's plane: only its upper half (z in [0, 0.5]) is above A
    B2 = rect([0.5, 0, -0.5], [0, 1, 0], [0, 0, 1])
    value, _ = plate_ff(A, B2)
    assert abs(value - 0.5 * c14(1.0, 0.5, 0.5)) < 1e-6


def test_partial_occlusion_has_the_known_visible_fraction():
    # Opposed unit squares at distance 1 with a wall in the plane x=0.5 between them: each half of the lower
    # square sees only the half of the upper square on its side, so F = C-11(0.5 × 1, gap 1).
    A = rect([0, 0, 0], [1, 0, 0], [0, 1, 0])
    B = rect([0, 0, 1], [0, 1, 0], [1, 0, 0])
    wall = rect([0.5, -20, 0.001], [0, 41, 0], [0, 0, 0.998])
    scene = ti.Scene.from_polygons(torch.tensor(A + B + wall, dtype=torch.float64))
    exact = c11(0.5, 1.0, 1.0)
    K = ti.form_factors(scene, visibility_samples=8, visibility_angle=None)  # all 8 × 8, whatever the size
    F_ab = float(K.to_dense()[0, 1])
    assert K.info["occluded_pairs"] >= 1 and K.info["rays"] > 0
    assert abs(F_ab - exact) / exact < 0.009, (F_ab, exact)  # measured 0.29 % (visibility from 8 x 8 rays)
    assert 0.05 < F_ab < 0.1998249 - 0.05  # fractional, not 0 or 1 per pair
    unoccluded = ti.form_factors(scene, occlusion=False).to_dense()[0, 1]
    assert abs(float(unoccluded) - c11(1.0, 1.0, 1.0)) < 2e-10  # measured 4e-11


def test_auto_occlusion_casts_rays_only_where_something_can_block():
    for scene in (ti.scenes.v_groove(30.0, divisions=3), ti.scenes.box_corner(divisions=3)):
        assert ti.form_factors(scene).info["rays"] == 0
    w = ti.scenes.w_shape(divisions=(2, 3, 2), dtype=torch.float64)
    K = ti.form_factors(w)
    K0 = ti.form_factors(w, occlusion=False)
    assert K.info["occluded_pairs"] > 0
    outer = (w.material == 0)[:, None] & (w.material == 3)[None, :]
    assert float(K.to_dense()[outer].sum()) < 0.9 * float(K0.to_dense()[outer].sum())
    # pairs that cannot be blocked keep their exact values
    valley = (w.material == 0)[:, None] & (w.material == 1)[None, :]
    torch.testing.assert_close(K.to_dense()[valley], K0.to_dense()[valley])


def test_monte_carlo_agrees_within_its_noise():
    s = ti.scenes.v_groove(60.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
    exact = 0.370905
    g = torch.Generator().manual_seed(0)
    K = ti.form_factors(s, method="monte_carlo", rays_per_facet=200_000, generator=g)
    sigma = math.sqrt(exact * (1 - exact) / 200_000)
    assert abs(float(K.to_dense()[0, 1]) - exact) < 4 * sigma


def test_dtype_follows_the_scene_and_values_agree(dtype):
    s = ti.scenes.v_groove(45.0, divisions=3, dtype=dtype)
    K = ti.form_factors(s)
    assert K.dtype == dtype and K.areas.dtype == dtype
    K64 = ti.form_factors(s.to(torch.float64))
    torch.testing.assert_close(K.to_dense().double(), K64.to_dense(), rtol=1e-5, atol=1e-7)


def test_sparse_layout_matches_dense():
    s = ti.scenes.box_corner(divisions=4, dtype=torch.float64)
    Kd = ti.form_factors(s, layout="dense")
    Ks = ti.form_factors(s, layout="sparse")
    assert Ks.is_sparse and not Kd.is_sparse
    torch.testing.assert_close(Ks.to_dense(), Kd.to_dense())
    x = torch.rand(2, s.num_facets, 3, dtype=torch.float64)
    torch.testing.assert_close(Ks.matmul(x), Kd.matmul(x))


def test_tighter_tolerance_converges():
    loose, _ = hinge(30.0, quadrature_tol=1e-3)
    tight, _ = hinge(30.0, quadrature_tol=1e-9)
    assert abs(tight - 0.619028) < 1e-6
    assert abs(loose - tight) < 1e-3 * tight


def test_bad_arguments():
    s = ti.scenes.box_corner(divisions=1)
    with pytest.raises(ValueError, match="method must be"):
        ti.form_factors(s, method="hemicube")
    with pytest.raises(ValueError, match="quadrature_tol must lie in"):
        ti.form_factors(s, quadrature_tol=0.0)
    with pytest.raises(ValueError, match="occlusion must be"):
        ti.form_factors(s, occlusion="yes")
    with pytest.raises(TypeError, match="expects a Scene"):
        ti.form_factors(np.zeros((2, 4, 3)))


def test_straddling_triangle_domain():
    # the same half-plane configuration with A split into two triangles along its diagonal
    tri1 = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0]]
    tri2 = [[0.0, 0, 0], [1, 1, 0], [0, 1, 0]]
    B = rect([0.5, 0, 0], [0, 1, 0], [0, 0, 1])[0]
    scene = ti.Scene.concatenate([
        ti.Scene.from_polygons(torch.tensor([tri1, tri2], dtype=torch.float64)),
        ti.Scene.from_polygons(torch.tensor([B], dtype=torch.float64)),
    ])
    K = ti.form_factors(scene).to_dense()
    A = scene.areas
    value = float((A[0] * K[0, 2] + A[1] * K[1, 2]) / (A[0] + A[1]))
    assert abs(value - 0.5 * c14(1.0, 0.5, 1.0)) < 2e-6


def test_old_keyword_names_still_work_with_a_deprecation_warning():
    s = ti.scenes.v_groove(60.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
    new = ti.form_factors(s, quadrature_tol=1e-4).to_dense()
    with pytest.warns(DeprecationWarning, match="quadrature_tol"):
        old = ti.form_factors(s, tol=1e-4).to_dense()
    torch.testing.assert_close(old, new, rtol=0, atol=0)
    with pytest.warns(DeprecationWarning, match="rays_per_facet"):
        ti.form_factors(s, method="monte_carlo", samples=1000, generator=torch.Generator().manual_seed(0))
    with pytest.raises(TypeError, match="both"):
        ti.form_factors(s, tol=1e-4, quadrature_tol=1e-4)


def test_sparse_form_factors_print_no_torch_warnings():
    """Sparse matrices are built without torch's "sparse CSR support is in beta" / "invariant checks are implicitly
    disabled" warnings (they used to appear on every sparse call)."""
    import warnings

    scene = ti.scenes.v_groove(40.0, divisions=3, dtype=torch.float64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        K = ti.form_factors(scene, layout="sparse")
        ti.solve(K, torch.full((scene.num_facets,), 0.8, dtype=torch.float64),
                 torch.ones(scene.num_facets, 1, dtype=torch.float64))
    assert K.matrix.layout == torch.sparse_csr
    assert not [w for w in caught if "sparse" in str(w.message).lower()], [str(w.message) for w in caught]
