"""The dense method under several torch threads (issue 13, item 1).

On torch 2.13 CPU, batched ``torch.linalg.lu_factor_ex`` with 2 threads returns invalid pivots for batches ≥ 2 of
matrices with ≳ 200 rows. The test suite pins one thread per worker (tests/conftest.py), so these tests set 2
threads themselves (and restore the count).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from tests.oracles import random_reciprocal
from torch_interreflect import FormFactors
from torch_interreflect.solver import solve, solve_with_info

F64 = torch.float64


@pytest.fixture
def two_threads() -> Iterator[None]:
    prev = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


def _nonreciprocal(n: int, seed: int = 0) -> FormFactors:
    g = torch.Generator().manual_seed(seed)
    f = torch.rand(n, n, generator=g, dtype=F64)
    f.fill_diagonal_(0)
    return FormFactors(f / f.sum(1, keepdim=True) * 0.9, torch.ones(n, dtype=F64))


@pytest.mark.parametrize("n", [256, 300])
def test_dense_with_two_threads_matches_cg(two_threads: None, n: int) -> None:
    """Batch of 4 grey reflectances (4 distinct columns, 4 factorisations) on a reciprocal kernel."""
    assert torch.get_num_threads() == 2
    ff = random_reciprocal(n, scale=0.95, seed=n)
    g = torch.Generator().manual_seed(1)
    r = 0.5 + 0.45 * torch.rand(4, n, generator=g, dtype=F64)  # [B, F] grey, B = 4
    e0 = torch.rand(n, 3, generator=g, dtype=F64)
    e_dense, info = solve_with_info(ff, r, e0, method="dense")
    e_cg = solve(ff, r, e0, method="cg", tol=1e-13)
    assert info.distinct_columns == 4
    torch.testing.assert_close(e_dense, e_cg, rtol=1e-10, atol=0)
    # the adjoint reuses the factors: gradients against CG's
    ra, rb = r.clone().requires_grad_(), r.clone().requires_grad_()
    solve(ff, ra, e0, method="dense").square().sum().backward()
    solve(ff, rb, e0, method="cg", tol=1e-13).square().sum().backward()
    torch.testing.assert_close(ra.grad, rb.grad, rtol=1e-9, atol=0)


def test_nonreciprocal_lu_with_two_threads(two_threads: None) -> None:
    """Without reciprocity the dense method is LU (guarded); compared with the Neumann series."""
    n = 256
    ff = _nonreciprocal(n)
    r = torch.linspace(0.3, 0.9, 6, dtype=F64).expand(n, 6)  # 6 distinct columns
    e0 = torch.rand(2, n, 6, generator=torch.Generator().manual_seed(2), dtype=F64)
    e_dense = solve(ff, r, e0, method="dense")
    e_neu = solve(ff, r, e0, method="neumann", tol=1e-14)
    torch.testing.assert_close(e_dense, e_neu, rtol=1e-11, atol=0)
    assert torch.get_num_threads() == 2  # the guard restored the count


def test_auto_picks_a_correct_method_with_two_threads(two_threads: None) -> None:
    """The issue's case: 8 grey reflectances on a ~256-facet scene, method='auto'."""
    n = 256
    ff = random_reciprocal(n, scale=0.99, seed=3)
    r = torch.linspace(0.1, 0.8, 8, dtype=F64)[:, None].expand(8, n)
    e0 = torch.ones(n, 31, dtype=F64)
    torch.testing.assert_close(solve(ff, r, e0), solve(ff, r, e0, method="cg", tol=1e-13), rtol=1e-10, atol=0)


@pytest.mark.parametrize("columns", [4, 400])
def test_cg_vector_operations_on_one_thread_and_restored(two_threads: None, columns: int,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Small systems (4 columns of 300 rows, under ``SMALL_VECTOR_ELEMENTS``) run CG's vector operations on one
    thread and its products on the caller's two; larger ones (400 columns) on two throughout. Either way the answer
    is the dense one within the CG tolerance, and the caller's thread count is back afterwards, also after an
    error raised inside the iteration."""
    from torch_interreflect._threads import SMALL_VECTOR_ELEMENTS
    from torch_interreflect.errors import SingularSystemError
    from torch_interreflect.solver.krylov import cg
    from torch_interreflect.solver.plan import Stats

    n = 300
    assert (n * columns <= SMALL_VECTOR_ELEMENTS) == (columns == 4)
    ff = random_reciprocal(n, scale=0.95, seed=3)
    g = torch.Generator().manual_seed(2)
    r = 0.5 + 0.45 * torch.rand(columns, n, generator=g, dtype=F64)
    e0 = torch.rand(n, 1, generator=g, dtype=F64)
    vector: list[int] = []
    real_vecdot = torch.linalg.vecdot
    monkeypatch.setattr(torch.linalg, "vecdot", lambda *a, **k: vector.append(torch.get_num_threads())
                        or real_vecdot(*a, **k))
    e_cg = solve(ff, r, e0, method="cg", tol=1e-12)  # through operator_cg: the scaling on one thread as well
    assert torch.get_num_threads() == 2
    assert vector and set(vector) == ({1} if columns == 4 else {2})
    vector.clear()
    torch.testing.assert_close(e_cg, solve(ff, r, e0, method="dense"), rtol=1e-10, atol=0)
    seen: list[int] = []
    sym = ff.matrix * ff.areas.sqrt()[:, None] / ff.areas.sqrt()

    def product(v: torch.Tensor) -> torch.Tensor:
        seen.append(torch.get_num_threads())
        return 0.5 * (sym + sym.mT) @ v

    s = torch.full((n, columns), 0.8, dtype=F64)
    cg(product, s, torch.rand(n, columns, generator=g, dtype=F64), 1e-10, 500, Stats())
    assert seen and set(seen) == {2} and torch.get_num_threads() == 2
    assert vector and set(vector) == ({1} if columns == 4 else {2})
    with pytest.raises(SingularSystemError):  # I − S (2 I) S = −0.28 I: indefinite, p·Ap < 0 at the first step
        cg(lambda v: 2.0 * v, s, torch.ones(n, columns, dtype=F64), 1e-10, 10, Stats())
    assert torch.get_num_threads() == 2


@pytest.mark.parametrize(("n", "columns"), [(100, 1), (300, 4)])
def test_small_dense_solves_on_one_thread(two_threads: None, n: int, columns: int,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """``c² N`` at most ``SMALL_DENSE_ELEMENTS`` (100² × 1) factors on one thread, larger systems (300² × 4) on the
    caller's two; the same answers as CG, the caller's count back afterwards."""
    from torch_interreflect.solver.dense import SMALL_DENSE_ELEMENTS

    assert (n * n * columns <= SMALL_DENSE_ELEMENTS) == (n == 100)
    seen: list[int] = []
    real = torch.linalg.cholesky_ex
    monkeypatch.setattr(torch.linalg, "cholesky_ex", lambda *a, **k: seen.append(torch.get_num_threads())
                        or real(*a, **k))
    ff = random_reciprocal(n, scale=0.95, seed=4)
    g = torch.Generator().manual_seed(5)
    r = 0.5 + 0.45 * torch.rand(columns, n, generator=g, dtype=F64)
    e0 = torch.rand(n, 1, generator=g, dtype=F64)
    e_dense = solve(ff, r, e0, method="dense")
    assert seen and set(seen) == ({1} if n == 100 else {2}) and torch.get_num_threads() == 2
    torch.testing.assert_close(e_dense, solve(ff, r, e0, method="cg", tol=1e-13), rtol=1e-10, atol=0)


@pytest.mark.parametrize(("n", "columns", "vectors", "products"), [(300, 4, {1}, {2}), (300, 400, {2}, {2})])
def test_cg_inside_compiled_work_keeps_the_callers_threads(two_threads: None, n: int, columns: int,
                                                           vectors: set[int], products: set[int],
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Inside ``compiled_work`` (torch's glue on one thread, as the quadratic planner runs) CG still takes the
    caller's two threads where it did outside: the products always, the vector operations of large systems; small
    systems' vector operations stay on one. Before, a CG solve in that block ran entirely on one thread."""
    from torch_interreflect._threads import compiled_work
    from torch_interreflect.solver.krylov import cg
    from torch_interreflect.solver.plan import Stats

    g = torch.Generator().manual_seed(4)
    ff = random_reciprocal(n, scale=0.95, seed=5)
    sym = ff.matrix * ff.areas.sqrt()[:, None] / ff.areas.sqrt()
    seen: list[int] = []
    vector: list[int] = []
    real_vecdot = torch.linalg.vecdot
    monkeypatch.setattr(torch.linalg, "vecdot", lambda *a, **k: vector.append(torch.get_num_threads())
                        or real_vecdot(*a, **k))

    def product(v: torch.Tensor) -> torch.Tensor:
        seen.append(torch.get_num_threads())
        return 0.5 * (sym + sym.mT) @ v

    s = torch.full((n, columns), 0.8, dtype=F64)
    rhs = torch.rand(n, columns, generator=g, dtype=F64)
    with compiled_work():
        assert torch.get_num_threads() == 1
        w = cg(product, s, rhs, 1e-12, 500, Stats())
        assert torch.get_num_threads() == 1
    assert set(seen) == products and set(vector) == vectors and torch.get_num_threads() == 2
    a = torch.eye(n, dtype=F64) - s[:, :1] * 0.5 * (sym + sym.mT) * s[:, :1].T
    torch.testing.assert_close(a @ w[:, :1], rhs[:, :1], rtol=0, atol=1e-9)


@pytest.mark.parametrize(("n", "threads"), [(200, 1), (600, 2)])
def test_dense_inside_compiled_work_factors_large_systems_on_the_callers_threads(
        two_threads: None, n: int, threads: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The dense method's factorisation inside ``compiled_work``: a small system on one thread (as outside), a large
    one (600² entries, above ``SMALL_DENSE_ELEMENTS``) on the caller's two; the same answer as outside."""
    from torch_interreflect._threads import compiled_work

    ff = random_reciprocal(n, scale=0.9, seed=6)
    r = torch.full((n,), 0.8, dtype=F64)
    e0 = torch.rand(n, 1, generator=torch.Generator().manual_seed(7), dtype=F64)
    seen: list[int] = []
    real = torch.linalg.cholesky_ex
    monkeypatch.setattr(torch.linalg, "cholesky_ex", lambda *a, **k: seen.append(torch.get_num_threads())
                        or real(*a, **k))
    outside = solve(ff, r, e0, method="dense")
    assert seen == [threads]
    seen.clear()
    with compiled_work():
        inside = solve(ff, r, e0, method="dense")
    assert seen == [threads] and torch.get_num_threads() == 2
    torch.testing.assert_close(inside, outside, rtol=1e-12, atol=0)


def test_operator_cg_inside_compiled_work_scales_on_one_thread(two_threads: None) -> None:
    """Through ``operator_cg`` (the path of ``solve`` and ``solve_moments``) inside ``compiled_work``, a small system
    keeps the area scaling around each product and the vector operations on one thread: every element-wise product
    or quotient of the areas' descendants runs on one thread, only the matrix product on the caller's two."""
    from torch_interreflect._threads import compiled_work
    from torch_interreflect.solver.krylov import operator_cg
    from torch_interreflect.solver.plan import Stats

    seen: list[int] = []

    class Spy(torch.Tensor):  # records the thread count of the element-wise products and quotients it meets
        @classmethod
        def __torch_function__(cls, func, types, args=(), kwargs=None):
            if getattr(func, "__name__", "") in ("__mul__", "__rmul__", "__truediv__", "__rtruediv__", "mul", "div"):
                seen.append(torch.get_num_threads())
            return super().__torch_function__(func, types, args, kwargs or {})

    n = 300
    ff = random_reciprocal(n, scale=0.95, seed=8)
    products: list[int] = []

    def apply_f(v: torch.Tensor) -> torch.Tensor:
        products.append(torch.get_num_threads())
        return ff.matrix @ v.as_subclass(torch.Tensor)

    b = torch.rand(n, 2, generator=torch.Generator().manual_seed(9), dtype=F64)
    r = torch.full((n, 2), 0.8, dtype=F64)
    with compiled_work():
        x = operator_cg(apply_f, ff.areas.as_subclass(Spy), r, b, False, 1e-12, 500, Stats())
    assert seen and set(seen) == {1} and set(products) == {2} and torch.get_num_threads() == 2
    ref = solve(ff, r.T, b.T[..., None], method="dense")[..., 0].T
    torch.testing.assert_close(x.as_subclass(torch.Tensor), ref, rtol=1e-9, atol=0)
