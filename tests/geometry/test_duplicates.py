"""Coincident / overlapping coplanar facets (issue 13 item 2) and the reflecting side of trimesh meshes (item 4)."""

import numpy as np
import pytest
import torch
import trimesh

import torch_interreflect as ti
from torch_interreflect.errors import GeometryError, GeometryWarning
from torch_interreflect.geometry.duplicates import overlapping_pairs

F64 = torch.float64


def _box_with_copies(copies):
    box = ti.scenes.closed_box(divisions=2, dtype=F64)
    return box, torch.cat([box.corners, box.corners[copies]])


def test_duplicate_facets_are_refused_naming_the_pairs():
    # before: accepted, rows summed to 1.4-1.6 and the solve at r = 0.9 gave negative irradiance
    box, corners = _box_with_copies([0, 5])
    n = box.num_facets
    with pytest.raises(GeometryError, match=rf"\(0, {n}\), \(5, {n + 1}\)"):
        ti.Scene.from_polygons(corners)


def test_drop_keeps_the_first_of_each_group_and_gives_the_clean_scene():
    box, corners = _box_with_copies([0, 5, 5])
    s = ti.Scene.from_polygons(corners, duplicates="drop")
    assert s.num_facets == box.num_facets
    torch.testing.assert_close(s.corners, box.corners)
    rs = ti.form_factors(s).row_sums()
    assert float((rs - 1).abs().max()) < 1e-6


def test_partial_overlap_is_found_and_touching_or_back_to_back_facets_are_not():
    sq = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]], dtype=F64)
    shifted = sq + torch.tensor([0.5, 0.25, 0.0], dtype=F64)  # overlaps a quarter-ish of the square
    touching = sq + torch.tensor([1.0, 0.0, 0.0], dtype=F64)  # shares an edge
    corner = sq + torch.tensor([1.0, 1.0, 0.0], dtype=F64)  # shares a corner
    back = sq.flip(1)  # same square, facing down: a thin wall
    above = sq + torch.tensor([0.0, 0.0, 1e-3], dtype=F64)  # parallel, 1 mm above
    with pytest.raises(GeometryError, match=r"\(0, 1\)"):
        ti.Scene.from_polygons(torch.cat([sq, shifted]))
    s = ti.Scene.from_polygons(torch.cat([sq, touching, corner, back, above]))
    assert s.num_facets == 5
    # a triangle inside a quad of the same plane
    tri = torch.tensor([[[0.2, 0.2, 0], [0.8, 0.2, 0], [0.5, 0.7, 0]]], dtype=F64)
    quad_tri = torch.cat([sq, torch.cat([tri, tri[:, 2:]], 1)]).numpy()  # a triangle repeats its last corner
    assert overlapping_pairs(quad_tri, np.array([[0.0, 0, 1], [0, 0, 1]])).tolist() == [[0, 1]]


def test_duplicates_from_trimesh_and_the_row_sum_guard():
    box = trimesh.creation.box()
    twice = trimesh.util.concatenate([box, box])
    with pytest.raises(GeometryError, match="overlap"):
        ti.Scene.from_trimesh(twice, dtype=F64, side="inside")
    assert ti.Scene.from_trimesh(twice, dtype=F64, side="inside", duplicates="drop").num_facets == 12
    # with the check switched off the form factors refuse rows that sum above 1
    kept = ti.Scene.from_trimesh(twice, dtype=F64, side="inside", duplicates="keep")
    with pytest.raises(GeometryError, match="rows must sum to at most 1"):
        ti.form_factors(kept)


def test_duplicate_check_is_fast_enough_for_a_large_mesh():
    # 20,480 triangles of a sphere plus a duplicated patch: found without an O(F^2) pass
    m = trimesh.creation.icosphere(subdivisions=5)
    v = np.asarray(m.vertices)[np.asarray(m.faces)]
    corners = np.concatenate([v, v[:, 2:3]], 1)
    normals = np.asarray(m.face_normals)
    pairs = overlapping_pairs(np.concatenate([corners, corners[:7]]), np.concatenate([normals, normals[:7]]))
    F = len(corners)
    assert pairs.tolist() == [[k, F + k] for k in range(7)]


def _bowl():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    keep = sphere.triangles_center[:, 2] < 0.3
    return trimesh.Trimesh(sphere.vertices, sphere.faces[keep]), sphere


def test_bowl_with_outward_normals_warns_and_inside_reflects():
    bowl, sphere = _bowl()
    outside = ti.Scene.from_trimesh(bowl, dtype=F64)  # trimesh's normals point out of the sphere: today's default
    with pytest.warns(GeometryWarning, match="side='inside'"):
        K = ti.form_factors(outside)
    assert K.nnz == 0
    inside = ti.Scene.from_trimesh(bowl, dtype=F64, side="inside")
    torch.testing.assert_close(inside.normals, -outside.normals)
    rs = ti.form_factors(inside).row_sums()
    # inside a sphere F_ij = A_j / A_sphere: each row of the bowl sums to about its share of the sphere's area
    # (measured within 0.016 on this 56-triangle polyhedron)
    assert float((rs - bowl.area / sphere.area).abs().max()) < 0.05
    both = ti.Scene.from_trimesh(bowl, dtype=F64, side="both")
    assert both.num_facets == 2 * outside.num_facets
    torch.testing.assert_close(both.normals[outside.num_facets :], inside.normals)
    with pytest.raises(ValueError, match="side must be"):
        ti.Scene.from_trimesh(bowl, side="up")


def test_convex_box_seen_from_inside_is_closed_and_flat_scene_does_not_warn(recwarn):
    inside = ti.Scene.from_trimesh(trimesh.creation.box(), dtype=F64, side="inside")
    assert float((ti.form_factors(inside).row_sums() - 1).abs().max()) < 4e-6  # measured 1.3e-6 (closed)
    flat = ti.Scene.from_polygons(ti.scenes.grid_quads([0, 0, 0], [1, 0, 0], [0, 1, 0], 2, 2))
    assert ti.form_factors(flat).nnz == 0
    assert not [w for w in recwarn if issubclass(w.category, GeometryWarning)]
