"""subdivide_to: pieces no longer than a size, covering their parents exactly, in the parents' order."""

import math

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ValueRangeError
from torch_interreflect.geometry import split_at_contacts, subdivide_to
from torch_interreflect.geometry.sizing import pieces_per_side


def strip_and_triangle(dtype):
    """A 1 × 0.25 m strip (z = 0) and a right triangle with legs 0.5 m (x = 0), both with materials."""
    quad = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.25, 0.0], [0.0, 0.25, 0.0]]
    tri = [[0.0, 0.0, 0.1], [0.0, 0.5, 0.1], [0.0, 0.0, 0.6], [0.0, 0.0, 0.6]]
    return ti.Scene.from_parts(torch.tensor([quad, tri], dtype=dtype), torch.tensor([False, True]),
                               torch.tensor([0, 1]), ["strip", "tri"])


def edges(scene):
    c = scene.corners
    return (c.roll(-1, dims=1) - c).norm(dim=-1)  # a triangle's last corner repeats: its 2→3 edge is 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pieces_no_longer_than_size_and_cover_parents(dtype):
    scene = strip_and_triangle(dtype)
    fine, parent = subdivide_to(scene, 0.3)
    ku, kv = pieces_per_side(scene, 0.3)
    assert ku.tolist() == [4, 3] and kv.tolist() == [1, 3]  # the strip cut across its length only; 0.71 m / 0.3
    assert parent.tolist() == [0] * 4 + [1] * 9
    assert fine.is_triangle.tolist() == [False] * 4 + [True] * 9
    assert fine.material.tolist() == parent.tolist() and fine.material_names == ["strip", "tri"]
    assert float(edges(fine).max()) <= 0.3 * (1 + 1e-6)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    areas = torch.zeros(2, dtype=dtype).index_add_(0, parent, fine.areas)
    torch.testing.assert_close(areas, scene.areas, rtol=tol, atol=0)
    assert fine.dtype == dtype


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_same_as_subdivide_on_squares(dtype):
    scene = ti.scenes.closed_box(divisions=2, dtype=dtype)  # 24 squares of side 0.5
    side = float(edges(scene).max())
    for k in (1, 2, 3):
        a, pa = scene.subdivide(k)
        b, pb = subdivide_to(scene, side / k)
        assert torch.equal(a.corners, b.corners) and torch.equal(pa, pb)


def test_large_size_keeps_the_scene():
    scene = ti.scenes.cornell_box(divisions=1, light=False)
    fine, parent = subdivide_to(scene, 10.0)
    assert torch.equal(fine.corners, scene.corners) and parent.tolist() == list(range(scene.num_facets))


def test_cornell_pieces_after_the_contacts():
    """The Cornell box split at its contacts, then to 0.3 m: every piece within the size, areas per user facet
    kept, and the floor's long strips cut across their length only."""
    box = ti.scenes.cornell_box(divisions=1, light=False, dtype=torch.float64)
    split, top = split_at_contacts(box)
    fine, parent = subdivide_to(split, 0.3)
    assert float(edges(fine).max()) <= 0.3 + 1e-12
    per_user = torch.zeros(box.num_facets, dtype=torch.float64).index_add_(0, top[parent], fine.areas)
    torch.testing.assert_close(per_user, box.areas, rtol=1e-13, atol=0)
    ku, kv = pieces_per_side(split, 0.3)
    assert int((ku * kv).sum()) == fine.num_facets and bool(((ku == 1) ^ (kv == 1) | (ku == kv)).all())


def test_differentiable_in_the_corners():
    """The pieces' areas sum to the parent's area, so their gradients with respect to the corners are equal."""
    corners = strip_and_triangle(torch.float64).corners.clone().requires_grad_(True)
    scene = ti.Scene.from_parts(corners, torch.tensor([False, True]), None, None)
    fine, _ = subdivide_to(scene, 0.2)
    (g_fine,) = torch.autograd.grad(fine.areas.sum(), corners)
    (g_parent,) = torch.autograd.grad(scene.areas.sum(), corners)
    for g in (g_fine, g_parent):  # the triangle's repeated last corner: one point, its gradient summed
        g[1, 2] += g[1, 3]
        g[1, 3] = 0.0
    torch.testing.assert_close(g_fine, g_parent, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("size", [0.0, -1.0, math.inf, math.nan, True, "0.3", None])
def test_bad_size(size):
    with pytest.raises(ValueRangeError, match="size must be a positive finite length"):
        subdivide_to(strip_and_triangle(torch.float64), size)


def test_not_a_scene():
    with pytest.raises(TypeError, match="expects a Scene"):
        subdivide_to(torch.zeros(2, 4, 3), 0.3)
