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
