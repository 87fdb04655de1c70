"""Translated copies among the moments' pairs (:func:`~torch_interreflect.formfactors.moment_copies.translated_copies`):
one pair of each class is integrated and the others take its sums (less their own blocked part when occluded), so
the moments equal those integrated pair by pair, to rounding."""

import numpy as np
import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.formfactors import moments as moments_module
from torch_interreflect.formfactors.compiled import loops
from torch_interreflect.formfactors.moment_copies import translated_copies

pytestmark = pytest.mark.skipif(loops("moments") is None, reason="the moments need numba")


def _pair_by_pair(monkeypatch):
    monkeypatch.setattr(moments_module, "translated_copies", lambda kern, setup, todo: todo.copy())


def _cornell(dtype):
    scene = ti.geometry.split_at_contacts(ti.scenes.cornell_box(dtype=dtype))[0]
    return ti.geometry.subdivide_to(scene, 0.2)[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [0, 2])
def test_copies_equal_pair_by_pair_on_a_groove(monkeypatch, degree, dtype):
    """A uniform groove: every pair repeats along the hinge, so most pairs are copies; the matrix is the one
    integrated pair by pair, to rounding (float64) or to the float32 scene's own rounding of its corners."""
    scene = ti.scenes.v_groove(30.0, divisions=6, dtype=dtype)
    K = moment_form_factors(scene, degree, quadrature_tol=1e-8)
    _pair_by_pair(monkeypatch)
    R = moment_form_factors(scene, degree, quadrature_tol=1e-8)
    assert R.info["copied_pairs"] == 0
    # 6 × 6 pieces a plate: a pair's class is its two pieces' columns and their offset along the hinge (11); a
    # float32 copy that straddles a step of the rounding would be integrated on its own
    copies = 36 * 36 - 6 * 6 * 11
    assert K.info["pairs"] == 36 * 36
    assert K.info["copied_pairs"] == copies if dtype == torch.float64 else K.info["copied_pairs"] >= 0.9 * copies
    dev = float((K.matrix - R.matrix).abs().amax() / R.matrix.abs().amax())
    # measured: 3.4e-16 / 3.3e-15 (degree 0 / 2) in float64; 3.6e-7 / 5.9e-7 in float32, where the copies' corners
    # differ by the float32 rounding of the scene itself (copy_tie: 16 ulp of its size)
    bound = {(0, torch.float64): 2e-15, (2, torch.float64): 2e-14, (0, torch.float32): 2e-6, (2, torch.float32): 2e-6}
    assert dev < bound[degree, dtype]
    assert K.matrix.dtype == dtype


@pytest.mark.parametrize("degree", [1, 2])
def test_occluded_copies_keep_their_own_rays(monkeypatch, degree):
    """The Cornell box split at its contacts and cut to 0.2 m: occluded copies take the exact sums of their class
    and subtract their own blocked part (their own rays), so the matrix is the pair-by-pair one to rounding; a copy
    given its class's blocked part instead would differ at the level of the ray noise."""
    scene = _cornell(torch.float64)
    K = moment_form_factors(scene, degree, quadrature_tol=1e-3, visibility_samples=2)
    _, setup, _ = K.info["_sums"]
    todo = np.arange(setup["dom"].numel(), dtype=np.int64)
    rep = translated_copies(loops("moments"), setup, todo)
    need = setup["need"].numpy()
    copy = rep != todo
    assert (copy & need & need[rep]).any()  # occluded copies of occluded pairs (the mixed cases: below)
    _pair_by_pair(monkeypatch)
    R = moment_form_factors(scene, degree, quadrature_tol=1e-3, visibility_samples=2)
    assert K.info["rays"] == R.info["rays"]
    dev = float((K.matrix - R.matrix).abs().amax() / R.matrix.abs().amax())
    assert dev < (5e-15 if degree == 1 else 1e-14)  # measured 6.1e-16 / 1.5e-15; 107 of 5,015 pairs copied
    # the occluded pairs' exact sums (kept to draw their rays again) agree as well
    _, setup_r, _ = R.info["_sums"]
    assert np.abs(setup["exact"] - setup_r["exact"]).max() < 1e-14 * np.abs(setup_r["exact"]).max()
    # and the rays drawn again (a replica) take the same exact sums and their own blocked parts
    again = moments_module.resample_visibility(K, seed=5)
    again_r = moments_module.resample_visibility(R, seed=5)
    assert float((again.matrix - again_r.matrix).abs().amax() / again_r.matrix.abs().amax()) < 1e-14


def _two_hinges(shift):
    """Two separate hinges of two unit squares; the second moved by ``(3, 0, 0) + shift``."""
    a = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]
    b = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]]
    move = np.array([3.0, 0.0, 0.0]) + np.asarray(shift)
    polys = np.array([a, b, np.array(a) + move, np.array(b) + move])
    return ti.Scene.from_polygons(torch.tensor(polys, dtype=torch.float64))


def _setup(scene):
    K = moment_form_factors(scene, 2, quadrature_tol=1e-4, occlusion=False)
    return K, K.info["_sums"][1]


def test_translated_copies_finds_the_moved_hinge():
    """The second hinge's pair copies the first's; the cross pairs between the hinges do not copy one another
    unless they are translates too."""
    K, setup = _setup(_two_hinges([0.0, 0.0, 0.0]))
    dom, tgt = setup["pairs"][0], setup["pairs"][1]
    todo = np.arange(dom.size, dtype=np.int64)
    rep = translated_copies(loops("moments"), setup, todo)
    hinge = [p for p in todo if {int(dom[p]), int(tgt[p])} in ({0, 1}, {2, 3})]
    assert len(hinge) == 2 and rep[hinge[1]] == hinge[0] and rep[hinge[0]] == hinge[0]
    assert K.info["copied_pairs"] >= 1


def test_a_pair_moved_by_more_than_the_quantum_is_not_a_copy():
    """A hinge whose second square is moved by 1000 quanta is integrated on its own."""
    size = float(np.linalg.norm([4.0, 1.0, 1.0]))
    _, setup = _setup(_two_hinges([0.0, 0.0, 0.0]))
    corners = setup["corners"].copy()
    corners[3] += 1000 * setup["tie"] * size * np.array([0.0, 0.0, 1.0])
    setup = dict(setup, corners=corners)
    dom, tgt = setup["pairs"][0], setup["pairs"][1]
    todo = np.arange(dom.size, dtype=np.int64)
    rep = translated_copies(loops("moments"), setup, todo)
    hinge = [p for p in todo if {int(dom[p]), int(tgt[p])} in ({0, 1}, {2, 3})]
    assert rep[hinge[1]] == hinge[1]


def test_hash_collisions_are_checked():
    """With every hash equal (a stand-in for collisions), pairs that are not copies of the first are integrated on
    their own, and the real copy is still found only when it is the first's."""

    class Colliding:
        same_pairs = staticmethod(loops("moments").same_pairs)

        @staticmethod
        def pair_hashes(*args):
            args[-1][:] = 7

    _, setup = _setup(_two_hinges([0.0, 0.0, 0.0]))
    todo = np.arange(setup["pairs"][0].size, dtype=np.int64)
    rep = translated_copies(Colliding(), setup, todo)
    honest = translated_copies(loops("moments"), setup, todo)
    # every pair maps to the first pair or to itself, and never to a pair that is not its copy
    assert np.all((rep == todo[0]) | (rep == todo))
    assert np.all((rep == todo) | (honest == rep))
    # with the first pair a hinge, its copy (the other hinge) is still found through the colliding hash
    dom, tgt = setup["pairs"][0], setup["pairs"][1]
    hinge = [p for p in todo if {int(dom[p]), int(tgt[p])} in ({0, 1}, {2, 3})]
    first = np.array([hinge[0], *[p for p in todo if p != hinge[0]]], dtype=np.int64)
    rep = translated_copies(Colliding(), setup, first)
    assert rep[list(first).index(hinge[1])] == hinge[0] and (rep != first).sum() == 1


def _hinges(blocked):
    """Hinges of two unit squares side by side along x (3 m apart), each with a small square floating in its corner
    (a blocker of its pair) where ``blocked`` says so."""
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    b = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    lid = np.array([[0.2, 0.3, 0.4], [0.5, 0.3, 0.4], [0.5, 0.6, 0.4], [0.2, 0.6, 0.4]])
    move = np.array([3.0, 0.0, 0.0])
    polys = [q + k * move for k in range(len(blocked)) for q in (a, b)]
    # the lids at other heights: coplanar ones would form one plane group spanning every hinge, a candidate blocker
    # of all (visibility.blocker_candidates is conservative per group)
    polys += [lid + k * move + [0.0, 0.0, 0.05 * k] for k, on in enumerate(blocked) if on]
    return ti.Scene.from_polygons(torch.tensor(np.array(polys), dtype=torch.float64))


@pytest.mark.parametrize("blocked", [(True, False, True), (False, True)])
def test_copies_across_occluded_and_open_pairs(monkeypatch, blocked):
    """Copies whose class's integrated pair is occluded while they are not, and the other way round: the open copy
    takes the class's exact sums (kept apart from its own ray-cast sums), the occluded one subtracts its own blocked
    part; both equal the pair-by-pair moments."""
    scene = _hinges(blocked)
    K = moment_form_factors(scene, 2, quadrature_tol=1e-6, visibility_samples=3)
    _, setup, _ = K.info["_sums"]
    todo = np.arange(setup["dom"].numel(), dtype=np.int64)
    rep = translated_copies(loops("moments"), setup, todo)
    need = setup["need"].numpy()
    copy = rep != todo
    if blocked[0]:  # the first hinge is occluded: an open copy of it, and an occluded one
        assert (copy & ~need & need[rep]).any() and (copy & need & need[rep]).any()
    else:
        assert (copy & need & ~need[rep]).any()
    _pair_by_pair(monkeypatch)
    R = moment_form_factors(scene, 2, quadrature_tol=1e-6, visibility_samples=3)
    assert float((K.matrix - R.matrix).abs().amax() / R.matrix.abs().amax()) < 1e-14
