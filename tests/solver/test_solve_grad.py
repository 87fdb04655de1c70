"""Gradients of :func:`torch_interreflect.solve.solve`: adjoint method against autograd and finite differences."""

from __future__ import annotations

import warnings

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from tests.oracles import per_column_solve, random_reciprocal
from torch_interreflect import FormFactors
from torch_interreflect.solver import solve

F64 = torch.float64
METHODS = ["dense", "cg", "neumann"]
TOL = 1e-13  # iterative methods: tight enough for finite differences


def direct(f: torch.Tensor, r: torch.Tensor, e0: torch.Tensor) -> torch.Tensor:
    """Autograd reference through torch.linalg.solve on (I - F R) per column ([..., F, L])."""
    return per_column_solve(f, r, e0)


def inputs(n: int = 5, b: int = 2, lw: int = 3, seed: int = 0, rmax: float = 0.9):
    g = torch.Generator().manual_seed(seed)
    r = (0.05 + (rmax - 0.05) * torch.rand(b, n, lw, generator=g, dtype=F64)).requires_grad_()
    e0 = torch.rand(b, n, lw, generator=g, dtype=F64).requires_grad_()
    return r, e0


@pytest.mark.parametrize("method", METHODS)
def test_gradcheck_reflectance_e0(method: str) -> None:
    ff = random_reciprocal(5)
    r, e0 = inputs()
    assert gradcheck(lambda r, e: solve(ff, r, e, method=method, tol=TOL), (r, e0))


@pytest.mark.parametrize("method", METHODS)
def test_gradcheck_matrix(method: str) -> None:
    ff = random_reciprocal(4, scale=0.8)
    r, e0 = inputs(n=4, b=1, lw=2)
    s = ff.areas[:, None] * ff.matrix  # symmetric: keep reciprocity when perturbing (needed by cg)
    iu = torch.triu_indices(4, 4, 1)
    vals = s[iu[0], iu[1]].clone().requires_grad_()

    def run(v: torch.Tensor, r: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
        w = torch.zeros(4, 4, dtype=F64).index_put((iu[0], iu[1]), v)
        f = (w + w.T) / ff.areas[:, None]
        return solve(FormFactors(f, ff.areas), r, e, method=method, tol=TOL)

    assert gradcheck(run, (vals, r, e0))


def _offdiag(n: int, v: torch.Tensor) -> torch.Tensor:
    """An [n, n] matrix with zero diagonal from its n(n-1) off-diagonal values (gradcheck never perturbs F_ii)."""
    mask = ~torch.eye(n, dtype=torch.bool)
    return torch.zeros(n, n, dtype=v.dtype).masked_scatter(mask, v)


def test_gradcheck_matrix_nonreciprocal() -> None:
    g = torch.Generator().manual_seed(2)
    v = (0.05 + torch.rand(12, generator=g, dtype=F64) * 0.25).requires_grad_()
    areas = torch.ones(4, dtype=F64)
    r, e0 = inputs(n=4, b=1, lw=2)
    for method in ("dense", "neumann"):
        assert gradcheck(
            lambda v, r, e, m=method: solve(FormFactors(_offdiag(4, v), areas), r, e, method=m, tol=TOL),
            (v, r, e0),
        )


@pytest.mark.parametrize("method", ["dense", "cg"])
def test_gradgradcheck(method: str) -> None:
    ff = random_reciprocal(4)
    r, e0 = inputs(n=4, b=1, lw=2)
    assert gradgradcheck(lambda r, e: solve(ff, r, e, method=method, tol=TOL), (r, e0))


def test_gradgradcheck_matrix_dense() -> None:
    g = torch.Generator().manual_seed(5)
    v = (0.05 + torch.rand(6, generator=g, dtype=F64) * 0.3).requires_grad_()
    r, e0 = inputs(n=3, b=1, lw=2)
    areas = torch.ones(3, dtype=F64)
    assert gradgradcheck(lambda v, r, e: solve(FormFactors(_offdiag(3, v), areas), r, e, method="dense"), (v, r, e0))


@pytest.mark.parametrize("method", METHODS)
def test_adjoint_equals_autograd_through_linalg_solve(method: str) -> None:
    ff = random_reciprocal(12, seed=3)
    f = ff.matrix.clone().requires_grad_()
    r, e0 = inputs(n=12, b=3, lw=4, seed=4)
    w = torch.randn(3, 12, 4, dtype=F64)
    (solve(FormFactors(f, ff.areas), r, e0, method=method, tol=TOL) * w).sum().backward()
    got = (f.grad, r.grad, e0.grad)
    f2, r2, e2 = (t.detach().clone().requires_grad_() for t in (ff.matrix, r, e0))
    (direct(f2, r2, e2) * w).sum().backward()
    for a, b in zip(got, (f2.grad, r2.grad, e2.grad), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def test_broadcast_gradients_reduce_to_input_shapes() -> None:
    ff = random_reciprocal(6, seed=1)
    r = (torch.rand(6, dtype=F64) * 0.9).requires_grad_()  # grey, no batch
    e0 = torch.rand(2, 6, 5, dtype=F64).requires_grad_()
    solve(ff, r, e0).sum().backward()
    assert r.grad is not None and r.grad.shape == (6,)
    r2 = r.detach().clone().requires_grad_()
    direct(ff.matrix, r2[:, None], e0.detach()).sum().backward()
    torch.testing.assert_close(r.grad, r2.grad)
    assert gradcheck(lambda r, e: solve(ff, r, e, method="cg", tol=TOL), (r, e0))


def test_zero_reflectance_gradients() -> None:
    ff = random_reciprocal(8, seed=2)
    r = torch.rand(8, 3, dtype=F64) * 0.9
    r[:3] = 0
    for method in METHODS:
        ra = r.clone().requires_grad_()
        f = ff.matrix.clone().requires_grad_()
        solve(FormFactors(f, ff.areas), ra, torch.ones(8, 3, dtype=F64), method=method, tol=TOL).sum().backward()
        rb = r.clone().requires_grad_()
        fb = ff.matrix.clone().requires_grad_()
        direct(fb, rb, torch.ones(8, 3, dtype=F64)).sum().backward()
        torch.testing.assert_close(ra.grad, rb.grad)
        torch.testing.assert_close(f.grad, fb.grad)


@pytest.mark.parametrize("bounces", [1, 2, 3, 6])
def test_n_bounce_gradients_equal_explicit_series(bounces: int) -> None:
    ff = random_reciprocal(7, seed=6)
    f = ff.matrix.clone().requires_grad_()
    r, e0 = inputs(n=7, seed=7)
    w = torch.randn(2, 7, 3, dtype=F64)
    (solve(FormFactors(f, ff.areas), r, e0, bounces=bounces) * w).sum().backward()
    got = (f.grad, r.grad, e0.grad)
    f2, r2, e2 = (t.detach().clone().requires_grad_() for t in (ff.matrix, r, e0))
    total, term = e2, e2
    for _ in range(bounces - 1):
        term = f2 @ (r2 * term)
        total = total + term
    (total * w).sum().backward()
    for a, b in zip(got, (f2.grad, r2.grad, e2.grad), strict=True):
        if b is None:
            assert a is None or torch.count_nonzero(a) == 0
        else:
            torch.testing.assert_close(a, b)
    assert gradcheck(lambda r, e: solve(ff, r, e, bounces=bounces), (r, e0))


@pytest.mark.parametrize("method", METHODS)
def test_sparse_gradient_on_stored_entries(method: str) -> None:
    ff = random_reciprocal(10, seed=8)
    mask = torch.rand(10, 10, generator=torch.Generator().manual_seed(9)) < 0.5
    mask = (mask | mask.T) & ~torch.eye(10, dtype=torch.bool)
    dense = ff.matrix * mask
    r, e0 = inputs(n=10, seed=10)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        csr = dense.to_sparse_csr().requires_grad_()
    solve(FormFactors(csr, ff.areas), r, e0, method=method, tol=TOL).sum().backward()
    assert csr.grad is not None and csr.grad.layout == torch.sparse_csr
    fd = dense.clone().requires_grad_()
    r2, e2 = (t.detach().clone().requires_grad_() for t in (r, e0))
    direct(fd, r2, e2).sum().backward()
    torch.testing.assert_close(csr.grad.to_dense(), fd.grad * mask)
    torch.testing.assert_close(r.grad, r2.grad)
    torch.testing.assert_close(e0.grad, e2.grad)


@pytest.mark.parametrize("method", METHODS)
def test_gradients_near_r1_finite(method: str) -> None:
    """Closed enclosure at r = 0.995: gradients finite and equal to central finite differences."""
    n = 6
    g = torch.Generator().manual_seed(11)
    areas = torch.rand(n, generator=g, dtype=F64) + 0.5
    ff = FormFactors(areas.expand(n, n) / areas.sum(), areas)
    r = torch.full((n, 2), 0.995, dtype=F64, requires_grad=True)
    e0 = torch.rand(n, 2, generator=g, dtype=F64)
    w = torch.rand(n, 2, generator=g, dtype=F64)
    (solve(ff, r, e0, method=method, tol=TOL) * w).sum().backward()
    assert r.grad is not None and torch.isfinite(r.grad).all()
    h = 1e-6
    for i, j in [(0, 0), (3, 1), (5, 0)]:
        rp, rm = r.detach().clone(), r.detach().clone()
        rp[i, j] += h
        rm[i, j] -= h
        fd = ((direct(ff.matrix, rp, e0) - direct(ff.matrix, rm, e0)) * w).sum() / (2 * h)
        torch.testing.assert_close(r.grad[i, j], fd, rtol=1e-5, atol=0)
