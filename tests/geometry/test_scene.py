import math

import numpy as np
import pytest
import torch
import trimesh

import torch_interreflect as ti
from torch_interreflect.errors import GeometryError, ShapeError

SQUARE = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_properties_of_a_quad_and_a_triangle(dtype):
    tri = [[0.0, 0, 0], [2, 0, 0], [0, 1, 0]]
    s = ti.Scene.from_polygons(torch.tensor([SQUARE], dtype=dtype))
    t = ti.Scene.from_polygons(torch.tensor([tri], dtype=dtype))
    assert s.dtype == dtype and t.dtype == dtype
    torch.testing.assert_close(s.areas, torch.tensor([1.0], dtype=dtype))
    torch.testing.assert_close(t.areas, torch.tensor([1.0], dtype=dtype))
    torch.testing.assert_close(s.normals, torch.tensor([[0.0, 0, 1]], dtype=dtype))
    torch.testing.assert_close(t.centroids, torch.tensor([[2 / 3, 1 / 3, 0.0]], dtype=dtype))
    torch.testing.assert_close(s.centroids, torch.tensor([[0.5, 0.5, 0.0]], dtype=dtype))
    assert bool(t.is_triangle[0]) and not bool(s.is_triangle[0])


def test_clockwise_order_flips_the_normal():
    s = ti.Scene.from_polygons(torch.tensor([SQUARE[::-1]]))
    torch.testing.assert_close(s.normals, torch.tensor([[0.0, 0, -1]]))


def test_vertices_and_faces_constructor_matches_polygons():
    v = torch.tensor([*SQUARE, [2.0, 0, 0]])
    s = ti.Scene(v, torch.tensor([[0, 1, 2, 3]]))
    torch.testing.assert_close(s.corners, torch.tensor([SQUARE]))
    t = ti.Scene(v, torch.tensor([[1, 4, 2]]))
    assert t.num_facets == 1 and bool(t.is_triangle[0])


def test_from_trimesh_keeps_face_colour_materials():
    box = trimesh.creation.box(extents=(1, 2, 3))
    colours = np.tile([255, 0, 0, 255], (12, 1))
    colours[6:] = [0, 255, 0, 255]
    box.visual.face_colors = colours
    s = ti.Scene.from_trimesh(box)
    assert s.num_facets == 12
    assert s.material.tolist() == [1] * 6 + [0] * 6 or s.material.tolist() == [0] * 6 + [1] * 6
    assert len(s.material_names) == 2
    torch.testing.assert_close(s.areas.sum(), torch.tensor(22.0))


@pytest.mark.parametrize(
    ("corners", "message"),
    [
        ([[[0.0, 0, 0], [1, 0, 0], [1, 1, math.nan], [0, 1, 0]]], "facet 0 has non-finite"),
        ([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]], "facet 0 is degenerate"),
        ([[[0.0, 0, 0], [1, 0, 0], [1, 1, 0.1], [0, 1, 0]]], "facet 0 is not planar"),
        ([[[0.0, 0, 0], [1, 0, 0], [0.2, 0.2, 0], [0, 1, 0]]], "facet 0 is not a convex quad"),
        ([[[0.0, 0, 0], [1, 1, 0], [1, 0, 0], [0, 1, 0]]], "facet 0 is not a convex quad"),
    ],
)
def test_invalid_facets_are_named(corners, message):
    with pytest.raises(GeometryError, match=message):
        ti.Scene.from_polygons(torch.tensor(corners))


def test_the_bad_facet_is_named_among_good_ones():
    good = [SQUARE] * 3
    bad = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0]]
    with pytest.raises(ValueError, match="facet 2 is not planar"):
        ti.Scene.from_polygons(torch.tensor([*good[:2], bad, good[2]]))


def test_shape_errors():
    with pytest.raises(ShapeError, match=r"\[F, 3, 3\] or \[F, 4, 3\]"):
        ti.Scene.from_polygons(torch.zeros(2, 5, 3))
    with pytest.raises(ShapeError, match="faces index vertices"):
        ti.Scene(torch.zeros(3, 3), torch.tensor([[0, 1, 7]]))
    with pytest.raises(TypeError):
        ti.Scene(torch.zeros(3, 3), torch.tensor([[0.0, 1.0, 2.0]]))


@pytest.mark.parametrize("k", [1, 2, 3])
def test_subdivide_preserves_area_plane_and_parents(k):
    tri = [[0.0, 0, 0], [2, 0, 0], [0, 1, 1]]
    scene = ti.Scene.concatenate(
        [ti.Scene.from_polygons(torch.tensor([SQUARE], dtype=torch.float64)),
         ti.Scene.from_polygons(torch.tensor([tri], dtype=torch.float64))]
    )
    fine, parent = scene.subdivide(k)
    assert fine.num_facets == 2 * k * k
    assert parent.tolist() == [0] * k * k + [1] * k * k
    sums = torch.zeros(2, dtype=torch.float64).index_add(0, parent, fine.areas)
    torch.testing.assert_close(sums, scene.areas)
    torch.testing.assert_close(fine.normals, scene.normals[parent])
    assert bool(fine.is_triangle[k * k :].all()) and not bool(fine.is_triangle[: k * k].any())
    avg = scene.average_to_parent(fine.centroids, parent, fine)
    torch.testing.assert_close(avg, scene.centroids)


def test_subdivide_rejects_bad_k():
    with pytest.raises(ValueError, match="k must be an integer >= 1"):
        ti.scenes.box_corner(divisions=1).subdivide(0)


def test_to_moves_dtype(dtype):
    s32 = ti.scenes.box_corner(divisions=2, dtype=torch.float32)
    s = s32.to(dtype)
    assert s.dtype == dtype and s.material.dtype == torch.int64
    torch.testing.assert_close(s.corners, s32.corners.to(dtype), rtol=0, atol=0)
    assert torch.equal(s.material, s32.material) and torch.equal(s.is_triangle, s32.is_triangle)
    torch.testing.assert_close(s.areas.sum(), torch.tensor(3.0, dtype=dtype))  # three unit squares


@pytest.mark.parametrize("angle", [30.0, 45.0, 90.0, 150.0])
def test_v_groove_geometry(angle):
    s = ti.scenes.v_groove(angle, size=(0.09, 0.06), divisions=(10, 5), dtype=torch.float64)
    assert s.num_facets == 100
    n_a, n_b = s.normals[0], s.normals[-1]
    # the angle between the plates' planes: normals make 180° - φ
    cosang = float(n_a @ n_b)
    assert math.isclose(cosang, math.cos(math.radians(180.0 - angle)), abs_tol=1e-12)
    torch.testing.assert_close(s.areas.sum(), torch.tensor(2 * 0.09 * 0.06, dtype=torch.float64))
    # the documented facet order: column 0 (nearest the hinge) first
    assert float(s.centroids[0, 0]) < float(s.centroids[10, 0])
    # plate B's normal points into the groove (toward plate A)
    assert float((s.centroids[:50].mean(0) - s.centroids[-1]) @ n_b) > 0


def test_closed_box_faces_inward():
    s = ti.scenes.closed_box(size=(1.0, 2.0, 3.0), divisions=2, dtype=torch.float64)
    centre = torch.tensor([0.5, 1.0, 1.5], dtype=torch.float64)
    assert bool((((centre - s.centroids) * s.normals).sum(1) > 0).all())
    torch.testing.assert_close(s.areas.sum(), torch.tensor(22.0, dtype=torch.float64))


def test_cornell_box_parts():
    s = ti.scenes.cornell_box(divisions=2)
    assert s.material_names[:2] == ["floor", "ceiling"] and "tall_block" in s.material_names
    floor = s.normals[s.material == 0]
    torch.testing.assert_close(floor, torch.tensor([[0.0, 1.0, 0.0]]).expand_as(floor))
    light = s.normals[s.material == s.material_names.index("light")]
    torch.testing.assert_close(light, torch.tensor([[0.0, -1.0, 0.0]]).expand_as(light))


def test_w_shape_parts_face_each_other_across_valleys():
    s = ti.scenes.w_shape(divisions=(2, 4, 2), dtype=torch.float64)
    assert s.material_names == ["outer_left", "inner_left", "inner_right", "outer_right"]
    m = s.material
    c = [s.centroids[m == k].mean(0) for k in range(4)]
    n = [s.normals[m == k][0] for k in range(4)]
    assert float((c[1] - c[0]) @ n[0]) > 0 and float((c[0] - c[1]) @ n[1]) > 0
    assert float((c[3] - c[2]) @ n[2]) > 0 and float((c[2] - c[3]) @ n[3]) > 0


def test_room_parts_and_scaling():
    s = ti.scenes.room(divisions=2, dtype=torch.float64)
    assert s.material_names == ["floor", "ceiling", "walls", "table", "cabinet", "box", "lamp"]
    # the shell faces inward: every shell facet's normal points toward the room's centre
    shell = s.material <= 2
    centre = torch.tensor([2.0, 2.5, 1.3], dtype=torch.float64)
    assert bool((((centre - s.centroids[shell]) * s.normals[shell]).sum(1) > 0).all())
    # shell area: floor + ceiling + walls of a 4 × 5 × 2.6 m room
    torch.testing.assert_close(s.areas[shell].sum(), torch.tensor(2 * 20.0 + 2 * 2.6 * 9.0, dtype=torch.float64))
    # furniture faces outward (away from its own centre); the lamp faces down
    cab = s.material == s.material_names.index("cabinet")
    assert bool((((s.centroids[cab] - s.centroids[cab].mean(0)) * s.normals[cab]).sum(1) > 0).all())
    lamp = s.normals[s.material == s.material_names.index("lamp")]
    torch.testing.assert_close(lamp, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64).expand_as(lamp))
    # facets per metre: about 98 · divisions² facets
    n4 = ti.scenes.room(divisions=4).num_facets
    assert 1400 < n4 < 1800 and n4 > 3 * s.num_facets
    with pytest.raises(ValueError, match="divisions"):
        ti.scenes.room(divisions=0)


def test_room_without_ceiling_is_the_closed_room_less_its_ceiling():
    closed = ti.scenes.room(divisions=1, lamp=False, dtype=torch.float64)
    open_top = ti.scenes.room(divisions=1, lamp=False, ceiling=False, dtype=torch.float64)
    assert open_top.material_names == ["floor", "walls", "table", "cabinet", "box"]
    keep = closed.material != closed.material_names.index("ceiling")
    assert open_top.num_facets == int(keep.sum()) < closed.num_facets
    torch.testing.assert_close(open_top.corners, closed.corners[keep], rtol=0, atol=0)
    # nothing faces down from the ceiling's height: the top is open
    top = (open_top.centroids[:, 2] > 2.59) & (open_top.normals[:, 2] < -0.5)
    assert not bool(top.any())
    with pytest.raises(TypeError, match="ceiling must be True or False; got 'no'"):
        ti.scenes.room(divisions=1, ceiling="no")
