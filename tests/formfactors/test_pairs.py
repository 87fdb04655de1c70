"""Culling, classification and blocker tests of facet pairs: the compiled loops against the torch reference, and
the compiled contour formula's angle (Cephes' atan) against libm."""

import math

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from tests.formfactors.test_fused import random_scene
from torch_interreflect.formfactors import compiled, pairs, quadrature, visibility
from torch_interreflect.geometry._polygon import plane_eps

pytestmark = pytest.mark.skipif(compiled.loops("pairs") is None, reason="needs numba")

SCENES = {
    "v_groove": lambda: ti.scenes.v_groove(30.0, divisions=6),
    "cornell": lambda: ti.scenes.cornell_box(5),
    "room": lambda: ti.scenes.room(divisions=1),
    "closed_box": lambda: ti.scenes.closed_box(divisions=3),
    "random": lambda: random_scene(3, n=40),
}


def _torch_reference(monkeypatch, fn):
    """``fn()`` with numba disabled (the torch path)."""
    with monkeypatch.context() as m:
        m.setenv("TI_DISABLE_NUMBA", "1")
        compiled.loops.cache_clear()
        try:
            return fn()
        finally:
            compiled.loops.cache_clear()


@pytest.mark.parametrize("name", sorted(SCENES))
def test_compiled_pair_stages_equal_the_torch_reference(monkeypatch, name):
    sc = SCENES[name]().to(torch.float64)
    eps = plane_eps(sc)

    def stages():
        iu, ju = pairs.facing_pairs(sc, eps, ("dense", 8))
        dom, tgt = pairs.order_pairs(sc.areas, iu, ju)
        cls = pairs.classify_pairs(sc, dom, tgt, 1e-6, None, eps)
        groups, clipped = pairs.rule_groups(cls)
        need = visibility.blocker_candidates(sc, dom, tgt, eps)
        value = torch.rand(dom.numel(), generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.2
        return iu, ju, cls, groups, clipped, need, quadrature.pair_entries(sc.areas, dom, tgt, value)

    got, ref = stages(), _torch_reference(monkeypatch, stages)
    for a, b in zip(got[:2], ref[:2], strict=True):
        assert torch.equal(a, b)
    assert torch.equal(torch.stack(pairs.order_pairs(sc.areas, got[0], got[1])),
                       torch.stack(_torch_reference(monkeypatch, lambda: pairs.order_pairs(sc.areas, ref[0], ref[1]))))
    for field in ("order", "has_edge", "has_vertex", "shift", "clip_t", "clip_d"):
        assert torch.equal(getattr(got[2], field), getattr(ref[2], field)), field
    torch.testing.assert_close(got[2].rho, ref[2].rho, rtol=4e-16, atol=0)
    assert [(k, n) for k, _, n in got[3]] == [(k, n) for k, _, n in ref[3]]
    assert all(torch.equal(a, b) for (_, a, _), (_, b, _) in zip(got[3], ref[3], strict=True))
    assert torch.equal(got[4], ref[4]) and torch.equal(got[5], ref[5])
    for a, b in zip(got[6], ref[6], strict=True):
        assert torch.equal(a, b)


def test_scenes_exercise_every_class():
    """The scenes above hold shared edges, shared vertices, clipped pairs and blockable pairs (else the equality
    test proves little)."""
    sc = random_scene(3, n=40).to(torch.float64)
    eps = plane_eps(sc)
    iu, ju = pairs.facing_pairs(sc, eps, ("dense", 8))
    cls = pairs.classify_pairs(sc, iu, ju, 1e-6, None, eps)
    assert int(cls.clip_t.sum()) > 10 and int(cls.clip_d.sum()) > 10
    corn = ti.scenes.cornell_box(5).to(torch.float64)
    e2 = plane_eps(corn)
    iu, ju = pairs.facing_pairs(corn, e2, ("dense", 8))
    c2 = pairs.classify_pairs(corn, iu, ju, 1e-6, None, e2)
    assert int(c2.has_edge.sum()) > 10 and int(c2.has_vertex.sum()) > 10
    assert 0 < int(visibility.blocker_candidates(corn, iu, ju, e2).sum()) < iu.numel()


def test_facing_pairs_on_odd_and_tiny_scenes():
    """Rows are taken in pairs (r, F − 1 − r): odd counts and one or two facets must not double or drop rows."""
    for n in (1, 2, 3):
        sc = ti.scenes.v_groove(60.0, divisions=n).to(torch.float64)
        for k in (1, 2, 3, sc.num_facets - 1):
            sub = ti.Scene.from_polygons(sc.corners[:k])
            iu, ju = pairs.facing_pairs(sub, plane_eps(sub), ("dense", 8))
            front = ti.geometry._polygon.facing_matrix(sub.corners, sub.normals, sub.centroids, plane_eps(sub))
            ref = torch.nonzero(torch.triu(front & front.T, diagonal=1), as_tuple=True)
            assert torch.equal(iu, ref[0]) and torch.equal(ju, ref[1])


def test_compiled_angle_is_within_two_ulp_of_libm():
    """The contour formula's edge angle ``atan2(|r × s|, r · s)`` (Cephes' atan) against math.atan2, over angles
    from 1e-10 rad to π − 1e-10 (measured: 2 ulp)."""
    kern = compiled.loops("quadrature")
    rng = np.random.default_rng(1)
    theta = np.concatenate([10.0 ** rng.uniform(-10, 0, 20000), rng.uniform(0, math.pi, 20000),
                            math.pi - 10.0 ** rng.uniform(-10, 0, 20000), [0.5 * math.pi, 0.0]])
    scale = 10.0 ** rng.uniform(-6, 6, theta.size)
    s, c = scale * np.sin(theta), scale * np.cos(theta)
    s[-1], c[-1] = 0.0, 3.0
    got = np.array([kern._angle(a, b) for a, b in zip(s, c, strict=True)])
    ref = np.arctan2(s, c)
    ulp = np.abs(got - ref) / np.spacing(np.maximum(np.abs(ref), 1e-300))
    assert ulp.max() <= 2.0, ulp.max()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dense_matrix_written_from_pairs_equals_the_entry_lists(dtype):
    """The dense output written straight from the pairs (no entry lists) holds the sparse output's entries bit for
    bit, the same nonzero count, and row sums that agree to rounding."""
    scene = ti.scenes.cornell_box(5).to(dtype)
    dense = ti.form_factors(scene, layout="dense")
    sparse = ti.form_factors(scene, layout="sparse")
    assert dense.info["layout"] == "dense" and sparse.info["layout"] == "sparse"
    assert dense.matrix.dtype == dtype and torch.equal(dense.matrix, sparse.to_dense())
    assert dense.info["nnz"] == sparse.info["nnz"] == int((dense.matrix != 0).sum())
    assert abs(dense.info["max_row_sum"] - sparse.info["max_row_sum"]) <= 1e-14


def test_order_pairs_ties_within_the_tie(monkeypatch):
    """Areas within ``tie`` (relative) are a tie and keep ``iu`` first, in the compiled loop and in the torch path
    alike; outside it the smaller facet is the domain. A float32 area against a float64 tie is compared in float64
    (1 + 1e-12 would round to 1 in float32)."""
    areas = torch.tensor([1.0, 1.0 + 5e-13, 1.0 - 5e-13, 1.0 + 5e-12], dtype=torch.float64)
    iu = torch.tensor([1, 0, 3, 1])
    ju = torch.tensor([0, 2, 0, 3])

    def run():
        return torch.stack(pairs.order_pairs(areas, iu, ju, 1e-12))

    got, ref = run(), _torch_reference(monkeypatch, run)
    assert torch.equal(got, ref)
    assert got[0].tolist() == [1, 0, 0, 1]  # ties keep iu; (3, 0): 5e-12 apart, facet 0 is smaller
    assert torch.stack(pairs.order_pairs(areas, iu, ju))[0].tolist() == [0, 2, 0, 1]  # tie 0: the smaller first
    # float32 areas one ulp (1.19e-7) apart with a tie of 1e-7: not a tie in float64 (in float32 1 + 1e-7 rounds to
    # that ulp, and the two would tie)
    small = torch.tensor([1.0, 1.0 + 1.2e-7], dtype=torch.float32)
    one = torch.tensor([1]), torch.tensor([0])
    assert pairs.order_pairs(small, *one, 1e-7)[0].tolist() == [0]
    assert _torch_reference(monkeypatch, lambda: pairs.order_pairs(small, *one, 1e-7))[0].tolist() == [0]
    assert _torch_reference(monkeypatch, lambda: pairs.order_pairs(small, *one, 1e-6))[0].tolist() == [1]


def _contact_scenes() -> dict[str, ti.Scene]:
    """Scenes whose pairs touch where their corners do not show it: the Cornell box split at its contacts and cut to
    0.4 m (T-junctions between pieces cut at other places), and a thin floor strip with walls along parts of its
    edge (from a shared corner: a wall's edge wholly on the strip's longer one, so the pair is turned around; inside
    the edge; past its end)."""
    from torch_interreflect.geometry import split_at_contacts, subdivide_to

    box = subdivide_to(split_at_contacts(ti.scenes.cornell_box(light=False, dtype=torch.float64))[0], 0.4)[0]
    quads = [[[0, 0, 0], [1, 0, 0], [1, 0.2, 0], [0, 0.2, 0]]]
    quads += [[[a, 0, 0], [a, 0, 0.6], [b, 0, 0.6], [b, 0, 0]] for a, b in ((0.0, 0.5), (0.6, 0.8), (0.9, 1.5))]
    floor = ti.Scene.from_polygons(torch.tensor(quads, dtype=torch.float64))
    return {"cornell_cut": box, "floor_and_walls": floor}


@pytest.mark.parametrize("name", ["cornell_cut", "floor_and_walls"])
def test_compiled_contacts_equal_the_torch_reference(monkeypatch, name):
    """:func:`pair_contacts.contacts` and :func:`pairs.corner_edge_contacts` (the moments' contacts that the shared
    corners do not show) in their compiled loops against the torch reference, on the same pairs: every output
    equal, and the scenes have contacts of every kind (or the comparison proves little)."""
    from torch_interreflect.formfactors.pair_contacts import contacts

    sc = _contact_scenes()[name]
    eps = plane_eps(sc)
    iu, ju = pairs.facing_pairs(sc, eps, ("dense", 8))
    dom, tgt = pairs.order_pairs(sc.areas, iu, ju)
    cls = pairs.classify_pairs(sc, dom, tgt, 1e-3, None, eps)
    radius = (sc.corners - sc.centroids[:, None, :]).norm(dim=-1).amax(1)

    def run():
        d, t, c = pairs.corner_edge_contacts(sc, dom, tgt, cls)
        near = (sc.centroids[d] - sc.centroids[t]).norm(dim=-1) <= (radius[d] + radius[t]) * (1 + 1e-6)
        return (d, t, c.shift, c.clip_t, c.clip_d,
                *contacts(sc, d, t, c.has_edge, c.has_vertex, torch.where(c.has_edge | c.has_vertex, c.shift, 0), near))

    inputs = [t.clone() for t in (dom, tgt, cls.has_edge, cls.has_vertex, cls.shift, cls.clip_t, cls.clip_d)]
    got = run()
    for a, b in zip(inputs, (dom, tgt, cls.has_edge, cls.has_vertex, cls.shift, cls.clip_t, cls.clip_d), strict=True):
        assert torch.equal(a, b)  # the compiled loops wrote to copies
    ref = _torch_reference(monkeypatch, run)
    for k, (a, b) in enumerate(zip(got, ref, strict=True)):
        assert torch.equal(a, b), k
    edge, vertex, swapped = got[7], got[8], got[10]
    turned = int((got[0] != dom).sum())
    new_edge, new_vertex = int((edge & ~cls.has_edge).sum()), int((vertex & ~cls.has_vertex).sum())
    cut = int(((got[11][:, 0] > 0) | (got[11][:, 1] < 1)).sum())
    if name == "cornell_cut":  # measured: 12 new edge contacts, 4 new corner contacts (1 turned around), 6 cut
        assert new_edge > 0 and new_vertex > 0 and int((swapped & vertex & ~edge).sum()) > 0 and cut > 0
    else:  # measured: 1 pair turned at its shared corner, 2 new edge contacts (1 turned around), 1 cut
        assert turned > 0 and new_edge > 0 and int((swapped & edge).sum()) > 0 and cut > 0
