"""Forward tests of :func:`torch_interreflect.solve.solve` against closed-form oracles and dense references."""

from __future__ import annotations

import itertools
import warnings

import pytest
import torch

from tests.oracles import per_column_solve, random_reciprocal
from torch_interreflect import FormFactors
from torch_interreflect.errors import ConvergenceWarning, ShapeError, SingularSystemError, ValueRangeError
from torch_interreflect.solver import SolveInfo, radiance, solve, solve_with_info

F64 = torch.float64
METHODS = ["dense", "cg", "neumann"]


# ------------------------------------------------------------------------------------------ builders
def sphere(n: int, dtype: torch.dtype = F64, seed: int = 0) -> FormFactors:
    """Sphere interior: F_ij = A_j / A_total (closed, reciprocal) with random positive areas."""
    g = torch.Generator().manual_seed(seed)
    areas = (torch.rand(n, generator=g, dtype=F64) + 0.5).to(dtype)
    return FormFactors(areas.expand(n, n) / areas.sum(), areas)


def two_facets(f12: float, a1: float, a2: float, dtype: torch.dtype = F64) -> FormFactors:
    f21 = a1 * f12 / a2
    return FormFactors(torch.tensor([[0.0, f12], [f21, 0.0]], dtype=dtype), torch.tensor([a1, a2], dtype=dtype))


def closed_ring(n: int, dtype: torch.dtype = F64, seed: int = 0) -> FormFactors:
    """A closed enclosure with a spread spectrum: random walk on a weighted ring-with-chords graph.

    W symmetric, A_i = Σ_j W_ij, F_ij = W_ij / A_i: row sums exactly 1 and A_i F_ij = W_ij symmetric.
    """
    g = torch.Generator().manual_seed(seed)
    w = torch.zeros(n, n, dtype=F64)
    i = torch.arange(n)
    for k in (1, 2, 5):
        w[i, (i + k) % n] = torch.rand(n, generator=g, dtype=F64) + 0.2
    w = w + w.T
    areas = w.sum(1)
    return FormFactors((w / areas[:, None]).to(dtype), areas.to(dtype))


def block_diag(*ffs: FormFactors) -> FormFactors:
    return FormFactors(torch.block_diag(*[f.matrix for f in ffs]), torch.cat([f.areas for f in ffs]))


def reference(ff: FormFactors, r: torch.Tensor, e0: torch.Tensor) -> torch.Tensor:
    """torch.linalg.solve on (I - F R) per column; r, e0 as [..., F, L]."""
    return per_column_solve(ff.to_dense(), r, e0)


# ------------------------------------------------------------------------------------------ closed forms
@pytest.mark.parametrize("method", [*METHODS, "auto"])
def test_two_facet_closed_form(method: str) -> None:
    f12, a1, a2 = 0.3, 1.0, 2.5
    ff = two_facets(f12, a1, a2)
    f21 = a1 * f12 / a2
    r = torch.tensor([[0.7, 0.2, 0.95], [0.4, 0.9, 0.0]], dtype=F64)
    e0 = torch.tensor([[1.0, 2.0, 0.5], [0.3, 0.0, 4.0]], dtype=F64)
    e = solve(ff, r, e0, method=method, tol=1e-13)
    den = 1 - f12 * f21 * r[0] * r[1]
    torch.testing.assert_close(e[0], (e0[0] + f12 * r[1] * e0[1]) / den, rtol=1e-11, atol=0)
    torch.testing.assert_close(e[1], (e0[1] + f21 * r[0] * e0[0]) / den, rtol=1e-11, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("method", [*METHODS, "auto"])
@pytest.mark.parametrize("rho", [0.5, 0.9, 0.99, 0.999])
def test_closed_enclosure(rho: float, method: str, dtype: torch.dtype) -> None:
    if method == "neumann" and rho == 0.999:
        pytest.skip("the Neumann series needs ~14 000 products at r = 0.999 (the reason cg exists)")
    ff = sphere(40, dtype)
    e0 = torch.rand(1, 31, dtype=dtype).expand(40, 31) + 1
    e = solve(ff, torch.full((40,), rho, dtype=dtype), e0, method=method)
    torch.testing.assert_close(e, e0 / (1 - rho), rtol=1e-3 if dtype == torch.float32 else 1e-5, atol=0)


@pytest.mark.parametrize("method", ["cg", "dense"])
def test_float32_r0999_spread_spectrum(method: str) -> None:
    """r = 0.999 in a closed enclosure whose G has a spread spectrum; float32 within 1e-3 of float64."""
    n = 200
    ff64 = closed_ring(n)
    ff32 = ff64.to(torch.float32)
    # uniform light: exact E0 / (1 - r)
    e, info = solve_with_info(ff32, torch.full((n,), 0.999), torch.ones(n, 3), method=method)
    torch.testing.assert_close(e, torch.full_like(e, 1000.0), rtol=1e-3, atol=0)
    # non-uniform light: a few hundred CG iterations at most; compared with a float64 reference
    g = torch.Generator().manual_seed(1)
    e0 = torch.rand(n, 4, generator=g, dtype=F64)
    r = 0.999 - 0.01 * torch.rand(n, 4, generator=g, dtype=F64)
    r[:, 0] = 0.999
    ref = reference(ff64, r, e0)
    e, info = solve_with_info(ff32, r.float(), e0.float(), method=method)
    assert (e.double() - ref).norm() / ref.norm() <= 1e-3
    if method == "cg":
        assert 10 < info.iterations < 1000
        assert info.converged


def test_singular_closed_r1() -> None:
    ff = sphere(10)
    for method in [*METHODS, "auto"]:
        with pytest.raises(SingularSystemError, match="singular"):
            solve(ff, torch.ones(10, dtype=F64), torch.ones(10, 2, dtype=F64), method=method)
    # r = 1 in only one wavelength column is enough
    r = torch.full((10, 3), 0.5, dtype=F64)
    r[:, 1] = 1
    with pytest.raises(SingularSystemError, match="closed group of 10 facets"):
        solve(ff, r, torch.ones(10, 3, dtype=F64))


def test_r1_open_scene_is_solvable() -> None:
    ff = random_reciprocal(12, scale=0.8)
    r = torch.ones(12, 2, dtype=F64)
    e0 = torch.rand(12, 2, dtype=F64)
    ref = reference(ff, r, e0)
    for method in METHODS:
        torch.testing.assert_close(solve(ff, r, e0, method=method, tol=1e-12), ref, rtol=1e-9, atol=1e-12)


# -------------------------------------------------------------------------------------- degenerate inputs
@pytest.mark.parametrize("method", [*METHODS, "auto"])
def test_zero_reflectance(method: str) -> None:
    ff = random_reciprocal(15)
    g = torch.Generator().manual_seed(3)
    e0 = torch.rand(2, 15, 4, generator=g, dtype=F64)
    r = torch.rand(2, 15, 4, generator=g, dtype=F64)
    r[:, :5] = 0  # five facets never reflect
    r[1, :, 2] = 0  # one column reflects nowhere
    e, info = solve_with_info(ff, r, e0, method=method, tol=1e-13)
    torch.testing.assert_close(e, reference(ff, r, e0), rtol=1e-10, atol=1e-13)
    if method == "dense":
        assert info.facets_skipped == 5
    # all zero
    e = solve(ff, torch.zeros(15, dtype=F64), e0, method=method)
    torch.testing.assert_close(e, e0, rtol=0, atol=0)


@pytest.mark.parametrize("method", [*METHODS, "auto"])
def test_zero_light_and_one_facet(method: str) -> None:
    ff = random_reciprocal(6)
    e = solve(ff, torch.full((6, 3), 0.5, dtype=F64), torch.zeros(6, 3, dtype=F64), method=method)
    assert torch.equal(e, torch.zeros(6, 3, dtype=F64))
    one = FormFactors(torch.zeros(1, 1, dtype=F64), torch.ones(1, dtype=F64))
    e, info = solve_with_info(
        one, torch.tensor([0.7], dtype=F64), torch.tensor([[2.0, 3.0]], dtype=F64), method=method
    )
    assert torch.equal(e, torch.tensor([[2.0, 3.0]], dtype=F64))
    assert info.facets_skipped == 1 and info.num_components == 0


def test_no_exchange_gives_e0() -> None:
    ff = FormFactors(torch.zeros(7, 7, dtype=F64), torch.ones(7, dtype=F64))
    e0 = torch.rand(3, 7, 5, dtype=F64)
    for method in [*METHODS, "auto"]:
        e, info = solve_with_info(ff, torch.full((7, 5), 0.9, dtype=F64), e0, method=method)
        assert torch.equal(e, e0)
        assert info.facets_skipped == 7


@pytest.mark.parametrize("method", ["auto", "cg"])
def test_thousands_of_facets(method: str) -> None:
    n = 3000
    ff = sphere(n)
    e0 = torch.rand(n, 8, dtype=F64)
    r = torch.full((n, 8), 0.8, dtype=F64)
    e, info = solve_with_info(ff, r, e0, method=method)
    # sphere interior: E = E0 + r/(1 - r) * (A·E0)/A_total for uniform r
    mean = (ff.areas[:, None] * e0).sum(0) / ff.areas.sum()
    torch.testing.assert_close(e, e0 + 0.8 / 0.2 * mean, rtol=1e-5, atol=0)
    assert info.residual < 1e-5


def test_components_and_isolated_facets() -> None:
    a, b = random_reciprocal(8, seed=1), closed_ring(10, seed=2)
    iso = FormFactors(torch.zeros(3, 3, dtype=F64), torch.ones(3, dtype=F64))
    ff = block_diag(a, iso, b)
    perm = torch.randperm(21, generator=torch.Generator().manual_seed(0))
    ff = FormFactors(ff.matrix[perm][:, perm], ff.areas[perm])
    r = torch.rand(2, 21, 3, dtype=F64) * 0.9
    e0 = torch.rand(2, 21, 3, dtype=F64)
    ref = reference(ff, r, e0)
    for method in METHODS:
        e, info = solve_with_info(ff, r, e0, method=method, tol=1e-13)
        torch.testing.assert_close(e, ref, rtol=1e-10, atol=1e-13)
        assert info.num_components == 2
        assert info.facets_skipped == 3
    # the plan is cached on the FormFactors and reused
    plan = ff.info["_solve_plan"]
    solve(ff, r, e0)
    assert ff.info["_solve_plan"] is plan


@pytest.mark.parametrize("method", METHODS)
def test_sparse_matches_dense(method: str) -> None:
    dense = block_diag(closed_ring(30, seed=4), random_reciprocal(12, seed=5))
    sparse = dense.to_sparse()
    r = torch.rand(30 + 12, 4, dtype=F64) * 0.95
    e0 = torch.rand(2, 42, 4, dtype=F64)
    e_sparse = solve(sparse, r, e0, method=method, tol=1e-12)
    torch.testing.assert_close(e_sparse, reference(dense, r, e0), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(solve(sparse, r, e0, bounces=3), solve(dense, r, e0, bounces=3))


# --------------------------------------------------------------------------------------------- n-bounce
def test_bounces() -> None:
    ff = random_reciprocal(9)
    r = torch.rand(2, 9, 3, dtype=F64)
    e0 = torch.rand(2, 9, 3, dtype=F64)
    torch.testing.assert_close(solve(ff, r, e0, bounces=1), e0, rtol=0, atol=0)
    torch.testing.assert_close(solve(ff, r, e0, bounces=2), e0 + ff.matrix @ (r * e0))
    e3 = e0 + ff.matrix @ (r * e0) + ff.matrix @ (r * (ff.matrix @ (r * e0)))
    torch.testing.assert_close(solve(ff, r, e0, bounces=3), e3)
    inf = solve(ff, r, e0, tol=1e-13)
    errs = [float((solve(ff, r, e0, bounces=n) - inf).abs().max()) for n in (1, 2, 4, 8, 16, 64)]
    assert all(b < a for a, b in itertools.pairwise(errs))
    assert errs[-1] < 1e-9
    _, info = solve_with_info(ff, r, e0, bounces=64)
    assert info.method == "series" and info.iterations == 63


# ------------------------------------------------------------------------------------------- agreement
def test_dense_cg_neumann_agree_and_float32() -> None:
    ff = closed_ring(64, seed=7)
    g = torch.Generator().manual_seed(8)
    r = torch.rand(3, 64, 31, generator=g, dtype=F64) * 0.95
    e0 = torch.rand(3, 64, 31, generator=g, dtype=F64)
    ed = solve(ff, r, e0, method="dense")
    for method in ("cg", "neumann"):
        e, info = solve_with_info(ff, r, e0, method=method, tol=1e-8)
        assert info.converged and info.residual < 1e-7
        assert float(((e - ed).norm(dim=-2) / ed.norm(dim=-2)).max()) <= info.relative_error_bound + 1e-12
        torch.testing.assert_close(e, ed, rtol=1e-6, atol=0)
    ff32 = ff.to(torch.float32)
    for method in METHODS:
        e32 = solve(ff32, r.float(), e0.float(), method=method)
        assert e32.dtype == torch.float32
        torch.testing.assert_close(e32.double(), ed, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_cg_frozen_columns_keep_their_converged_values(monkeypatch, dtype: torch.dtype) -> None:
    """CG keeps converged columns in its working set, frozen, until they are ``COMPACT_FRACTION`` of it: the result
    is the same whether they are dropped at once (0), at half (the default) or only at the end, since a frozen
    column's step is 0 (up to the rounding of products over more columns: measured 0.3 and 1.2 units of the last
    place of the largest entry in float32 and float64), and columns from r = 0.05 to 0.95 (converging many iterations
    apart) meet the dense solve within the error tolerance (measured 3.9e-7 and 6.0e-8 at tol 1e-6)."""
    from torch_interreflect.solver import krylov

    ff = closed_ring(64, dtype=dtype, seed=3)
    g = torch.Generator().manual_seed(4)
    r = (torch.linspace(0.05, 0.95, 40, dtype=F64)[:, None, None] * (0.9 + 0.1 * torch.rand(40, 64, 1, generator=g,
                                                                                            dtype=F64))).to(dtype)
    e0 = torch.rand(40, 64, 1, generator=g, dtype=F64).to(dtype)
    out = {}
    for frac in (0.0, 0.5, 1.01):
        monkeypatch.setattr(krylov, "COMPACT_FRACTION", frac)
        out[frac], info = solve_with_info(ff, r, e0, method="cg", tol=1e-6)
        assert info.converged
    eps = torch.finfo(dtype).eps
    for frac in (0.5, 1.01):
        assert float((out[frac] - out[0.0]).abs().max() / out[0.0].abs().max()) <= 4 * eps
    ed = solve(ff.to(F64), r.double(), e0.double(), method="dense")
    err = float(((out[0.5].double() - ed).norm(dim=-2) / ed.norm(dim=-2)).max())
    assert err <= 1e-6


def test_broadcast_shapes_and_grey() -> None:
    ff = random_reciprocal(5)
    r_grey = torch.rand(5, dtype=F64)
    e0 = torch.rand(4, 5, 7, dtype=F64)
    e, info = solve_with_info(ff, r_grey, e0, method="dense")
    assert e.shape == (4, 5, 7)
    assert info.distinct_columns == 1 and info.num_columns == 28
    torch.testing.assert_close(e, reference(ff, r_grey[:, None], e0))
    # [B, F] grey batch with E0 [F, 1]
    rb = torch.rand(3, 5, dtype=F64)
    e = solve(ff, rb, torch.ones(5, 1, dtype=F64))
    assert e.shape == (3, 5, 1)
    # E0 as a plain [F] vector: shape in = shape out
    assert solve(ff, r_grey, torch.ones(5, dtype=F64)).shape == (5,)
    # mixed dtypes promote
    assert solve(ff, r_grey.float(), e0.float()).dtype == F64


# ---------------------------------------------------------------------------------------------- errors
def test_validation_errors() -> None:
    ff = random_reciprocal(20)
    r = torch.full((20, 4), 0.5, dtype=F64)
    e0 = torch.ones(20, 4, dtype=F64)
    bad = r.clone()
    bad[12, 2] = 1.7
    with pytest.raises(ValueRangeError, match=r"reflectance must lie in \[0, 1\]; got max 1.7 at facet 12"):
        solve(ff, bad, e0)
    bad[12, 2] = -0.1
    with pytest.raises(ValueRangeError, match=r"got min -0\.1 at facet 12"):
        solve(ff, bad, e0)
    bad[12, 2] = float("nan")
    with pytest.raises(ValueRangeError, match="reflectance must be finite; got nan at facet 12"):
        solve(ff, bad, e0)
    bad_e0 = e0.clone()
    bad_e0[3, 1] = float("inf")
    with pytest.raises(ValueRangeError, match="E0 must be finite; got inf at facet 3"):
        solve(ff, r, bad_e0)
    m = ff.matrix.clone()
    m[2, 5] = float("nan")
    with pytest.raises(ValueRangeError, match=r"form factors must be finite.*F\[2, 5\]"):
        solve(FormFactors(m, ff.areas), r, e0)
    with pytest.raises(ShapeError, match=r"F = 20 facets; got \[19, 4\]"):
        solve(ff, r[:19], e0)
    with pytest.raises(ShapeError, match="E0 must have shape"):
        solve(ff, r, torch.ones(4, 20, dtype=F64))
    with pytest.raises(ShapeError, match="wavelength counts L = 4 vs 31"):
        solve(ff, r, torch.ones(20, 31, dtype=F64))
    with pytest.raises(TypeError, match="FormFactors"):
        solve(ff.matrix, r, e0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="method must be one of"):
        solve(ff, r, e0, method="lu")
    with pytest.raises(ValueError, match="bounces must be"):
        solve(ff, r, e0, bounces=0)
    with pytest.raises(ValueError, match="tol must be"):
        solve(ff, r, e0, tol=-1.0)


def test_cg_requires_reciprocity() -> None:
    f = torch.rand(6, 6, dtype=F64) * 0.15
    f.fill_diagonal_(0)
    ff = FormFactors(f, torch.ones(6, dtype=F64))
    r, e0 = torch.full((6, 2), 0.9, dtype=F64), torch.rand(6, 2, dtype=F64)
    with pytest.raises(ValueError, match="reciprocal"):
        solve(ff, r, e0, method="cg")
    e, info = solve_with_info(ff, r, e0)
    assert info.method == "dense"
    torch.testing.assert_close(e, reference(ff, r, e0))
    torch.testing.assert_close(solve(ff, r, e0, method="neumann", tol=1e-13), e)


@pytest.mark.parametrize("method", ["cg", "neumann"])
def test_convergence_warning(method: str) -> None:
    ff = closed_ring(50)
    r = torch.full((50, 2), 0.99, dtype=F64)
    e0 = torch.rand(50, 2, dtype=F64)
    with pytest.warns(ConvergenceWarning, match="residual") as rec:
        e, info = solve_with_info(ff, r, e0, method=method, max_iter=3)
    assert rec[0].message.residual > 1e-6  # type: ignore[union-attr]
    assert not info.converged and info.iterations == 3
    assert torch.isfinite(e).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solve(ff, r, e0, method=method)


def test_info_and_radiance() -> None:
    ff = sphere(10)
    e, info = solve_with_info(ff, torch.full((10,), 0.5, dtype=F64), torch.ones(10, 3, dtype=F64))
    assert isinstance(info, SolveInfo)
    assert info.num_components == 1 and info.facets_skipped == 0 and info.num_columns == 3
    assert info.residual < 1e-10 and info.error_bound < 1e-8
    rad = radiance(e, torch.full((10,), 0.5, dtype=F64))
    torch.testing.assert_close(rad, 0.5 * e / torch.pi)
    with pytest.raises(ShapeError):
        radiance(e, torch.ones(10, 4, dtype=F64))


def test_distinct_columns_counts_as_unique_does() -> None:
    """The cost model's count of distinct reflectance columns (one projection per column) equals
    ``torch.unique(dim=1)`` on repeated, grey and spectral columns, float32 and float64."""
    from torch_interreflect.solver.method import distinct_columns

    g = torch.Generator().manual_seed(0)
    materials = torch.rand(5, 30, generator=g, dtype=F64)
    for cols in (materials[torch.randint(0, 5, (100,), generator=g)].T,  # 100 columns of 5 kinds
                 torch.rand(300, 64, generator=g, dtype=F64),  # all distinct
                 torch.full((300, 7), 0.5, dtype=F64), torch.rand(4, 1, generator=g, dtype=F64)):
        for dtype in (torch.float32, F64):
            c = cols.to(dtype)
            assert distinct_columns(c) == int(torch.unique(c, dim=1).shape[1])
