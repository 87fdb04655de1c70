"""The openings of a scene (:func:`torch_interreflect.geometry.openings.openings`): the uncovered faces of its hull."""

from __future__ import annotations

import math

import torch

import torch_interreflect as ti
from torch_interreflect.geometry.openings import openings


def test_the_cornell_box_opens_at_its_front_only():
    o = openings(ti.scenes.cornell_box(light=False, dtype=torch.float64))
    assert o.num_facets == 1
    assert o.normals[0].tolist() == [0.0, 0.0, 1.0]  # into the box
    # the published front edges: floor 552.8 mm wide, ceiling 556 mm, 548.8 mm apart: a trapezoid
    assert abs(float(o.areas[0]) - 0.5 * (0.5528 + 0.556) * 0.5488) < 1e-12
    assert float(o.corners[0, :, 2].abs().max()) == 0.0


def test_a_v_groove_opens_at_its_top_and_both_ends():
    angle, (length, width) = 30.0, (0.09, 0.06)
    o = openings(ti.scenes.v_groove(angle, size=(length, width), divisions=3, dtype=torch.float64))
    half = math.radians(angle / 2)
    top = 2 * width * math.sin(half) * length
    end = 0.5 * width * width * math.sin(math.radians(angle))
    assert o.num_facets == 3
    assert torch.allclose(o.areas.sort().values, torch.tensor(sorted([top, end, end]), dtype=torch.float64),
                          rtol=1e-12, atol=0)
    # every opening faces into the groove: its normal points at the plates' centre
    centre = ti.scenes.v_groove(angle, size=(length, width), divisions=3, dtype=torch.float64).centroids.mean(0)
    assert bool((((centre - o.centroids) * o.normals).sum(1) > 0).all())


def test_no_openings_where_none_can_be_told():
    assert openings(ti.scenes.closed_box(dtype=torch.float64)) is None  # closed
    assert openings(ti.scenes.w_shape(dtype=torch.float64)) is None  # two plates meet along the floor's edges
    floor = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    half_wall = [[0.0, 0, 0], [0, 0.5, 0], [0, 0.5, 1], [0, 0, 1]]  # covers half of the hull's face x = 0
    assert openings(ti.Scene.from_polygons(torch.tensor([floor, half_wall], dtype=torch.float64))) is None


def test_facing_out_marks_the_back_of_a_cabinet_against_a_wall():
    """The open room: the cabinet's back stands on the wall x = 4 and faces out of the room; nothing else does."""
    from torch_interreflect.geometry.openings import facing_out

    room = ti.scenes.room(1.0, lamp=False, ceiling=False, dtype=torch.float64)
    out = facing_out(room)
    assert int(out.sum()) >= 1
    x_axis = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(room.normals[out], x_axis.expand(int(out.sum()), 3), atol=1e-12)
    assert torch.allclose(room.centroids[out][:, 0], torch.full((int(out.sum()),), 4.0, dtype=torch.float64))
    names = [room.material_names[int(m)] for m in room.material[out]]
    assert set(names) == {"cabinet"}
    assert not bool(facing_out(ti.scenes.v_groove(30.0, dtype=torch.float64)).any())


def test_a_two_sided_panel_covers_its_part_of_a_hull_face_once():
    """A panel of two facets back to back over half of the hull's face x = 0: the face is half covered (the two
    sides do not add up to a whole face), so the openings cannot be told."""
    floor = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    front = [[0.0, 0, 0], [0, 0.5, 0], [0, 0.5, 1], [0, 0, 1]]
    back = front[::-1]
    scene = ti.Scene.from_polygons(torch.tensor([floor, front, back], dtype=torch.float64))
    assert openings(scene) is None


def test_a_float32_scene_has_the_openings_of_the_float64_one():
    """A V-groove turned about an oblique axis (its plates slanted in every coordinate), float32 against float64:
    the corners' rounding stays within the tolerance of a hull face (:data:`ON_FACE`)."""
    groove = ti.scenes.v_groove(40.0, divisions=4, dtype=torch.float64)
    axis = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) / 14**0.5
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    rot = torch.linalg.matrix_exp(0.7 * k)
    turned = ti.Scene.from_polygons(groove.corners @ rot.T)
    o64 = openings(turned)
    o32 = openings(turned.to(torch.float32))
    assert o64 is not None and o32 is not None and o64.num_facets == o32.num_facets == 3
    assert torch.allclose(o32.areas.double().sort().values, o64.areas.sort().values, rtol=1e-5, atol=0)
