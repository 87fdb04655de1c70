"""Coincident and overlapping coplanar facets: found when a :class:`~torch_interreflect.Scene` is built.

Two facets that lie in one plane, face the same way and overlap in an area are the same surface counted twice:
every facet that sees them gets form factors summing above 1 (a duplicated mesh gives row sums of 1.4–1.6 and
negative irradiance at high reflectance). :func:`overlapping_pairs` finds them without an ``O(F²)`` pass:
candidate pairs share a plane key (normal and offset, rounded) and a cell of a uniform grid over the facets'
bounding boxes (so exact duplicates always meet), and are then tested exactly (same orientation, same plane, separating
axis test of the two convex polygons in that plane). Facets that only touch along an edge or at a corner, and
back-to-back facets (opposite normals, a thin wall), do not overlap.
"""

from __future__ import annotations

import numpy as np

from ..errors import GeometryError

__all__ = ["keep_first", "overlapping_pairs", "resolve_duplicates"]

#: Relative tolerance (of the larger facet's diameter) under which two facets count as coplanar, and an overlap
#: (or a separation) along a separating axis counts as zero.
COPLANAR_RTOL = 1e-6
#: Cosine above which two normals count as the same orientation.
SAME_NORMAL = 1.0 - 1e-6
#: Rounding of the normal and of the plane offset (relative to the scene size) for the plane key.
PLANE_QUANTUM = 1e-6


def overlapping_pairs(corners: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Pairs ``(i, j)``, ``i < j``, of coplanar facets with the same orientation that overlap in an area.

    Args:
        corners: Facet corners ``[F, 4, 3]`` (triangles repeat their last corner), float64.
        normals: Unit normals ``[F, 3]``.

    Returns:
        ``[K, 2]`` int64, sorted.

    Shape:
        - corners: ``[F, 4, 3]``; normals: ``[F, 3]``; output: ``[K, 2]``
    """
    F = corners.shape[0]
    if F < 2:
        return np.zeros((0, 2), dtype=np.int64)
    cand = _grid_candidates(corners, _plane_hash(corners, normals))
    if cand.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    i, j = cand[:, 0], cand[:, 1]
    diam = np.linalg.norm(corners.max(1) - corners.min(1), axis=1)
    tol = COPLANAR_RTOL * np.maximum(diam[i], diam[j])
    same = (normals[i] * normals[j]).sum(1) > SAME_NORMAL
    off = np.abs(((corners[j] - corners[i][:, :1]) * normals[i][:, None]).sum(-1)).max(1)
    # the boxes of two facets that overlap in an area (of width > tol) overlap by more than tol × the length of
    # each axis projected into the plane (a cheap test that drops neighbours touching along an edge)
    lo, hi = corners.min(1), corners.max(1)
    ext = np.minimum(hi[i], hi[j]) - np.maximum(lo[i], lo[j])
    inplane = np.sqrt(np.clip(1.0 - normals[i] ** 2, 0.0, 1.0))
    boxes = (ext > tol[:, None] * (inplane - 1e-3)).all(1)
    ok = same & (off <= tol) & boxes
    i, j, tol = i[ok], j[ok], tol[ok]
    hit = _overlap_2d(corners[i], corners[j], normals[i], tol)
    key = np.unique(i[hit] * F + j[hit])
    return np.stack([key // F, key % F], axis=1)


def keep_first(pairs: np.ndarray, num_facets: int) -> np.ndarray:
    """Boolean mask ``[F]``: keep each facet unless it overlaps a facet of lower index that is kept (greedy)."""
    keep = np.ones(num_facets, dtype=bool)
    for a, b in pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]:  # by the later facet, then the earlier one
        if keep[a]:
            keep[b] = False
    return keep


def _plane_hash(corners: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """An int64 per facet, equal for facets in one plane with one orientation (normal and offset rounded far above
    float noise; a collision of two planes only adds candidates, which the exact tests drop)."""
    size = float(np.linalg.norm(corners.reshape(-1, 3).max(0) - corners.reshape(-1, 3).min(0))) or 1.0
    offset = (normals * corners.mean(1)).sum(1) / size
    q = np.round(np.concatenate([normals, offset[:, None]], axis=1) / PLANE_QUANTUM).astype(np.int64)
    h = np.zeros(len(q), dtype=np.uint64)
    with np.errstate(over="ignore"):
        for k in range(4):
            h = (h ^ q[:, k].astype(np.uint64)) * np.uint64(0x100000001B3)
    return h.view(np.int64)


def _grid_candidates(corners: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Pairs of facets of one plane key whose bounding boxes share a cell of a uniform grid (cell ~ facet size)."""
    lo, hi = corners.min(1), corners.max(1)
    diam = np.linalg.norm(hi - lo, axis=1)
    cell = max(float(np.median(diam)), float(diam.max()) / 8.0, 1e-300)
    origin = lo.min(0)
    c0 = np.floor((lo - origin) / cell).astype(np.int64)
    c1 = np.floor((hi - origin) / cell).astype(np.int64)
    n = c1 - c0 + 1  # cells per axis per facet
    count = n.prod(1)
    owner = np.repeat(np.arange(len(lo)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    nx, ny = n[owner, 0], n[owner, 1]
    ix = c0[owner, 0] + k % nx
    iy = c0[owner, 1] + (k // nx) % ny
    iz = c0[owner, 2] + k // (nx * ny)
    dims = c1.max(0) + 2
    cell_id = ((ix * dims[1] + iy) * dims[2] + iz).astype(np.uint64)
    with np.errstate(over="ignore"):
        key = (plane[owner].view(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) ^ cell_id
    return _pairs_within_groups(key.view(np.int64), owner)


def _pairs_within_groups(group: np.ndarray, member: np.ndarray) -> np.ndarray:
    """All pairs ``(min, max)`` of distinct members that share a group id."""
    order = np.argsort(group, kind="stable")
    g, m = group[order], member[order]
    starts = np.r_[0, np.nonzero(np.diff(g))[0] + 1]
    sizes = np.diff(np.r_[starts, len(g)])
    pos = np.arange(len(g))
    end = np.repeat(starts + sizes, sizes)
    after = end - pos - 1  # members after this one in its group
    total = int(after.sum())
    if total == 0:
        return np.zeros((0, 2), dtype=np.int64)
    first = np.repeat(pos, after)
    second = first + 1 + (np.arange(total) - np.repeat(np.cumsum(after) - after, after))
    a, b = m[first], m[second]
    out = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    return out[out[:, 0] != out[:, 1]]


def _overlap_2d(p: np.ndarray, q: np.ndarray, normal: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """Separating axis test of convex polygons ``p, q [K, 4, 3]`` in their common plane: overlap beyond ``tol``."""
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0.0, 1, 0]])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    origin = p[:, :1]
    pu, pv = ((p - origin) * t1[:, None]).sum(-1), ((p - origin) * t2[:, None]).sum(-1)  # [K, 4]
    qu, qv = ((q - origin) * t1[:, None]).sum(-1), ((q - origin) * t2[:, None]).sum(-1)
    separated = np.zeros(len(p), dtype=bool)
    for u, v in ((pu, pv), (qu, qv)):
        au, av = -(np.roll(v, -1, axis=1) - v), np.roll(u, -1, axis=1) - u  # edge normals [K, 4]
        length = np.sqrt(au * au + av * av)
        valid = length > 0  # a triangle's repeated corner gives a zero edge
        au, av = au / np.where(valid, length, 1.0), av / np.where(valid, length, 1.0)
        pa = pu[:, None, :] * au[:, :, None] + pv[:, None, :] * av[:, :, None]  # [K, edges, corners]
        qa = qu[:, None, :] * au[:, :, None] + qv[:, None, :] * av[:, :, None]
        gap = np.maximum(pa.min(-1) - qa.max(-1), qa.min(-1) - pa.max(-1))  # > -tol: no area overlap
        separated |= (valid & (gap > -tol[:, None])).any(1)
    return ~separated


def resolve_duplicates(corners: np.ndarray, normals: np.ndarray, mode: str) -> np.ndarray | None:
    """Apply the ``duplicates=`` option of :class:`~torch_interreflect.Scene`: the facets to keep, or ``None``.

    Args:
        corners: ``[F, 4, 3]`` float64; normals: ``[F, 3]``.
        mode: ``"error"`` (raise on any overlapping pair), ``"drop"`` (keep the first facet of each overlapping
            group, by index) or ``"keep"`` (no check).

    Returns:
        ``None`` when every facet stays, else a boolean mask ``[F]``.

    Raises:
        GeometryError: ``mode="error"`` and some coplanar facets with the same orientation overlap.
    """
    if mode not in ("error", "drop", "keep"):
        raise ValueError(f"duplicates must be 'error', 'drop' or 'keep'; got {mode!r}")
    if mode == "keep":
        return None
    pairs = overlapping_pairs(corners, normals)
    if len(pairs) == 0:
        return None
    if mode == "error":
        shown = ", ".join(f"({a}, {b})" for a, b in pairs[:8].tolist())
        more = f" and {len(pairs) - 8} more" if len(pairs) > 8 else ""
        raise GeometryError(
            f"{len(pairs)} pairs of facets overlap: coincident or overlapping coplanar facets facing the same way "
            f"(facets {shown}{more}); each is the same surface counted twice and would make form-factor rows sum "
            "above 1. Remove them from the mesh, or pass duplicates='drop' to keep the first facet of each "
            "overlapping group"
        )
    return keep_first(pairs, len(corners))
