"""Moments reused across a refinement (``moment_form_factors(..., reuse=(previous, kept))``): the pairs of two
unchanged facets take their sums from the previous moments, and nothing else changes."""

import math

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.accuracy import moments_plan
from torch_interreflect.accuracy.leaves import Leaves, split
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors import moments as moments_module
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.formfactors.moment_reuse import reused_sums

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")
D = torch.float64


def _blocks(K, n):
    nb = K.size
    return K.matrix.reshape(n, nb, n, nb).permute(0, 2, 1, 3)  # [i, j, a, b]


def _occluded_scene():
    """A floor and a ceiling with a blocker between them (occluded pairs), and a wall that nothing blocks."""
    sq = [[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]]
    ceiling = [[x, y, 1.0] for x, y, _ in sq[::-1]]
    blocker = [[-0.8, -0.8, 0.5], [0.1, -0.8, 0.5], [0.1, 0.3, 0.5], [-0.8, 0.3, 0.5]]
    side = [[0.7, -0.5, 0.0], [0.7, 0.5, 0.0], [0.7, 0.5, 1.0], [0.7, -0.5, 1.0]]
    scene = ti.Scene.from_polygons(torch.tensor([sq, ceiling, blocker, blocker[::-1], side], dtype=D))
    return scene.subdivide(2)[0]


def _split_some(scene, every=5):
    leaves = Leaves(scene, torch.arange(scene.num_facets))
    return split(leaves, torch.arange(scene.num_facets) % every == 0)


def _pair_by_pair(monkeypatch):
    """Every pair integrated on its own (no translated copies, :mod:`~torch_interreflect.formfactors.moment_copies`):
    which pair of a class is integrated then cannot move the result's last bits."""
    monkeypatch.setattr(moments_module, "translated_copies", lambda kern, setup, todo: todo.copy())


@pytest.mark.parametrize("copies", [False, True])
@pytest.mark.parametrize("degree", [0, 2])
def test_reuse_without_occlusion_equals_a_fresh_computation(monkeypatch, degree, copies):
    """On a groove (no third facet) the moments with ``reuse`` equal a fresh computation, and every pair of two kept
    facets is reused: bit for bit with every pair integrated on its own; to rounding where translated copies take
    the sums of the pair of their class that was integrated (another pair of the class in each computation)."""
    if not copies:
        _pair_by_pair(monkeypatch)
    scene = ti.scenes.v_groove(30.0, divisions=4, dtype=D)
    previous = moment_form_factors(scene, degree)
    leaves = _split_some(scene)
    fresh = moment_form_factors(leaves.scene, degree)
    again = moment_form_factors(leaves.scene, degree, reuse=(previous, leaves.kept))
    if copies:
        assert fresh.info["copied_pairs"] > 0
        # measured: 2.7e-16 (degree 0) and 1.0e-15 (degree 2) of the largest entry
        assert float((again.matrix - fresh.matrix).abs().amax() / fresh.matrix.abs().amax()) < 5e-15
    else:
        assert torch.equal(again.matrix, fresh.matrix)
    m = leaves.kept.numel()
    _, setup, _ = fresh.info["_sums"]
    both_kept = int(((setup["dom"] < m) & (setup["tgt"] < m)).sum())
    assert again.info["reused_pairs"] == both_kept > 0
    assert fresh.info["reused_pairs"] == 0


def test_reuse_keeps_the_previous_rays():
    """With occlusion, the blocks of two kept facets are the previous ones exactly (their rays are not drawn again),
    those of a new facet are computed (here with other rays: another seed)."""
    scene = _occluded_scene()
    previous = moment_form_factors(scene, 2, seed=0)
    assert previous.info["occluded_pairs"] > 0
    leaves = _split_some(scene)
    kept = leaves.kept
    m = kept.numel()
    with pytest.raises(ValueError, match="same settings"):
        moment_form_factors(leaves.scene, 2, seed=0, visibility_samples=4, reuse=(previous, kept))
    again = moment_form_factors(leaves.scene, 2, seed=0, reuse=(previous, kept))
    old = _blocks(previous, scene.num_facets)[kept][:, kept]
    assert torch.equal(_blocks(again, leaves.scene.num_facets)[:m, :m], old)
    fresh = moment_form_factors(leaves.scene, 2, seed=0)
    # the fresh call draws other rays for the kept occluded pairs (the jitter is seeded by the pair's index)
    assert not torch.equal(_blocks(fresh, leaves.scene.num_facets)[:m, :m], old)
    new = _blocks(again, leaves.scene.num_facets)[:, m:]
    assert torch.equal(new, _blocks(fresh, leaves.scene.num_facets)[:, m:])  # new facets: as a fresh call


def test_reuse_with_the_facets_in_another_order():
    """Kept facets in the reverse order: pairs whose domain and target swap take the transposed sums. The result is
    the previous matrix permuted (to rounding: the blocks are multiplied out in the other order) and agrees with a
    fresh computation to the quadrature's accuracy."""
    scene = ti.scenes.v_groove(45.0, divisions=2, dtype=D)
    previous = moment_form_factors(scene, 2, quadrature_tol=1e-9)
    order = torch.arange(scene.num_facets - 1, -1, -1)
    permuted = ti.Scene.from_parts(scene.corners[order], scene.is_triangle[order], None, None)
    again = moment_form_factors(permuted, 2, quadrature_tol=1e-9, reuse=(previous, order))
    n = scene.num_facets
    assert again.info["reused_pairs"] == again.info["pairs"]
    assert torch.allclose(_blocks(again, n), _blocks(previous, n)[order][:, order], rtol=1e-14, atol=1e-16)
    fresh = moment_form_factors(permuted, 2, quadrature_tol=1e-9)
    assert torch.allclose(again.matrix, fresh.matrix, rtol=0, atol=1e-9)


def test_reuse_rejects_what_it_cannot_use():
    scene = ti.scenes.v_groove(45.0, divisions=2, dtype=D)
    K = moment_form_factors(scene, 2)
    leaves = _split_some(scene, every=2)
    with pytest.raises(ValueError, match="straight from moment_form_factors"):
        moment_form_factors(leaves.scene, 2, reuse=(K.truncate(1), leaves.kept))
    with pytest.raises(ValueError, match="same settings"):
        moment_form_factors(leaves.scene, 2, quadrature_tol=1e-4, reuse=(K, leaves.kept))
    with pytest.raises(ValueError, match="first facets, unchanged"):
        moment_form_factors(leaves.scene, 2, reuse=(K, leaves.kept.flip(0)))
    with pytest.raises(ValueError, match="must index"):
        moment_form_factors(leaves.scene, 2, reuse=(K, leaves.kept + scene.num_facets))


def test_reuse_refuses_other_surfaces():
    """Kept facets unchanged but a blocker moved: the kept pairs' rays were cast against the old blocker, so reuse
    refuses (it would give F between floor and ceiling 0.0819 for a fresh 0.0573)."""
    scene = _occluded_scene()
    previous = moment_form_factors(scene, 2)
    n = scene.num_facets
    moved = scene.corners.clone()
    moved[8:16, :, 0] += 0.6  # the blocker's pieces (both sides), the floor and ceiling kept
    keep = torch.cat([torch.arange(8), torch.arange(16, n)])
    order = torch.cat([keep, torch.arange(8, 16)])
    other = ti.Scene.from_parts(moved[order], scene.is_triangle[order], None, None)
    with pytest.raises(ValueError, match="refinement of the previous scene"):
        moment_form_factors(other, 2, reuse=(previous, keep))


def test_reused_sums_copies_transposes_and_skips_a_changed_need():
    """The pair sums are copied where both facets are kept, transposed where domain and target swapped, and left to
    integrate where the pair needs rays now but not before (or the reverse) or holds a new facet."""
    nb = 2
    old_acc = np.arange(3 * nb * nb, dtype=float).reshape(3, nb, nb)
    old = ({"dom": torch.tensor([0, 1, 0]), "tgt": torch.tensor([1, 2, 2]),
            "need": torch.tensor([False, False, True])}, old_acc)
    new = {"dom": torch.tensor([0, 2, 0, 3]), "tgt": torch.tensor([1, 1, 2, 0]),
           "need": torch.tensor([False, False, False, False])}
    acc = np.full((4, nb, nb), -1.0)
    todo = reused_sums(new, old, np.array([0, 1, 2, -1]), acc)
    assert todo.tolist() == [2, 3]  # pair (0, 2) needed rays before; facet 3 is new
    assert np.array_equal(acc[0], old_acc[0])
    assert np.array_equal(acc[1], old_acc[1].T)  # (2, 1) was (1, 2)
    assert (acc[2:] == -1).all()


@pytest.mark.parametrize("copies", [False, True])
def test_the_planner_reuses_and_gives_the_same_answer(monkeypatch, copies):
    """``render`` on the quadratic basis reuses the previous level's moments after a split; on an unoccluded groove its
    answer is that of the planner without reuse: bit for bit with every pair integrated on its own, to rounding with
    translated copies."""
    if not copies:
        _pair_by_pair(monkeypatch)
    groove = ti.scenes.v_groove(60.0, size=(1.0, 1.0), divisions=2, dtype=D)
    args = (groove, torch.full((8,), 0.9, dtype=D), "uniform", torch.ones(1, dtype=D))
    kw = {"wavelengths": torch.tensor([550.0], dtype=D), "accuracy": 1e-4, "basis": "quadratic"}
    reused = []
    real = moments_plan.moment_form_factors

    def counting(*a, **k):
        K = real(*a, **k)
        reused.append(K.info["reused_pairs"])
        return K

    monkeypatch.setattr(moments_plan, "moment_form_factors", counting)
    out = ti.render(*args, **kw)
    assert out.report.iterations >= 1 and max(reused) > 0
    monkeypatch.setattr(moments_plan, "moment_form_factors", lambda *a, reuse=None, **k: real(*a, **k))
    plain = ti.render(*args, **kw)
    if copies:  # measured: the irradiance the same bits, the estimate 5.3e-14 apart (relative)
        assert torch.allclose(out.irradiance, plain.irradiance, rtol=1e-15, atol=0)
        assert math.isclose(out.report.estimated, plain.report.estimated, rel_tol=2e-13, abs_tol=0)
    else:
        assert torch.equal(out.irradiance, plain.irradiance)
        assert math.isclose(out.report.estimated, plain.report.estimated, rel_tol=0, abs_tol=0)
