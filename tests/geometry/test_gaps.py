"""Gaps between facets: the least distance between two convex facets against a dense sampling of both, and the
pairs that nearly touch (a wall hung above a floor) apart from those that touch or continue a contact."""

import pytest
import torch

import torch_interreflect as ti
from torch_interreflect.errors import ShapeError, ValueRangeError
from torch_interreflect.geometry.gaps import near_pairs, polygon_gaps

D = torch.float64
FLOOR = [[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]]


def _sampled_gap(a: torch.Tensor, b: torch.Tensor, n: int = 81) -> float:
    """The least distance between ``n²`` bilinear samples of each quad (an upper bound of the gap)."""
    u = torch.linspace(0, 1, n, dtype=D)
    U, V = (t.reshape(-1, 1) for t in torch.meshgrid(u, u, indexing="ij"))

    def points(c: torch.Tensor) -> torch.Tensor:
        return (1 - U) * (1 - V) * c[0] + U * (1 - V) * c[1] + U * V * c[2] + (1 - U) * V * c[3]

    return float(torch.cdist(points(a), points(b)).min())


def _normal(c: torch.Tensor) -> torch.Tensor:
    n = torch.linalg.cross(c[2] - c[0], c[3] - c[1], dim=-1)
    return n / n.norm()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gaps_of_known_pairs(dtype):
    """Parallel squares 0.2 apart (face to face, the gap between two interiors), a wall hung 5 cm above a floor (an
    edge over a face), and a square beside another in its plane (edge to edge, 0.1)."""
    sq = torch.tensor(FLOOR, dtype=D)
    pairs = [
        (sq, (sq + torch.tensor([0.1, 0.2, 0.2], dtype=D)).flip(0), 0.2),
        (sq, torch.tensor([[0.3, -2, 0.05], [0.3, 2, 0.05], [0.3, 2, 3], [0.3, -2, 3]], dtype=D), 0.05),
        (sq, sq + torch.tensor([1.1, 0, 0], dtype=D), 0.1),
    ]
    a = torch.stack([p[0] for p in pairs]).to(dtype)
    b = torch.stack([p[1] for p in pairs]).to(dtype)
    na, nb = torch.stack([_normal(x) for x in a]), torch.stack([_normal(x) for x in b])
    got = polygon_gaps(a, b, na, nb)
    assert got.shape == (3,) and got.dtype == dtype
    for k, (_, _, exact) in enumerate(pairs):
        assert float(got[k]) == pytest.approx(exact, abs=1e-12 if dtype == torch.float64 else 1e-6), k


def test_triangles_and_crossing_facets():
    """A triangle (its last corner repeated) 0.3 above a square, over its interior and beside it; a square through
    another (gap 0); a vertical square whose bottom edge runs 0.1 under a floor's edge, through no interior."""
    sq = torch.tensor(FLOOR, dtype=D)
    tri = torch.tensor([[-0.2, -0.2, 0.3], [0.2, -0.2, 0.3], [0.0, 0.2, 0.3], [0.0, 0.2, 0.3]], dtype=D)
    through = torch.tensor([[0.0, -1.0, -0.5], [0.0, 1.0, -0.5], [0.0, 1.0, 0.5], [0.0, -1.0, 0.5]], dtype=D)
    below = torch.tensor([[0.5, -1.0, -0.1], [0.5, 1.0, -0.1], [0.5, 1.0, -1.0], [0.5, -1.0, -1.0]], dtype=D)
    a = torch.stack([sq, sq, sq, sq])
    b = torch.stack([tri, tri + torch.tensor([1.0, 0, 0], dtype=D), through, below])
    got = polygon_gaps(a, b, torch.stack([_normal(x) for x in a]), torch.stack([_normal(x) for x in b]))
    torch.testing.assert_close(got, torch.tensor([0.3, (0.3**2 + 0.3**2) ** 0.5, 0.0, 0.1], dtype=D))


def test_gaps_against_dense_sampling():
    """Random rectangles placed apart: the gap is at most the sampled least distance, and within the sampling's
    spacing of it."""
    gen = torch.Generator().manual_seed(3)
    quads = []
    for _ in range(60):
        o, e1, e2 = (torch.randn(3, generator=gen, dtype=D) for _ in range(3))
        e2 = e2 - (e2 @ e1) / (e1 @ e1) * e1
        quads.append(torch.stack([o, o + e1, o + e1 + e2, o + e2]))
    a = torch.stack(quads[:30])
    b = torch.stack(quads[30:]) + 4.0 * torch.randn(30, 1, 3, generator=gen, dtype=D)
    got = polygon_gaps(a, b, torch.stack([_normal(x) for x in a]), torch.stack([_normal(x) for x in b]))
    sampled = torch.tensor([_sampled_gap(x, y) for x, y in zip(a, b, strict=True)], dtype=D)
    far = sampled > 0.2  # pairs that cross are not this function's (their gap is not 0)
    assert int(far.sum()) >= 20
    assert bool((got[far] <= sampled[far] + 1e-9).all())
    spacing = torch.stack([torch.maximum(x[1:].sub(x[0]).norm(dim=-1).max(), y[1:].sub(y[0]).norm(dim=-1).max())
                           for x, y in zip(a, b, strict=True)]) / 80
    assert bool((sampled[far] - got[far] <= spacing[far]).all())


def test_near_pairs_find_a_hung_wall_not_touching_facets():
    """A wall hung 5 cm above a floor is near it (both orders); a groove's facets touch along its hinge, and a block
    standing on one floor tile beside another has its foot in that tile's plane (a contact continued): neither is
    near."""
    wall = [[0.3, -2.0, 0.05], [0.3, 2.0, 0.05], [0.3, 2.0, 3.0], [0.3, -2.0, 3.0]]
    i, j, gap = near_pairs(ti.Scene.from_polygons(torch.tensor([FLOOR, wall], dtype=D)), 0.1)
    assert i.tolist() == [0, 1] and j.tolist() == [1, 0]
    torch.testing.assert_close(gap, torch.full((2,), 0.05, dtype=D))
    assert near_pairs(ti.Scene.from_polygons(torch.tensor([FLOOR, wall], dtype=D)), 0.005)[0].numel() == 0
    assert near_pairs(ti.scenes.v_groove(30.0, divisions=3, dtype=D), 0.1)[0].numel() == 0
    tile = [[0.5, -0.5, 0.0], [1.5, -0.5, 0.0], [1.5, 0.5, 0.0], [0.5, 0.5, 0.0]]
    side = [[0.45, -0.4, 0.0], [0.45, 0.4, 0.0], [0.45, 0.4, 0.5], [0.45, -0.4, 0.5]]  # faces +x, 5 cm from the tile
    assert near_pairs(ti.Scene.from_polygons(torch.tensor([FLOOR, tile, side], dtype=D)), 0.1)[0].numel() == 0


def test_bad_input_says_what_was_expected():
    sq = torch.tensor([FLOOR], dtype=D)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=D)
    with pytest.raises(ShapeError, match=r"\[P, 4, 3\]"):
        polygon_gaps(sq[:, :3], sq[:, :3], n, n)
    with pytest.raises(ShapeError, match=r"normals \[P, 3\]"):
        polygon_gaps(sq, sq, n[0], n[0])
    scene = ti.Scene.from_polygons(torch.tensor([FLOOR], dtype=D))
    for bad in (0.0, -0.1, float("nan"), "0.1"):
        with pytest.raises(ValueRangeError, match="ratio"):
            near_pairs(scene, bad)
