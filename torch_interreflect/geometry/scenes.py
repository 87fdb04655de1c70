"""Built-in scenes: the V-groove and W shape of Deeb et al. (2017), folds, box corner, closed box, Cornell box.

All sizes are in metres. Every builder returns a :class:`~torch_interreflect.Scene` whose
``material`` index names its parts (``scene.material_names``), with facets ordered part by part.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .scene import Scene

__all__ = ["box_corner", "closed_box", "cornell_box", "fold", "grid_quads", "room", "v_groove", "w_shape"]


def _pair(x: int | Sequence[int], name: str) -> tuple[int, int]:
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        t = (int(x), int(x))
    else:
        t = tuple(int(v) for v in x)  # type: ignore[union-attr]
        if len(t) != 2:
            raise ValueError(f"{name} must be an int or a pair of ints; got {x!r}")
    if min(t) < 1:
        raise ValueError(f"{name} must be >= 1; got {x!r}")
    return t  # type: ignore[return-value]


def grid_quads(origin: Sequence[float], a: Sequence[float], b: Sequence[float], na: int, nb: int) -> np.ndarray:
    """Split the parallelogram ``origin + s a + t b`` (s, t in [0, 1]) into ``na × nb`` quads.

    The quads are ordered with ``s`` (along ``a``) as the slow index; their normal is ``a × b``.

    Returns:
        Corners ``[na * nb, 4, 3]`` (float64 numpy array).
    """
    o, a_, b_ = (np.asarray(v, dtype=np.float64) for v in (origin, a, b))
    s = np.arange(na + 1)[:, None] / na
    t = np.arange(nb + 1)[None, :] / nb
    p = o + s[..., None] * a_ + t[..., None] * b_  # [na+1, nb+1, 3]
    q = np.stack([p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]], axis=2)  # [na, nb, 4, 3]
    return q.reshape(-1, 4, 3)


def _grid_quads_t(origin: Tensor, a: Tensor, b: Tensor, na: int, nb: int) -> Tensor:
    """:func:`grid_quads` on tensors (float64 ``[3]`` each): differentiable in ``origin``, ``a`` and ``b``."""
    s = torch.arange(na + 1, dtype=a.dtype)[:, None, None] / na
    t = torch.arange(nb + 1, dtype=a.dtype)[None, :, None] / nb
    p = origin + s * a + t * b  # [na+1, nb+1, 3]
    q = torch.stack([p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]], dim=2)  # [na, nb, 4, 3]
    return q.reshape(-1, 4, 3)


def _param(x: float | Tensor, name: str) -> Tensor:
    """A scalar parameter as a float64 tensor that keeps its graph (a Python number, or a 0-d/1-element tensor)."""
    t = x if isinstance(x, Tensor) else torch.as_tensor(float(x), dtype=torch.float64)
    if t.numel() != 1:
        raise ValueError(f"{name} must be a number or a one-element floating tensor; got shape {list(t.shape)}")
    return t.reshape(()).to(torch.float64)


def _param_dtype(dtype: torch.dtype | None, *params: object) -> torch.dtype:
    """``dtype``, else that of the first floating tensor parameter, else torch's default dtype."""
    if dtype is not None:
        return dtype
    for p in params:
        if isinstance(p, Tensor) and p.is_floating_point():
            return p.dtype
    return torch.get_default_dtype()


def _build(parts: list[tuple[str, np.ndarray | Tensor]], dtype: torch.dtype | None) -> Scene:
    dt = dtype or torch.get_default_dtype()
    corners = torch.cat([torch.as_tensor(c, dtype=torch.float64) for _, c in parts]).to(dt)
    material = np.concatenate([np.full(len(c), k) for k, (_, c) in enumerate(parts)])
    return Scene.from_polygons(corners, material=material, material_names=[n for n, _ in parts])


def v_groove(
    angle_deg: float | Tensor,
    size: tuple[float, float] = (0.09, 0.06),
    divisions: int | Sequence[int] = 10,
    *,
    dtype: torch.dtype | None = None,
) -> Scene:
    """Two plates sharing an edge (the hinge) with interior angle ``angle_deg``, as in the paper's §6.

    The hinge runs along ``+y`` from the origin. Plate A lies in ``z = 0`` (``x >= 0``, normal ``+z``); plate
    B leaves the hinge in direction ``(cos φ, 0, sin φ)`` with its normal into the groove.

    **Differentiable geometry.** ``angle_deg`` (and either entry of ``size``) may be a tensor that requires grad:
    the corners are built with torch operations, so ``scene.corners`` keeps the graph and form factors, light and
    images computed from the scene pass gradients back to it (``d E / d angle``: see
    :func:`torch_interreflect.form_factors`).

    Args:
        angle_deg: Interior angle φ between the plates in degrees, in (0, 180); a number or a one-element tensor.
        size: ``(length along the hinge, width away from the hinge)`` of each plate in metres (the paper's
            9 cm × 6 cm by default); numbers or one-element tensors.
        divisions: Facets ``(along the hinge, across)`` per plate, or one int for both (paper: 10 × 10).
        dtype: Floating dtype (default: that of a tensor ``angle_deg``, else torch's default).

    Returns:
        A scene with ``2 * n_along * n_across`` quads. Facet ``p * n_across * n_along + c * n_along + r`` is on
        plate ``p`` (material 0 = "plate_a", 1 = "plate_b"), column ``c`` (0 nearest the hinge), row ``r``.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> ti.scenes.v_groove(45.0).num_facets
        200
        >>> angle = torch.tensor(45.0, dtype=torch.float64, requires_grad=True)
        >>> ti.scenes.v_groove(angle, divisions=2).corners.requires_grad
        True
    """
    phi_deg = _param(angle_deg, "angle_deg")
    if not 0.0 < float(phi_deg.detach()) < 180.0:
        raise ValueError(f"angle_deg must lie in (0, 180); got {float(phi_deg.detach())}")
    length, width = (_param(v, "size") for v in size)
    if float(length.detach()) <= 0 or float(width.detach()) <= 0:
        raise ValueError(f"size must be positive (length, width); got {[float(v.detach()) for v in (length, width)]}")
    n_along, n_across = _pair(divisions, "divisions")
    phi = torch.deg2rad(phi_deg)
    zero = torch.zeros((), dtype=torch.float64)
    d = torch.stack([torch.cos(phi), zero, torch.sin(phi)])
    y = torch.stack([zero, length, zero])
    ex = torch.stack([width, zero, zero])
    origin = torch.zeros(3, dtype=torch.float64)
    # plate A: columns along +x (slow index), rows along y; normal x × y = +z
    plate_a = _grid_quads_t(origin, ex, y, n_across, n_along)
    # plate B: slow index along d; normal must be y × d (into the groove), so reverse the corner order
    plate_b = _grid_quads_t(origin, width * d, y, n_across, n_along).flip(1)
    return _build([("plate_a", plate_a), ("plate_b", plate_b)], _param_dtype(dtype, angle_deg, *size))


def box_corner(
    size: float | Tensor = 1.0, divisions: int | Sequence[int] = 4, *, dtype: torch.dtype | None = None
) -> Scene:
    """Three mutually perpendicular squares meeting at the origin (a room corner), normals inward.

    Args:
        size: Edge length of each square in metres (a number, or a one-element tensor whose graph the corners
            keep).
        divisions: Facets per edge (one int, or a pair for the two directions of each square).
        dtype: Floating dtype (default: that of a tensor ``size``, else torch's default).

    Returns:
        A scene with materials ``floor`` (z = 0), ``wall_x`` (x = 0) and ``wall_y`` (y = 0).
    """
    n1, n2 = _pair(divisions, "divisions")
    ex, ey, ez = torch.eye(3, dtype=torch.float64) * _param(size, "size")
    o = torch.zeros(3, dtype=torch.float64)
    parts = [
        ("floor", _grid_quads_t(o, ex, ey, n1, n2)),
        ("wall_x", _grid_quads_t(o, ey, ez, n1, n2)),
        ("wall_y", _grid_quads_t(o, ez, ex, n1, n2)),
    ]
    return _build(parts, _param_dtype(dtype, size))


def closed_box(
    size: float | Sequence[float] | Tensor = 1.0, divisions: int = 3, *, dtype: torch.dtype | None = None
) -> Scene:
    """The six inner faces of a rectangular box, normals pointing inward (a closed enclosure).

    Args:
        size: Edge lengths ``(sx, sy, sz)`` in metres, or one number for a cube; numbers or a tensor (``[3]`` or
            one element) whose graph the corners keep.
        divisions: Facets per edge of each face.
        dtype: Floating dtype (default: that of a tensor ``size``, else torch's default).

    Returns:
        A scene with ``6 * divisions²`` quads, materials ``bottom, top, y0, y1, x0, x1``.
    """
    if isinstance(size, Tensor) and size.numel() == 3:
        sx, sy, sz = size.reshape(3).to(torch.float64).unbind()
    elif isinstance(size, Tensor) or np.isscalar(size):
        sx = sy = sz = _param(size, "size")  # type: ignore[arg-type]
    else:
        sx, sy, sz = (_param(v, "size") for v in size)  # type: ignore[union-attr]
    n = int(divisions)
    if n < 1:
        raise ValueError(f"divisions must be >= 1; got {divisions}")
    ex, ey, ez = torch.diag(torch.stack([sx, sy, sz]))
    o = torch.zeros(3, dtype=torch.float64)
    parts = [
        ("bottom", _grid_quads_t(o, ex, ey, n, n)),
        ("top", _grid_quads_t(ez, ey, ex, n, n)),
        ("y0", _grid_quads_t(o, ez, ex, n, n)),
        ("y1", _grid_quads_t(ey, ex, ez, n, n)),
        ("x0", _grid_quads_t(o, ey, ez, n, n)),
        ("x1", _grid_quads_t(ex, ez, ey, n, n)),
    ]
    return _build(parts, _param_dtype(dtype, size))


def fold(
    profile: Tensor | Sequence[Sequence[float]],
    length: float | Tensor = 0.1,
    divisions: int | Sequence[int] = 10,
    *,
    names: Sequence[str] | None = None,
    dtype: torch.dtype | None = None,
) -> Scene:
    """A folded sheet: the polyline ``profile`` in the xz-plane swept ``length`` along ``+y`` (V-grooves, W folds,
    corrugations).

    Plate ``k`` joins profile points ``k`` and ``k + 1``; its normal is the profile's direction rotated by +90° in
    the xz-plane (to the left when walking along the profile with ``+z`` up and ``+x`` right: a profile going down
    then up reflects on the upper side). ``profile`` may be a tensor that requires grad (fold heights, widths):
    the corners keep its graph.

    Args:
        profile: Points ``(x, z)`` in metres. Shape ``[K + 1, 2]`` for ``K`` plates.
        length: Extent along ``+y`` in metres (a number or a one-element tensor).
        divisions: ``(along, across)`` facets per plate, ``across`` one int for all plates or one per plate; or
            one int for both.
        names: Material name of each plate (default ``plate_0, plate_1, ...``).
        dtype: Floating dtype (default: that of a tensor ``profile``, else torch's default).

    Returns:
        A scene with one material per plate, plates in profile order, each ``across`` columns (slow index, from
        point ``k``) of ``along`` rows.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> h = torch.tensor([0.05, 0.03, 0.05], dtype=torch.float64, requires_grad=True)
        >>> zero = torch.zeros(1, dtype=torch.float64)
        >>> z = torch.stack([h[0], zero[0], h[1], zero[0], h[2]])
        >>> x = torch.tensor([0.0, 0.03, 0.05, 0.07, 0.1], dtype=torch.float64)
        >>> w = ti.scenes.fold(torch.stack([x, z], dim=1), divisions=(2, 3))
        >>> w.num_facets, w.corners.requires_grad
        (24, True)
    """
    prof = profile if isinstance(profile, Tensor) else torch.as_tensor(np.asarray(profile, dtype=np.float64))
    if prof.ndim != 2 or prof.shape[0] < 2 or prof.shape[1] != 2:
        raise ValueError(f"profile must be (x, z) points of shape [K + 1, 2] with K >= 1; got {list(prof.shape)}")
    prof = prof.to(torch.float64)
    k = prof.shape[0] - 1
    if isinstance(divisions, (int, np.integer)):
        n_along, across = int(divisions), [int(divisions)] * k
    else:
        n_along, rest = int(divisions[0]), list(divisions[1:])
        across = [int(v) for v in rest] * (k if len(rest) == 1 else 1)
    if len(across) != k or min([*across, n_along]) < 1:
        raise ValueError(f"divisions must be an int or (along, across) / (along, *across per plate) ints >= 1 for "
                         f"{k} plates; got {divisions!r}")
    names = list(names) if names is not None else [f"plate_{i}" for i in range(k)]
    if len(names) != k:
        raise ValueError(f"names must name each of the {k} plates; got {len(names)}")
    zero = torch.zeros((), dtype=torch.float64)
    y = torch.stack([zero, _param(length, "length"), zero])
    pts = torch.stack([prof[:, 0], torch.zeros_like(prof[:, 0]), prof[:, 1]], dim=1)  # [K + 1, 3]
    parts = [(names[i], _grid_quads_t(pts[i], pts[i + 1] - pts[i], y, across[i], n_along)) for i in range(k)]
    return _build(parts, _param_dtype(dtype, profile, length))


def w_shape(
    valley_angle_deg: float | Tensor = 45.0,
    outer: float | Tensor = 0.08,
    inner: float | Tensor = 0.04,
    length: float | Tensor = 0.10,
    divisions: Sequence[int] = (10, 20, 10),
    *,
    dtype: torch.dtype | None = None,
) -> Scene:
    """The paper's W shape: four plates, two deep outer ones and two shallower inner ones (§6.3, Fig. 10).

    The profile lies in the xz-plane and is swept ``length`` along ``+y``: outer-left, inner-left,
    inner-right, outer-right plates, with valleys of ``valley_angle_deg`` and a central ridge lower than the
    outer tops, so the ridge hides part of each outer plate from the other (occlusion). Any parameter may be a
    one-element tensor that requires grad (the corners keep its graph); :func:`fold` builds other profiles.

    Args:
        valley_angle_deg: Interior angle at both valleys, degrees.
        outer: Width of the outer plates (m), the paper's 8 cm.
        inner: Width of the inner plates (m).
        length: Extent along the valleys (m), the paper's 10 cm.
        divisions: ``(along, outer across, inner across)`` facets per plate (paper: 10, 20, 10).
        dtype: Floating dtype (default: that of a tensor parameter, else torch's default).

    Returns:
        A scene with materials ``outer_left, inner_left, inner_right, outer_right``.
    """
    angle = _param(valley_angle_deg, "valley_angle_deg")
    if not 0.0 < float(angle.detach()) < 180.0:
        raise ValueError(f"valley_angle_deg must lie in (0, 180); got {float(angle.detach())}")
    if len(divisions) != 3 or min(divisions) < 1:
        raise ValueError(f"divisions must be three ints >= 1 (along, outer, inner); got {divisions!r}")
    n_along, n_outer, n_inner = (int(v) for v in divisions)
    half = torch.deg2rad(90.0 - angle / 2.0)  # elevation of each plate at a symmetric valley
    c, s = torch.cos(half), torch.sin(half)
    wo, wi = _param(outer, "outer"), _param(inner, "inner")
    v1 = torch.zeros(2, dtype=torch.float64)
    p0 = v1 + wo * torch.stack([-c, s])
    ridge = v1 + wi * torch.stack([c, s])
    v2 = ridge + wi * torch.stack([c, -s])
    p4 = v2 + wo * torch.stack([c, s])
    return fold(
        torch.stack([p0, v1, ridge, v2, p4]),
        length,
        (n_along, n_outer, n_inner, n_inner, n_outer),
        names=["outer_left", "inner_left", "inner_right", "outer_right"],
        dtype=_param_dtype(dtype, valley_angle_deg, outer, inner, length),
    )


# The Cornell box as published by the Cornell Program of Computer Graphics (millimetres).
_CORNELL_MM: dict[str, list[list[list[float]]]] = {
    "floor": [[[552.8, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 559.2], [549.6, 0.0, 559.2]]],
    "ceiling": [[[556.0, 548.8, 0.0], [556.0, 548.8, 559.2], [0.0, 548.8, 559.2], [0.0, 548.8, 0.0]]],
    "back_wall": [[[549.6, 0.0, 559.2], [0.0, 0.0, 559.2], [0.0, 548.8, 559.2], [556.0, 548.8, 559.2]]],
    "green_wall": [[[0.0, 0.0, 559.2], [0.0, 0.0, 0.0], [0.0, 548.8, 0.0], [0.0, 548.8, 559.2]]],
    "red_wall": [[[552.8, 0.0, 0.0], [549.6, 0.0, 559.2], [556.0, 548.8, 559.2], [556.0, 548.8, 0.0]]],
    "short_block": [
        [[130.0, 165.0, 65.0], [82.0, 165.0, 225.0], [240.0, 165.0, 272.0], [290.0, 165.0, 114.0]],
        [[290.0, 0.0, 114.0], [290.0, 165.0, 114.0], [240.0, 165.0, 272.0], [240.0, 0.0, 272.0]],
        [[130.0, 0.0, 65.0], [130.0, 165.0, 65.0], [290.0, 165.0, 114.0], [290.0, 0.0, 114.0]],
        [[82.0, 0.0, 225.0], [82.0, 165.0, 225.0], [130.0, 165.0, 65.0], [130.0, 0.0, 65.0]],
        [[240.0, 0.0, 272.0], [240.0, 165.0, 272.0], [82.0, 165.0, 225.0], [82.0, 0.0, 225.0]],
    ],
    "tall_block": [
        [[423.0, 330.0, 247.0], [265.0, 330.0, 296.0], [314.0, 330.0, 456.0], [472.0, 330.0, 406.0]],
        [[423.0, 0.0, 247.0], [423.0, 330.0, 247.0], [472.0, 330.0, 406.0], [472.0, 0.0, 406.0]],
        [[472.0, 0.0, 406.0], [472.0, 330.0, 406.0], [314.0, 330.0, 456.0], [314.0, 0.0, 456.0]],
        [[314.0, 0.0, 456.0], [314.0, 330.0, 456.0], [265.0, 330.0, 296.0], [265.0, 0.0, 296.0]],
        [[265.0, 0.0, 296.0], [265.0, 330.0, 296.0], [423.0, 330.0, 247.0], [423.0, 0.0, 247.0]],
    ],
    # the light, 0.5 mm below the ceiling so the two do not overlap
    "light": [[[343.0, 548.3, 227.0], [343.0, 548.3, 332.0], [213.0, 548.3, 332.0], [213.0, 548.3, 227.0]]],
}
_CORNELL_CENTRE = np.array([278.0, 274.4, 279.6])


def _orient(quad: np.ndarray, towards: np.ndarray, inward: bool) -> np.ndarray:
    n = np.cross(quad[2] - quad[0], quad[3] - quad[1])
    c = quad.mean(0)
    facing = float(np.dot(n, towards - c)) > 0
    return quad if facing == inward else quad[::-1].copy()


def _planar(quad: np.ndarray, rtol: float = 1e-6) -> bool:
    n = np.cross(quad[2] - quad[0], quad[3] - quad[1])
    n = n / np.linalg.norm(n)
    dev = np.abs((quad - quad.mean(0)) @ n).max()
    return bool(dev <= rtol * np.linalg.norm(quad - quad.mean(0), axis=1).max())


def cornell_box(
    divisions: int = 1, *, light: bool = True, scale: float = 1e-3, dtype: torch.dtype | None = None
) -> Scene:
    """The published Cornell box (walls, ceiling, floor and its two blocks), normals toward the air.

    Coordinates are the Cornell Program of Computer Graphics measurements in millimetres times ``scale``
    (metres by default). The red wall of the published data is slightly non-planar; it is split into two
    triangles so every facet stays planar. With ``light=True`` the ceiling light is a facet 0.5 mm below the
    ceiling, facing down.

    Args:
        divisions: Each published quad is split into ``divisions × divisions`` quads (triangles into
            ``divisions²`` triangles).
        light: Include the light facet (material ``light``).
        scale: Metres per published unit (millimetres).

    Returns:
        A scene with materials ``floor, ceiling, back_wall, green_wall, red_wall, short_block, tall_block``
        and ``light``.
    """
    if int(divisions) < 1:
        raise ValueError(f"divisions must be >= 1; got {divisions}")
    scenes = []
    names = []
    for name, quads in _CORNELL_MM.items():
        if name == "light" and not light:
            continue
        polys_q, polys_t = [], []
        for q in quads:
            q = np.asarray(q, dtype=np.float64)
            if name.endswith("block"):
                centre = np.mean(np.asarray(quads).reshape(-1, 3), axis=0)
                q = _orient(q, centre, inward=False)
            else:
                q = _orient(q, _CORNELL_CENTRE, inward=True)
            if _planar(q):
                polys_q.append(q)
            else:
                polys_t += [q[[0, 1, 2]], q[[0, 2, 3]]]
        dt = dtype or torch.get_default_dtype()
        for polys in (polys_q, polys_t):
            if polys:
                s = Scene.from_polygons(torch.as_tensor(np.array(polys) * scale, dtype=dt))
                if divisions > 1:
                    s, _ = s.subdivide(int(divisions))
                scenes.append(s)
                names.append(name)
    joined = Scene.concatenate(scenes)
    # one material per published part, even where it was split into quads and triangles
    uniq = list(dict.fromkeys(names))
    remap = torch.tensor([uniq.index(n) for n in names])
    return Scene.from_parts(joined.corners, joined.is_triangle, remap[joined.material], uniq)


def _box_faces(extents: Sequence[float], centre: Sequence[float], inward: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    """The six faces of a ``trimesh.creation.box`` as ``(corners [4, 3] counter-clockwise about n, n)``."""
    import trimesh

    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(np.asarray(centre, dtype=np.float64))
    out = []
    for tris, normal in zip(mesh.facets, mesh.facets_normal, strict=True):
        pts = np.unique(mesh.vertices[mesh.faces[tris].reshape(-1)], axis=0)  # the face's 4 corners
        n = -normal if inward else normal
        c = pts.mean(0)
        t1 = pts[0] - c
        t2 = np.cross(n, t1)
        order = np.argsort(np.arctan2((pts - c) @ t2, (pts - c) @ t1))
        out.append((pts[order], n))
    return out


def room(
    divisions: float = 4.0,
    size: Sequence[float] = (4.0, 5.0, 2.6),
    *,
    lamp: bool = True,
    ceiling: bool = True,
    dtype: torch.dtype | None = None,
) -> Scene:
    """An indoor-like room built from ``trimesh.creation.box`` primitives, for large-scene tests.

    The room shell (floor, ceiling, four walls, seen from inside) holds a table (top and four legs), a cabinet
    against a wall, a box on the table and, with ``lamp=True``, a ceiling lamp panel 1 cm below the ceiling,
    facing down. Every box face is split into quads of about ``1 / divisions`` metres; faces resting on the floor
    or on another box (leg tops, box and cabinet bottoms) are left out. With its ceiling the room is closed, so a
    sky light sees nothing: light it with the lamp (an area light, material ``"lamp"``). Without it
    (``ceiling=False``, a courtyard, usually with ``lamp=False``: the panel would hang under no ceiling) light it
    with the sky.

    Args:
        divisions: Facets per metre along each face edge (at least one facet per edge): about
            ``98·divisions²`` facets for the default size (4 → 1,596, 15 → 22,171, 23 → ~51,600).
        size: Room extents ``(x, y, z)`` in metres (z up).
        lamp: Include the lamp panel.
        ceiling: Include the ceiling; without it the room is open at the top (and has no ``ceiling`` material).
        dtype: Floating dtype.

    Returns:
        A scene with materials ``floor, ceiling, walls, table, cabinet, box`` (and ``lamp``); without the ceiling
        ``floor, walls, table, cabinet, box`` (the indices after ``floor`` move down by one).

    Example:
        >>> import torch_interreflect as ti
        >>> s = ti.scenes.room(divisions=2)
        >>> s.num_facets, s.material_names[:3]
        (410, ['floor', 'ceiling', 'walls'])
    """
    if not (isinstance(divisions, (int, float)) and not isinstance(divisions, bool) and divisions > 0):
        raise ValueError(f"divisions must be a positive number (facets per metre); got {divisions!r}")
    if not isinstance(ceiling, bool):
        raise TypeError(f"ceiling must be True or False; got {ceiling!r}")
    sx, sy, sz = (float(v) for v in size)
    if min(sx, sy, sz) <= 0:
        raise ValueError(f"size must be three positive extents in metres; got {size!r}")
    res = float(divisions)
    tx, ty, th = 0.45 * sx, 0.5 * sy, 0.75  # table centre and height
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("floor", "ceiling", "walls", "table", "cabinet", "box",
                                                          "lamp")}

    def add(name: str, extents: Sequence[float], centre: Sequence[float], inward: bool = False,
            drop: tuple[str, ...] = ()) -> None:
        for quad, n in _box_faces(extents, centre, inward):
            if ("bottom" in drop and n[2] < -0.5) or ("top" in drop and n[2] > 0.5):
                continue
            a, b = quad[1] - quad[0], quad[3] - quad[0]
            na = max(1, round(np.linalg.norm(a) * res))
            nb = max(1, round(np.linalg.norm(b) * res))
            q = grid_quads(quad[0], a, b, na, nb)
            shell_key = "floor" if n[2] > 0.5 else "ceiling" if n[2] < -0.5 else "walls"
            if name == "shell" and shell_key == "ceiling" and not ceiling:
                continue
            parts[shell_key if name == "shell" else name].append(q)

    add("shell", (sx, sy, sz), (sx / 2, sy / 2, sz / 2), inward=True)
    add("table", (1.6, 0.9, 0.05), (tx, ty, th - 0.025))
    for ex in (-0.7, 0.7):
        for ey in (-0.35, 0.35):
            add("table", (0.06, 0.06, th - 0.05), (tx + ex, ty + ey, (th - 0.05) / 2), drop=("bottom", "top"))
    add("cabinet", (0.5, 1.2, 1.8), (sx - 0.25, 0.25 * sy, 0.9), drop=("bottom",))
    add("box", (0.4, 0.3, 0.25), (tx + 0.3, ty - 0.1, th + 0.125), drop=("bottom",))
    if lamp:
        lamp_q = np.array([[sx / 2 - 0.3, sy / 2 - 0.3, sz - 0.01], [sx / 2 - 0.3, sy / 2 + 0.3, sz - 0.01],
                           [sx / 2 + 0.3, sy / 2 + 0.3, sz - 0.01], [sx / 2 + 0.3, sy / 2 - 0.3, sz - 0.01]])
        n = max(1, round(0.6 * res))
        parts["lamp"].append(grid_quads(lamp_q[0], lamp_q[1] - lamp_q[0], lamp_q[3] - lamp_q[0], n, n))
    built = [(k, np.concatenate(v)) for k, v in parts.items() if v]
    return _build(built, dtype)
