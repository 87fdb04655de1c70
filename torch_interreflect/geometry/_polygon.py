"""Polygon helpers shared by the form factors, the lights and the hierarchical kernel (internal).

Quads are stored as ``[..., 4, 3]`` corner arrays (a triangle repeats its last corner); every helper works on
batches of polygons in float64 or float32 and keeps autograd where the maths is differentiable.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._unique import unique_rows
from .scene import Scene

__all__ = [
    "bilinear",
    "clip_interval",
    "clip_polygons",
    "clip_segments",
    "compact_polygons",
    "facet_samples",
    "facing_any",
    "facing_matrix",
    "facing_others",
    "group_firsts",
    "plane_eps",
    "plane_groups",
    "plane_ids",
    "quad_coordinates",
    "rotate_to_plane_edge",
    "scene_size",
    "signed_distances",
    "tangent_frame",
]



def bilinear(corners: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Points ``[P, Q, 3]`` and area Jacobians ``[P, Q]`` of the bilinear map of quads ``[P, 4, 3]`` at unit-square
    coordinates ``u, v``: ``[Q]`` (one rule for every quad) or ``[P, Q]`` (points per quad)."""
    d0, d1, d2, d3 = (c[:, None, :] for c in corners.unbind(1))
    uu, vv = (u[..., None], v[..., None]) if u.ndim == 2 else (u[None, :, None], v[None, :, None])
    x = (1 - uu) * (1 - vv) * d0 + uu * (1 - vv) * d1 + uu * vv * d2 + (1 - uu) * vv * d3
    du = (1 - vv) * (d1 - d0) + vv * (d2 - d3)
    dv = (1 - uu) * (d3 - d0) + uu * (d2 - d1)
    jac = torch.linalg.cross(du, dv, dim=-1).norm(dim=-1)
    return x, jac


def bilinear_coordinates(quads: Tensor, points: Tensor, iterations: int = 12) -> Tensor:
    """Unit-square coordinates ``(u, v)`` ``[P, K, 2]`` of points ``[P, K, 3]`` lying on the planar quads
    ``[P, 4, 3]`` (triangles as quads with two equal corners): the inverse of :func:`bilinear`, by damped
    Gauss–Newton from the affine guess (exact for parallelograms after one step). Not differentiated."""
    c = quads.detach().to(torch.float64)
    p = points.detach().to(torch.float64)
    c0, c1, c2, c3 = (t[:, None, :] for t in c.unbind(1))
    e1, e2 = c1 - c0, c3 - c0
    a = torch.stack([e1.expand_as(p), torch.where((e2.norm(dim=-1, keepdim=True) > 0), e2, c2 - c0).expand_as(p)],
                    -1)
    uv = torch.linalg.lstsq(a, (p - c0)[..., None]).solution[..., 0].clamp(0.0, 1.0)
    for _ in range(iterations):
        u, v = uv[..., :1], uv[..., 1:]
        x = (1 - u) * (1 - v) * c0 + u * (1 - v) * c1 + u * v * c2 + (1 - u) * v * c3
        du = (1 - v) * (c1 - c0) + v * (c2 - c3)
        dv = (1 - u) * (c3 - c0) + u * (c2 - c1)
        jac = torch.stack([du, dv], -1)  # [P, K, 3, 2]
        jtj = jac.transpose(-1, -2) @ jac
        jtj = jtj + 1e-14 * jtj.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] * torch.eye(2, dtype=c.dtype)
        step = torch.linalg.solve(jtj, (jac.transpose(-1, -2) @ (p - x)[..., None]))[..., 0]
        uv = (uv + step).clamp(0.0, 1.0)
    return uv.to(quads.dtype)


def clip_polygons(poly: Tensor, point: Tensor, normal: Tensor, eps: float) -> Tensor:
    """Clip polygons ``[P, K, 3]`` to the half-space ``(y − point)·normal >= 0``.

    Returns ``[P, 2K, 3]``: the clipped polygon followed by copies of its first vertex (zero-length edges).
    Vertices within ``eps`` of the plane count as inside.
    """
    P, K, _ = poly.shape
    d = ((poly - point[:, None, :]) * normal[:, None, :]).sum(-1)  # [P, K]
    inside = d >= -eps
    nxt = torch.roll(poly, -1, dims=1)
    dn = torch.roll(d, -1, dims=1)
    inside_n = torch.roll(inside, -1, dims=1)
    cross = inside != inside_n
    t = torch.where(cross, d / torch.where(cross, d - dn, torch.ones_like(d)), torch.zeros_like(d))
    inter = poly + t[..., None] * (nxt - poly)
    slots = torch.stack([poly, inter], dim=2).reshape(P, 2 * K, 3)
    valid = torch.stack([inside, cross], dim=2).reshape(P, 2 * K)
    return compact_polygons(slots, valid)[0]


def tangent_frame(normals: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangents ``[F, 3]`` completing each unit normal to a right-handed orthonormal frame."""
    e = torch.eye(3, dtype=normals.dtype, device=normals.device)
    helper = torch.where(normals[:, :1].abs() < 0.9, e[0], e[1])
    t1 = torch.linalg.cross(normals, helper, dim=-1)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    return t1, torch.linalg.cross(normals, t1, dim=-1)


def signed_distances(points: Tensor, origin: Tensor, normal: Tensor) -> Tensor:
    """Signed distances ``[P, K]`` of points ``[P, K, 3]`` to the planes ``(origin [P, 3], normal [P, 3])``."""
    return ((points - origin[:, None, :]) * normal[:, None, :]).sum(-1)


def compact_polygons(poly: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
    """Move the kept corners of ``[P, K, 3]`` to the front (in order) and pad with corner 0; also the count."""
    K = poly.shape[1]
    key = (~keep).to(torch.int64) * K + torch.arange(K, device=poly.device)
    order = torch.argsort(key, dim=1)
    out = torch.gather(poly, 1, order[..., None].expand(-1, -1, 3))
    count = keep.sum(1)
    pad = torch.arange(K, device=poly.device)[None, :] >= count[:, None]
    return torch.where(pad[..., None], out[:, :1, :], out), count


def rotate_to_plane_edge(poly: Tensor, point: Tensor, normal: Tensor, eps: float) -> Tensor:
    """Rotate clipped polygons ``[P, K, 3]`` so that an edge lying on the clipping plane starts at corner 0."""
    K = poly.shape[1]
    poly, count = compact_polygons(poly, (poly - torch.roll(poly, -1, 1)).norm(dim=-1) > eps)
    count = count.clamp_min(1)
    ar = torch.arange(K)[None, :]
    real = ar < count[:, None]
    nxt = torch.gather(poly, 1, ((ar + 1) % count[:, None])[..., None].expand(-1, -1, 3))
    on = ((poly - point[:, None, :]) * normal[:, None, :]).sum(-1).abs() <= 4 * eps
    on_next = ((nxt - point[:, None, :]) * normal[:, None, :]).sum(-1).abs() <= 4 * eps
    edge = on & on_next & real
    start = torch.where(edge.any(1), torch.argmax(edge.to(torch.int8), dim=1), torch.zeros_like(count))
    idx = torch.where(real, (ar + start[:, None]) % count[:, None], start[:, None])
    return torch.gather(poly, 1, idx[..., None].expand(-1, -1, 3))


def facing_matrix(corners: Tensor, normals: Tensor, cent: Tensor, eps: float, chunk: int | None = None) -> Tensor:
    """``front[i, j]``: some corner of j lies strictly in front of i's plane. Boolean ``[F, F]``."""
    F = corners.shape[0]
    chunk = chunk or max(1, (1 << 22) // (4 * F))
    front = torch.empty(F, F, dtype=torch.bool, device=corners.device)
    pts = corners  # [F, 4, 3]
    for s in range(0, F, chunk):
        n = normals[s : s + chunk]  # [b, 3]
        c = cent[s : s + chunk]
        d = torch.einsum("bx,fkx->bfk", n, pts) - (n * c).sum(-1)[:, None, None]
        front[s : s + chunk] = (d > eps).any(-1)
    return front


def facing_others(scene: Scene) -> Tensor:
    """``facing_matrix`` of a scene (float64, CPU) with the diagonal cleared: ``[i, j]`` for facets j ≠ i only."""
    sc = scene.to(torch.float64).to("cpu")
    front = facing_matrix(sc.corners, sc.normals, sc.centroids, plane_eps(scene))
    return front.fill_diagonal_(False)


def facing_any(scene: Scene, *, one_way: bool = False, chunk: int | None = None) -> Tensor:
    """Per facet ``[F]`` bool: does some other facet lie (partly) in front of it, without an ``[F, F]`` matrix.

    ``facing_others(scene).any(1)``, or with ``one_way=True`` ``(front & ~front.T).any(1)`` (some facet in front of
    i that i is not in front of: i sees its back), computed in row blocks: memory ``O(chunk · F)``.
    """
    sc = scene.to(torch.float64).to("cpu")
    corners, normals, cent = sc.corners, sc.normals, sc.centroids
    eps = plane_eps(scene)
    F = corners.shape[0]
    chunk = chunk or max(1, (1 << 22) // (4 * F))
    out = torch.zeros(F, dtype=torch.bool)
    offs = (normals * cent).sum(-1)
    for s in range(0, F, chunk):
        rows = torch.arange(s, min(s + chunk, F))
        n, c = normals[rows], cent[rows]
        front = (torch.einsum("bx,fkx->bfk", n, corners) - (n * c).sum(-1)[:, None, None] > eps).any(-1)  # [b, F]
        front[torch.arange(rows.numel()), rows] = False
        if one_way:
            # front.T rows: some corner of facet i (in the block) in front of facet j's plane
            back = (torch.einsum("fx,bkx->bfk", normals, corners[rows]) - offs[None, :, None] > eps).any(-1)
            front &= ~back
        out[rows] = front.any(1)
    return out


def scene_size(scene: Scene) -> float:
    """Diagonal (m) of the bounding box of the scene's corners, in float64 (0 without facets)."""
    c = scene.corners.detach().reshape(-1, 3).double()
    return float((c.max(0).values - c.min(0).values).norm()) if c.numel() else 0.0


def plane_eps(scene: Scene) -> float:
    """Distance (m) under which a point counts as on a plane: float noise of the scene's own dtype."""
    return scene_size(scene) * max(1e-9, 16.0 * torch.finfo(scene.dtype).eps)


def group_firsts(group: Tensor) -> Tensor:
    """The first (lowest) index in each group of ``group [F]`` (ids ``0..G-1``, e.g. :func:`plane_ids`). Shape
    ``[G]``."""
    G = int(group.max()) + 1 if group.numel() else 0
    return torch.full((G,), group.numel(), dtype=torch.int64).scatter_reduce_(
        0, group, torch.arange(group.numel()), "amin"
    )


def plane_ids(sc: Scene, eps: float) -> Tensor:
    """The plane of each facet ``[F]`` int64: facets with equal ids are coplanar and face the same way.

    Normals and offsets are rounded well above the float noise of the scene's dtype (``eps``, e.g.
    :func:`plane_eps`); a boundary between two rounding cells only splits a plane into two ids.
    """
    corners, normals = sc.corners.detach(), sc.normals.detach()
    offs = (normals * sc.centroids.detach()).sum(-1)
    size = float((corners.reshape(-1, 3).max(0).values - corners.reshape(-1, 3).min(0).values).norm())  # own dtype
    res = max(1e-6, 100.0 * eps / max(size, 1e-300))
    key = torch.round(torch.cat([normals, offs[:, None] / max(size, 1e-300)], dim=1) / res)
    return unique_rows(key)[1]


def plane_groups(sc: Scene, eps: float, frames: bool = False) -> tuple[Tensor, ...] | None:
    """The planes of the scene's coplanar facet groups that could block anything: normal ``[G, 3]``, offset
    ``[G]`` and the group's bounding box ``lo, hi [G, 3]``; None when no plane has corners on both sides.

    With ``frames``, also in-plane axes ``e1, e2 [G, 3]`` (``e1`` along the first edge of the group's first facet,
    ``e2 = n × e1``), the group's bounding rectangle in them, ``(min e1·x, max e1·x, min e2·x, max e2·x)``
    ``[G, 4]`` (tight around the rectangular faces of a rotated box, where the axis-aligned box is not), and its
    thickness ``[G]``: the largest distance of a member's corner from the plane (members are grouped by rounded
    normals and offsets, so they may lie off the first member's plane by up to ~``1e-4`` of the scene's size)."""
    corners, normals, cent = sc.corners, sc.normals, sc.centroids
    offs = (normals * cent).sum(-1)
    plane_of = plane_ids(sc, eps)
    n_planes = int(plane_of.max()) + 1
    lo = corners.min(1).values
    hi = corners.max(1).values
    idx3 = plane_of[:, None].expand(-1, 3)
    plo = torch.full((n_planes, 3), math.inf, dtype=lo.dtype).scatter_reduce_(0, idx3, lo, "amin")
    phi = torch.full((n_planes, 3), -math.inf, dtype=hi.dtype).scatter_reduce_(0, idx3, hi, "amax")
    first = group_firsts(plane_of)
    pn, po = normals[first], offs[first]
    # a plane can only separate two facets if some corner of the scene lies strictly on each side of it
    dall = corners.reshape(-1, 3) @ pn.T - po[None, :]
    useful = (dall > eps).any(0) & (dall < -eps).any(0)
    if not bool(useful.any()):
        return None
    if not frames:
        return pn[useful], po[useful], plo[useful], phi[useful]
    edge = corners[first, 1] - corners[first, 0]
    e1 = edge - (edge * pn).sum(-1, keepdim=True) * pn
    e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    e2 = torch.cross(pn, e1, dim=-1)
    rect = []
    for axis in (e1, e2):
        along = (corners.reshape(-1, 4, 3) * axis[plane_of][:, None, :]).sum(-1)  # [F, 4]
        idx = plane_of[:, None].expand(-1, 4).reshape(-1)
        rect.append(torch.full((n_planes,), math.inf, dtype=along.dtype).scatter_reduce_(0, idx, along.reshape(-1),
                                                                                           "amin"))
        rect.append(torch.full((n_planes,), -math.inf, dtype=along.dtype).scatter_reduce_(0, idx, along.reshape(-1),
                                                                                            "amax"))
    box2 = torch.stack(rect, dim=1)
    off = ((corners.reshape(-1, 4, 3) * pn[plane_of][:, None, :]).sum(-1) - po[plane_of][:, None]).abs()  # [F, 4]
    thick = torch.zeros(n_planes, dtype=off.dtype).scatter_reduce_(0, plane_of, off.amax(1), "amax")
    return (pn[useful], po[useful], plo[useful], phi[useful], e1[useful], e2[useful], box2[useful],
            thick[useful])


def facet_samples(corners: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Midpoint-rule points ``[F, n², 3]`` and area weights ``[F, n²]`` on each facet."""
    g = (torch.arange(n, dtype=corners.dtype) + 0.5) / n
    u = g.repeat_interleave(n)
    v = g.repeat(n)
    x, jac = bilinear(corners, u, v)
    return x, jac / (n * n)


def clip_interval(lo: Tensor, hi: Tensor, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Intersect ``[lo, hi]`` with ``{s : a + s b >= 0}`` (broadcast)."""
    safe = torch.where(b == 0, torch.ones_like(b), b)
    root = -a / safe
    lo = torch.where(b > 0, torch.maximum(lo, root), lo)
    hi = torch.where(b < 0, torch.minimum(hi, root), hi)
    hi = torch.where((b == 0) & (a < 0), torch.full_like(hi, -1.0), hi)
    return lo, hi


def clip_segments(ya: Tensor, yb: Tensor, quads: Tensor, normals: Tensor) -> tuple[Tensor, Tensor]:
    """The part ``[λ_a, λ_b]`` of each segment ``ya + λ (yb − ya)`` (``[n, 3]``, in the quad's plane) inside the
    convex quad ``[n, 4, 3]`` with unit normal ``normals [n, 3]`` (empty where ``λ_b <= λ_a``)."""
    la, lb = torch.zeros_like(ya[:, 0]), torch.ones_like(ya[:, 0])
    for k in range(4):
        c0, c1 = quads[:, k], quads[:, (k + 1) % 4]
        inward = torch.linalg.cross(normals, c1 - c0, dim=-1)
        fa = ((ya - c0) * inward).sum(-1)
        la, lb = clip_interval(la, lb, fa, ((yb - c0) * inward).sum(-1) - fa)
    return la, lb


def quad_coordinates(quads: Tensor, y: Tensor, iterations: int = 4) -> tuple[Tensor, Tensor]:
    """Unit-square coordinates ``(u, v)`` ``[n]`` of points ``y [n, 3]`` on planar quads ``[n, 4, 3]`` (the inverse
    of :func:`bilinear`): Gauss–Newton with closed-form 2 × 2 normal
    equations from ``u = v = 1/2`` (exact for parallelograms after one step). Not differentiated."""
    c0, c1, c2, c3 = quads.unbind(1)
    u = torch.full_like(y[:, 0], 0.5)
    v = torch.full_like(u, 0.5)
    for _ in range(iterations):
        uu, vv = u[:, None], v[:, None]
        x = (1 - uu) * (1 - vv) * c0 + uu * (1 - vv) * c1 + uu * vv * c2 + (1 - uu) * vv * c3
        du = (1 - vv) * (c1 - c0) + vv * (c2 - c3)
        dv = (1 - uu) * (c3 - c0) + uu * (c2 - c1)
        r = y - x
        a, bb, cc = (du * du).sum(-1), (du * dv).sum(-1), (dv * dv).sum(-1)
        f, g = (du * r).sum(-1), (dv * r).sum(-1)
        det = (a * cc - bb * bb).clamp_min(1e-300)
        u = u + (cc * f - bb * g) / det
        v = v + (a * g - bb * f) / det
    return u, v


def pieces_between(segment: Tensor, par: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The pieces between consecutive break points of each segment: ``(segment, start, end)`` ``[n]`` of positive
    length, from break points given as ``segment [N]`` (int64) and their parameters ``par [N]`` in any order."""
    order = torch.argsort(par, stable=True)
    order = order[torch.argsort(segment[order], stable=True)]
    segment, par = segment[order], par[order]
    keep = (segment[1:] == segment[:-1]) & (par[1:] > par[:-1])
    return segment[:-1][keep], par[:-1][keep], par[1:][keep]


def ray_plane_points(origin: Tensor, direction: Tensor, centre: Tensor, normal: Tensor) -> Tensor:
    """Where rays ``origin + t · direction`` meet the planes ``(centre, normal)`` (broadcast, ``[..., 3]``;
    differentiable; a ray parallel to its plane gets ``t = (centre − origin)·normal``)."""
    nd = (normal * direction).sum(-1)
    t = ((centre - origin) * normal).sum(-1) / torch.where(nd != 0, nd, torch.ones_like(nd))
    return origin + t[..., None] * direction
