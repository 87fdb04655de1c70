"""Hierarchical form factors against the dense kernel: products, solves, reciprocity, near field, gradients."""

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import DeviceError, ShapeError, ValueRangeError

# Measured on these scenes at eta = 0.5 (README "Large scenes" states about 1-1.5 % at ~5,000 facets): products
# 0.31 % (Cornell) / 0.49 % (closed box), row sums 0.48 % RMS / 1.2 % max, E 0.17 % / 0.28 % (Cornell, r = 0.5 /
# 0.9), 0.19 % (room, r = 0.7). The bounds are about 2x what was measured.
PROD_RTOL = 0.01
SOLVE_RTOL = 0.006


def _rel_rms(a, b):
    return float((a - b).norm() / b.norm())


@pytest.fixture(scope="module")
def cornell():
    sc = ti.scenes.cornell_box(divisions=4, dtype=torch.float64)
    dense = ti.form_factors(sc)
    hier = ti.hierarchical_form_factors(sc, leaf_size=4, quadrature_tol=1e-6)
    return sc, dense, hier


@pytest.fixture(scope="module")
def box():
    sc = ti.scenes.closed_box(divisions=8, dtype=torch.float64)
    return sc, ti.form_factors(sc), ti.hierarchical_form_factors(sc, leaf_size=8, quadrature_tol=1e-6)


def test_has_far_blocks_and_info(cornell, box):
    for _, _, h in (cornell, box):
        assert h.num_far_blocks > 0
        for key in ("seconds_tree", "seconds_near", "near_nnz", "far_blocks", "rays", "bytes", "estimated_rel_error"):
            assert key in h.info
        assert h.info["bytes"] > 0


def test_matvec_against_dense(cornell, box):
    for sc, dense, hier in (cornell, box):
        x = torch.rand(sc.num_facets, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        assert _rel_rms(hier.matmul(x), dense.matmul(x)) < PROD_RTOL
        # batched leading dims
        xb = x.T[:, :, None]
        assert torch.allclose(hier.matmul(xb)[..., 0].T, hier.matmul(x))


def test_closure_closed_box(box):
    _, _, hier = box
    rs = hier.row_sums()
    assert float((rs - 1).pow(2).mean().sqrt()) < PROD_RTOL
    assert float((rs - 1).abs().max()) < 2.5 * PROD_RTOL


def test_reciprocity(cornell):
    sc, _, hier = cornell
    g = torch.Generator().manual_seed(1)
    x = torch.rand(sc.num_facets, 1, dtype=torch.float64, generator=g)
    y = torch.rand(sc.num_facets, 1, dtype=torch.float64, generator=g)
    a = sc.areas[:, None]
    lhs = float((x * a * hier.matmul(y)).sum())
    rhs = float((y * a * hier.matmul(x)).sum())
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)


def test_near_field_equals_dense_entries(cornell):
    _, dense, hier = cornell
    near = hier.near.to_dense()
    d = dense.to_dense()
    mask = near != 0
    assert int(mask.sum()) > 0
    assert torch.allclose(near[mask], d[mask], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("r", [0.5, 0.9])
def test_solve_against_dense(cornell, r):
    sc, dense, hier = cornell
    e0 = ti.lights.light_geometry(sc, dense, "light")[:, None]
    refl = torch.full((sc.num_facets,), r, dtype=torch.float64)
    E = ti.solve(dense, refl, e0)
    Eh, info = ti.solver.solve_with_info(hier, refl, e0, method="cg", tol=1e-8)
    assert info.converged and info.method == "cg"
    assert _rel_rms(Eh, E) < SOLVE_RTOL
    En = ti.solve(hier, refl, e0, method="neumann", tol=1e-10)
    assert _rel_rms(En, Eh) < 1e-6


def test_room_small():
    sc = ti.scenes.room(divisions=2, dtype=torch.float64)
    dense = ti.form_factors(sc)
    hier = ti.hierarchical_form_factors(sc, leaf_size=8, quadrature_tol=1e-6)
    assert hier.num_far_blocks > 0
    e0 = ti.lights.light_geometry(sc, dense, "lamp")[:, None]
    e0h = ti.lights.light_geometry(sc, hier, "lamp")[:, None]
    assert _rel_rms(e0h, e0) < PROD_RTOL
    refl = torch.full((sc.num_facets,), 0.7, dtype=torch.float64)
    assert _rel_rms(ti.solve(hier, refl, e0), ti.solve(dense, refl, e0)) < SOLVE_RTOL


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtypes(dtype):
    sc = ti.scenes.closed_box(divisions=6, dtype=dtype)
    hier = ti.hierarchical_form_factors(sc, leaf_size=4)
    assert hier.dtype == dtype and hier.num_far_blocks > 0
    E = ti.solve(hier, torch.full((sc.num_facets,), 0.5, dtype=dtype), torch.ones(sc.num_facets, 2, dtype=dtype))
    assert E.dtype == dtype
    # closed box, uniform light: E = E0 / (1 - r) up to the far-field error of the row sums
    assert float((E - 2.0).abs().max()) < 0.05  # measured 0.021 (float32), 0.016 (float64)
    h64 = hier.to(torch.float64)
    x = torch.rand(sc.num_facets, 2, dtype=torch.float64)
    assert torch.allclose(hier.matmul(x.to(dtype)).double(), h64.matmul(x), rtol=1e-4, atol=1e-6)


def test_gradcheck_reflectance_and_e0():
    sc = ti.scenes.closed_box(divisions=3, dtype=torch.float64)
    hier = ti.hierarchical_form_factors(sc, leaf_size=2)
    assert hier.num_far_blocks > 0
    g = torch.Generator().manual_seed(3)
    r = (0.8 * torch.rand(sc.num_facets, 2, dtype=torch.float64, generator=g)).requires_grad_()
    e0 = torch.rand(sc.num_facets, 2, dtype=torch.float64, generator=g).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: ti.solve(hier, a, b, tol=1e-12), (r, e0))
    # the n-bounce series goes through the (differentiable) products
    assert torch.autograd.gradcheck(lambda a, b: ti.solve(hier, a, b, bounces=3), (r, e0))


def test_dense_operator_matches_matmul(box):
    sc, _, hier = box
    d = hier.to_dense()
    x = torch.rand(sc.num_facets, 2, dtype=torch.float64)
    assert torch.allclose(d @ x, hier.matmul(x), rtol=1e-10, atol=1e-12)


def test_bad_input():
    sc = ti.scenes.closed_box(divisions=2, dtype=torch.float64)
    with pytest.raises(TypeError):
        ti.hierarchical_form_factors(sc.corners)
    with pytest.raises(ValueRangeError, match="eta"):
        ti.hierarchical_form_factors(sc, eta=0.0)
    with pytest.raises(ValueRangeError, match="leaf_size"):
        ti.hierarchical_form_factors(sc, leaf_size=0)
    with pytest.raises(ValueError, match="occlusion"):
        ti.hierarchical_form_factors(sc, occlusion="yes")
    hier = ti.hierarchical_form_factors(sc, leaf_size=2)
    with pytest.raises(ShapeError):
        hier.matmul(torch.ones(5, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="dense"):
        ti.solve(hier, torch.full((24,), 0.5, dtype=torch.float64), torch.ones(24, 1, dtype=torch.float64),
                 method="dense")
    with pytest.raises(ValueRangeError, match="reflectance"):
        ti.solve(hier, torch.full((24,), 1.5, dtype=torch.float64), torch.ones(24, 1, dtype=torch.float64))


def test_operator_promotes_dtypes_like_solve_and_refuses_other_devices():
    sc = ti.scenes.closed_box(divisions=3, dtype=torch.float32)
    hier = ti.hierarchical_form_factors(sc, leaf_size=2)
    assert hier.dtype == torch.float32 and hier.num_far_blocks > 0
    x = torch.rand(sc.num_facets, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    y = hier.matmul(x)  # float32 operator, float64 input: computed and returned in float64
    assert y.dtype == torch.float64
    torch.testing.assert_close(y, hier.to(torch.float64).matmul(x), rtol=0, atol=0)
    assert hier.matmul(x.float()).dtype == torch.float32
    with pytest.raises(DeviceError, match=r"meta.*cpu"):
        hier.matmul(x.to("meta"))
