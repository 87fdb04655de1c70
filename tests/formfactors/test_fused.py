"""The fused (compiled, multi-core) quadrature against Howell's values and against the torch quadrature."""

import math

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from tests.oracles import HOWELL_C16, reference_tolerance
from torch_interreflect.formfactors import fused, fused_points
from torch_interreflect.formfactors.rules import quadrature_rule

F64 = torch.float64


def hinge_scene(phi, n=1):
    """Two unit squares sharing the y axis at interior angle ``phi`` (radians, float or 0-d tensor)."""
    phi = torch.as_tensor(phi, dtype=F64)
    a = torch.tensor(ti.scenes.grid_quads([0, 0, 0], [1, 0, 0], [0, 1, 0], n, n), dtype=F64)
    d = torch.stack([torch.cos(phi), torch.zeros_like(phi), torch.sin(phi)])
    s, t = torch.meshgrid(torch.arange(n + 1, dtype=F64) / n, torch.arange(n + 1, dtype=F64) / n, indexing="ij")
    grid = s[..., None] * torch.tensor([0.0, 1.0, 0.0], dtype=F64) + t[..., None] * d  # [n+1, n+1, 3]
    b = torch.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]], dim=2).reshape(-1, 4, 3)
    return ti.Scene.from_polygons(torch.cat([a, b]))


def random_scene(seed, n=24):
    """Random squares and triangles in a unit cube: straddling (clipped), facing and grazing pairs."""
    rng = np.random.default_rng(seed)
    quads, tris = [], []
    for k in range(n):
        c = rng.random(3)
        nrm = rng.normal(size=3)
        nrm /= np.linalg.norm(nrm)
        t1 = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(nrm, t1)
        h = 0.1 + 0.2 * rng.random()
        quad = [c - h * t1 - h * t2, c + h * t1 - h * t2, c + h * t1 + h * t2, c - h * t1 + h * t2]
        (tris if k % 3 == 0 else quads).append(quad[:3] if k % 3 == 0 else quad)
    parts = [ti.Scene.from_polygons(torch.tensor(np.array(p), dtype=F64)) for p in (quads, tris)]
    return ti.Scene.concatenate(parts)


def assert_same(a, b, rel=1e-12, atol=1e-15):
    """Per entry: within ``rel`` of the entry, or ``atol`` (the float64 rounding of grazing entries ~1e-8)."""
    A, B = a.to_dense().double(), b.to_dense().double()
    assert torch.equal(A > 0, B > 0)
    err = (A - B).abs()
    assert bool((err <= rel * A.abs() + atol).all()), float((err / A.abs().clamp_min(1e-300)).max())


@pytest.mark.parametrize(("angle", "ref"), HOWELL_C16)
@pytest.mark.parametrize("n", [1, 3])
def test_howell_c16_fused(angle, ref, n):
    scene = hinge_scene(math.radians(angle), n)
    K = ti.form_factors(scene, backend="fused")
    A = scene.areas
    F = float((A[: n * n, None] * K.to_dense()[: n * n, n * n :]).sum() / A[: n * n].sum())
    assert abs(F - ref) <= reference_tolerance(ref, 2e-6)
    assert K.info["pairs_adjacent"] > 0


@pytest.mark.parametrize(
    "build",
    [
        lambda: ti.scenes.cornell_box(2, dtype=F64),
        lambda: ti.scenes.v_groove(30.0, divisions=6, dtype=F64),
        lambda: ti.scenes.closed_box(divisions=3, dtype=F64),
        lambda: random_scene(0),
        lambda: random_scene(1),
    ],
    ids=["cornell", "v_groove", "closed_box", "random0", "random1"],
)
@pytest.mark.parametrize("occlusion", [False, "auto"])
def test_fused_matches_torch(build, occlusion):
    scene = build()
    a = ti.form_factors(scene, backend="torch", occlusion=occlusion, layout="dense")
    b = ti.form_factors(scene, backend="fused", occlusion=occlusion, layout="dense")
    assert_same(a, b)
    assert a.info["points"] == b.info["points"] and a.info["rays"] == b.info["rays"]


def test_random_scenes_have_clipped_and_adjacent_pairs():
    info = ti.form_factors(random_scene(0), backend="fused").info
    assert info["pairs_clipped"] > 0
    info = ti.form_factors(ti.scenes.cornell_box(2, dtype=F64), backend="fused", occlusion=False).info
    assert info["pairs_clipped"] > 0 and info["pairs_adjacent"] > 0 and info["occluded_pairs"] == 0


def test_float32_scene(dtype):
    scene = ti.scenes.cornell_box(2, dtype=dtype)
    a = ti.form_factors(scene, backend="torch")
    b = ti.form_factors(scene, backend="fused")
    assert b.dtype == dtype
    # both compute in float64 and round the result: equal up to one rounding of the scene's dtype
    assert_same(a, b, rel=max(1e-12, float(torch.finfo(dtype).eps)))


def test_gradient_keeps_torch_path_and_matches_finite_differences():
    def mean_f(phi, backend):
        K = ti.form_factors(hinge_scene(phi, 2), backend=backend)
        return K.to_dense().mean()

    phi = torch.tensor(math.radians(50.0), dtype=F64, requires_grad=True)
    for backend in ("auto", "fused"):  # both fall back to torch where the vertices require grad
        (g,) = torch.autograd.grad(mean_f(phi, backend), phi)
        h = 1e-5
        with torch.no_grad():
            fd = (mean_f(phi + h, "fused") - mean_f(phi - h, "fused")) / (2 * h)
        assert abs(float(g) - float(fd)) <= 1e-8 * abs(float(fd))


def test_group_sums_on_device(device):
    """The same entry point runs on any device (torch there) and agrees with the CPU compiled loop."""
    scene = ti.scenes.v_groove(40.0, divisions=3, dtype=F64)
    F = scene.num_facets
    iu, ju = torch.triu_indices(F, F, 1)
    keep = (scene.centroids[ju] - scene.centroids[iu]).mul(scene.normals[iu]).sum(-1) > 0
    iu, ju = iu[keep], ju[keep]
    rule = quadrature_rule("plain", 5, F64, torch.device("cpu"))
    shift = torch.zeros_like(iu)
    clip = torch.ones_like(iu, dtype=torch.bool)
    args = (scene.corners, scene.normals, scene.centroids)
    cpu = fused.group_sums(*args, iu, ju, shift, clip, rule, 1e-12, backend="fused")
    on = fused.group_sums(*(t.to(device) for t in args), iu.to(device), ju.to(device), shift.to(device),
                          clip.to(device), tuple(t.to(device) for t in rule), 1e-12, backend="fused")
    torch.testing.assert_close(on.cpu(), cpu, rtol=1e-12, atol=1e-15)
    ref = fused.group_sums(*args, iu, ju, shift, clip, rule, 1e-12, backend="torch")
    torch.testing.assert_close(ref, cpu, rtol=1e-12, atol=1e-15)


def _pair_set(seed=4):
    """The facing pairs of a random scene, ``(dom, tgt, shift, clip)`` (clipped targets as the quadrature
    classifies them; domains rotated at random)."""
    from torch_interreflect.formfactors import pairs
    from torch_interreflect.geometry._polygon import plane_eps

    scene = random_scene(seed, n=40).to(F64)
    eps = plane_eps(scene)
    dom, tgt = pairs.order_pairs(scene.areas, *pairs.facing_pairs(scene, eps, ("dense", 8)))
    cls = pairs.classify_pairs(scene, dom, tgt, 1e-6, None, eps)
    assert int(cls.clip_t.sum()) > 5
    shift = torch.randint(0, 4, dom.shape, generator=torch.Generator().manual_seed(seed))  # any rotation is valid
    return scene, (dom, tgt, shift, cls.clip_t)


def test_grouped_sums_equal_one_group_at_a_time():
    """Several rules of very different sizes in one launch (runs of equal point counts) give, pair by pair, what
    group_sums gives per rule (compiled and torch), and write nothing outside the selected pairs."""
    scene, pairs = _pair_set()
    args = (scene.corners, scene.normals, scene.centroids)
    perm = torch.randperm(pairs[0].numel(), generator=torch.Generator().manual_seed(1))
    cuts = [0, 3, 4, 60, 60, 150, perm.numel() - 7]  # an empty group, a group of one, a few large ones
    kinds = [("edge", 6), ("plain", 2), ("vertex", 5), ("plain", 9), ("plain", 31), ("plain", 1)]
    parts = [(quadrature_rule(k, n, F64, torch.device("cpu")), torch.sort(perm[a:b]).values)
             for (k, n), a, b in zip(kinds, cuts[:-1], cuts[1:], strict=True)]
    ref = torch.full((perm.numel(),), float("nan"), dtype=F64)
    for rule, sel in parts:
        fused.group_sums(*args, *pairs, rule, 1e-9, backend="torch", select=sel, out=ref)
    for threads in (1, 2, 3):
        with torch.inference_mode():
            prev = torch.get_num_threads()
            torch.set_num_threads(threads)
            try:
                out = torch.full_like(ref, float("nan"))
                fused.grouped_sums(*args, pairs, parts, 1e-9, out)
            finally:
                torch.set_num_threads(prev)
        assert torch.equal(out.isnan(), ref.isnan()) and int((~out.isnan()).sum()) == cuts[-1]
        torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-15, equal_nan=True)


@pytest.mark.parametrize("blocks", [1, 2, 7, 64, 5000])
def test_rule_sums_cover_every_pair_once_for_any_block_count(blocks):
    """The compiled loop's runs of equal point counts (more or fewer runs than pairs) write each selected pair."""
    from torch_interreflect.formfactors import compiled

    kern = compiled.loops()
    if kern is None:
        pytest.skip("needs numba")
    scene, (iu, ju, shift, clip) = _pair_set(5)
    rules = [quadrature_rule("plain", n, F64, torch.device("cpu")) for n in (1, 7, 3)]
    sel = torch.arange(0, iu.numel(), 3)
    bounds = torch.tensor([0, 10, 11, sel.numel()])
    size = torch.tensor([r[0].numel() for r in rules])
    table = torch.zeros(3, 3, int(size.max()), dtype=F64)
    for g, r in enumerate(rules):
        for k in range(3):
            table[k, g, : r[k].numel()] = r[k]
    out = np.full(iu.numel(), np.nan)
    kern.rule_sums(*(t.numpy() for t in (scene.corners, scene.normals, scene.centroids, iu, ju, shift, clip, sel,
                                         bounds, table[0], table[1], table[2], size)), 1e-9, blocks, out)
    assert np.isnan(out).sum() == iu.numel() - sel.numel() and not np.isnan(out[sel.numpy()]).any()
    for g, r in enumerate(rules):
        part = sel[bounds[g] : bounds[g + 1]]
        want = fused.group_sums(scene.corners, scene.normals, scene.centroids, iu, ju, shift, clip, r, 1e-9,
                                backend="torch", select=part)
        torch.testing.assert_close(torch.from_numpy(out[part.numpy()]), want, rtol=1e-12, atol=1e-15)


def test_backend_is_checked():
    with pytest.raises(ValueError, match="backend"):
        ti.form_factors(ti.scenes.closed_box(divisions=1), backend="numba")


@pytest.mark.parametrize("threads", [1, 2])
def test_fused_kernel_leaves_torch_threads_alone(threads):
    """numba's OpenMP layer shares the runtime with torch: the fused path must not change torch's thread count
    (it turned a test worker's 1 thread into 2, where batched LU on torch 2.13 CPU gives invalid pivots)."""
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        ti.form_factors(ti.scenes.w_shape(), backend="fused")
        assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(prev)


def test_fused_kernel_is_fork_safe():
    """A process that forks after the fused kernel (a DataLoader's workers, multiprocessing) must not be killed:
    numba's GNU OpenMP layer aborted the child ("fork() called from a process already using GNU OpenMP"), and the
    ray-casting thread pool inherited without its threads hung it."""
    import subprocess
    import sys

    code = (
        "import os, torch, torch_interreflect as ti\n"
        "torch.set_num_threads(1)\n"  # torch's own GNU OpenMP pool is not fork-safe with more than one thread
        "K = ti.form_factors(ti.scenes.w_shape(), backend='fused')\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    K2 = ti.form_factors(ti.scenes.w_shape(), backend='fused')\n"
        "    os._exit(0 if torch.equal(K2.to_dense(), K.to_dense()) else 3)\n"
        "print(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "0", out.stdout + out.stderr[-2000:]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_point_sums_match_the_torch_contour_formula(dtype):
    """The compiled point loop equals point_polygon_factor (float64 rounding; float32 inputs computed in float64)
    and the plane test, with many pairs sharing points and polygons."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(300, 3, generator=g, dtype=torch.float64) * 0.1
    n = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    poly = torch.randn(40, 5, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    poly[:, 4] = poly[:, 0]  # padding by a repeated corner
    rows = torch.randint(0, 300, (5000,), generator=g)
    which = torch.randint(0, 40, (5000,), generator=g)
    plane = (poly[:, 0], torch.nn.functional.normalize(torch.randn(40, 3, generator=g, dtype=torch.float64), dim=-1))
    args = (x.to(dtype), n.to(dtype), rows, poly.to(dtype), which, tuple(t.to(dtype) for t in plane))
    f, ahead = fused_points.point_sums(*args, backend="fused")
    ref, ref_ahead = fused_points.point_sums(*args, backend="torch", chunk=777)
    assert f.dtype == dtype and f.shape == (5000,)
    tol = 1e-15 if dtype == torch.float64 else 2e-7
    assert float((f - ref).abs().max()) <= tol * float(ref.abs().max())
    assert torch.equal(ahead, ref_ahead) and 0 < int(ahead.sum()) < 5000


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_point_polygon_factors_and_their_adjoint_match_autograd(dtype):
    """One point per polygon: the compiled loop and its compiled adjoint equal the torch contour formula and
    autograd through it (measured 6e-17 and 3.6e-16 relative in float64), padded polygons (triangles) included;
    the gradient matches central differences on quads (gradcheck)."""
    g = torch.Generator().manual_seed(0)
    P = 200
    x = torch.rand(P, 3, dtype=torch.float64, generator=g) * 0.5
    x[:, 2] = 0
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(P, 3).clone()
    quad = torch.tensor([[-0.5, -0.5, 1.0], [-0.5, 0.5, 1.0], [0.5, 0.5, 1.0], [0.5, -0.5, 1.0]], dtype=torch.float64)
    poly = quad + 0.1 * torch.rand(P, 4, 3, dtype=torch.float64, generator=g)
    poly[::5, 3] = poly[::5, 2]  # triangles: a repeated corner
    inputs = [t.to(dtype).requires_grad_(True) for t in (x, n, poly)]
    w = torch.rand(P, dtype=torch.float64, generator=g).to(dtype)
    a = fused_points.point_polygon_factors(*inputs)
    b = fused_points.point_polygon_factors(*inputs, backend="torch")
    assert a.dtype == dtype and a.shape == (P,)
    tol = 1e-15 if dtype == torch.float64 else 2e-7
    assert float((a - b).abs().max()) <= tol * float(b.abs().max())
    ga = torch.autograd.grad((a * w).sum(), inputs)
    gb = torch.autograd.grad((b * w).sum(), inputs)
    for u, v in zip(ga, gb, strict=True):
        assert u.dtype == dtype
        assert float((u - v).abs().max()) <= (2e-15 if dtype == torch.float64 else 1e-5) * float(v.abs().max())
    if dtype == torch.float64:
        quads = [t[1:5].detach().clone().requires_grad_(True) for t in (x, n, poly)]  # quads only
        assert torch.autograd.gradcheck(lambda *t: fused_points.point_polygon_factors(*t), quads)


def test_compiled_loops_keep_the_callers_threads_while_torch_glue_runs_on_one():
    """Inside ``compiled_work`` torch runs on one thread (its OpenMP workers spun on the core the next compiled loop
    wanted: 2 threads took 0.66-0.76 of 1 thread's time on the 1,024-facet box, 0.58 without), while compiled loops and
    ray casts get the caller's count; torch's count comes back on exit, nested blocks included."""
    import numba

    from torch_interreflect._threads import compiled_work, work_threads
    from torch_interreflect.formfactors.compiled import launch

    @numba.njit(parallel=True)
    def threads_in_loop(out):  # pragma: no cover - compiled
        for i in numba.prange(out.shape[0]):
            out[i] = numba.get_num_threads()

    out = np.zeros(4, dtype=np.int64)
    prev = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with compiled_work() as n:
            assert (n, torch.get_num_threads(), work_threads()) == (2, 1, 2)
            with compiled_work() as inner:
                assert (inner, torch.get_num_threads(), work_threads()) == (2, 1, 2)
            assert torch.get_num_threads() == 1
            launch(threads_in_loop, out)
            assert out.tolist() == [2] * 4 and torch.get_num_threads() == 1
        assert (torch.get_num_threads(), work_threads()) == (2, 2)
        torch.set_num_threads(1)
        assert work_threads() == 1
        launch(threads_in_loop, out)
        assert out.tolist() == [1] * 4
        # the same bits whatever the threads (the glue's reductions run on one thread in both)
        scene = ti.scenes.cornell_box(3, light=False)
        one = ti.form_factors(scene, backend="fused").to_dense()
        torch.set_num_threads(2)
        two = ti.form_factors(scene, backend="fused").to_dense()
        assert torch.equal(one, two) and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(prev)


def test_the_torch_path_keeps_torchs_threads(monkeypatch):
    """Only the compiled path runs torch's glue on one thread: ``backend="torch"`` and inputs that require grad keep
    torch's own count (the torch path ran on one core when it did not)."""
    from torch_interreflect import _threads

    seen = []
    real = _threads.compiled_work

    def spy():
        seen.append(True)
        return real()

    monkeypatch.setattr("torch_interreflect.formfactors.quadrature.compiled_work", spy)
    scene = ti.scenes.w_shape()
    ti.form_factors(scene, backend="torch")
    corners = scene.corners.clone().double().requires_grad_(True)
    ti.form_factors(ti.Scene.from_polygons(corners), backend="fused")
    assert seen == []
    ti.form_factors(scene, backend="fused")
    assert seen == [True]
