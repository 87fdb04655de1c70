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
    # 6 × 6 pieces a plate: a pair's class is its two pieces' columns and their offset along the hinge (11)
    assert K.info["pairs"] == 36 * 36 and K.info["copied_pairs"] == 36 * 36 - 6 * 6 * 11
    dev = float((K.matrix - R.matrix).abs().amax() / R.matrix.abs().amax())
    # measured: 3.4e-16 / 3.3e-15 (degree 0 / 2) in float64; 3.6e-7 / 5.9e-7 in float32, where the copies' corners
    # differ by the float32 rounding of the scene itself (copy_tie: 16 ulp of its size)
    assert dev < (2e-14 if dtype == torch.float64 else 2e-6)
    assert K.matrix.dtype == dtype


@pytest.mark.parametrize("degree", [1, 2])
def test_occluded_copies_keep_their_own_rays(monkeypatch, degree):
    """The Cornell box split at its contacts and cut to 0.2 m: occluded copies take the exact sums of their class
    and subtract their own blocked part (their own rays), so the matrix is the pair-by-pair one to rounding; a copy
    given its class's blocked part instead would differ at the level of the ray noise."""
    scene = _cornell(torch.float64)
    K = moment_form_factors(scene, degree, quadrature_tol=1e-3, visibility_samples=2)
    _, setup, _ = K.info["_sums"]
    assert K.info["copied_pairs"] > 0 and K.info["occluded_pairs"] > 0
    _pair_by_pair(monkeypatch)
    R = moment_form_factors(scene, degree, quadrature_tol=1e-3, visibility_samples=2)
    assert K.info["rays"] == R.info["rays"]
    dev = float((K.matrix - R.matrix).abs().amax() / R.matrix.abs().amax())
    assert dev < 1e-14  # measured 6.1e-16 / 1.5e-15 (degree 1 / 2); 107 of 5,015 pairs copied
    # the occluded pairs' exact sums (kept to draw their rays again) agree as well
    _, setup_r, _ = R.info["_sums"]
    assert np.abs(setup["exact"] - setup_r["exact"]).max() < 1e-12 * np.abs(setup_r["exact"]).max()


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
