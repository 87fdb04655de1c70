"""Contact lines: split facets where another facet stands on them.

A block resting on a floor touches it along edges that run through the floor facets' interiors. Part of such a
floor facet is then hidden under the block: it receives no light and sends none, but a piecewise-constant
solution spreads the facet's light evenly over the hidden part too, so everything the floor lights gets too
little. On the Cornell box under the sky (r = 0.9) this biased every wall low by 2–4 % at 256–1,024 facets, and it
falls only as the facets shrink. Splitting the floor along the contact lines first removes the bias:
``benchmarks/results/visibility.md`` has the numbers.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ._polygon import group_firsts, plane_eps, plane_ids, scene_size
from .scene import Scene

__all__ = ["PAIR_CHUNK", "contact_pairs", "split_at_contacts", "through_interior"]

#: Largest number of (facet, candidate edge) triplets tested at once.
PAIR_CHUNK = 1 << 20


def contact_pairs(scene: Scene) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``: an edge of facet ``j`` lies in facet ``i``'s plane and runs through ``i``'s interior
    (``j`` not coplanar with ``i``). Edges along ``i``'s boundary (facets meeting at a shared edge, a grid's
    neighbours) are not contacts.

    The edges are first matched to the scene's planes (coplanar facets share one, :func:`plane_ids`), with a margin
    that covers how far a member's own plane can lie from its group's, and only those candidates are tested
    against each member facet: ``O(F × planes)`` work instead of ``O(F²)`` for meshes of few planes (a V-groove of
    200 facets has two), the same pairs.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"contact_pairs expects a Scene; got {type(scene).__name__}")
    sc = scene.to(torch.float64).to("cpu")
    corners, normals = sc.corners.detach(), sc.normals.detach()
    eps = plane_eps(scene)
    F = sc.num_facets
    if F == 0:
        return []
    nxt = torch.roll(corners, -1, dims=1)  # edges: corner k → k + 1 (a triangle's repeated corner: length 0)
    offs = (normals * corners[:, 0]).sum(-1)
    group = plane_ids(sc, eps)
    first = group_firsts(group)
    pn, po = normals[first], offs[first]
    # a member's distance n_i·(x − c_i0) differs from its group's n_g·x − o_g by at most |n_i − n_g| |x − c_i0|
    # plus the group's distance at c_i0
    size = scene_size(sc)
    dn = torch.zeros(len(first), dtype=torch.float64).scatter_reduce_(0, group, (normals - pn[group]).norm(dim=-1),
                                                                       "amax")
    thick = ((corners * pn[group][:, None, :]).sum(-1) - po[group][:, None]).abs().amax(1)
    slack = eps + dn * size + torch.zeros_like(dn).scatter_reduce_(0, group, thick, "amax") + 1e-12 * size
    members = torch.argsort(group, stable=True)
    count = torch.bincount(group, minlength=len(first))
    start = torch.cumsum(count, 0) - count
    out: list[tuple[int, int]] = []
    chunk = max(1, (1 << 21) // max(1, 4 * F))
    for s in range(0, len(first), chunk):
        g = torch.arange(s, min(s + chunk, len(first)))
        da = torch.einsum("gx,fkx->gfk", pn[g], corners) - po[g][:, None, None]  # [g, F, 4]
        db = torch.einsum("gx,fkx->gfk", pn[g], nxt) - po[g][:, None, None]
        # coplanar with every member (the exact test: |n_i·n_j| > 1 − 1e-9): parallel by the bound on the members'
        # normals, or the group's own facets when any two members' normals are within 2 dn of each other with
        # 1 − (2 dn)²/2 > 1 − 1e-9 (a float32 group can hold facets tilted further: those go to the exact test)
        own = (group[None, :] == g[:, None]) & (2.0 * dn[g] ** 2 < 1e-9)[:, None]
        surely_coplanar = ((normals @ pn[g].T).T.abs() - dn[g][:, None] > 1 - 1e-9) | own
        near = (da.abs() <= slack[g][:, None, None]) & (db.abs() <= slack[g][:, None, None])
        gi, fj, k = torch.nonzero(near & ~surely_coplanar[..., None]).unbind(1)
        gi = g[gi]
        # every member of the edge's group, in runs of at most PAIR_CHUNK triplets
        ends = torch.cumsum(count[gi], 0)
        lo = 0
        while lo < gi.numel():
            hi = max(lo + 1, int(torch.searchsorted(ends, int(ends[lo]) - int(count[gi[lo]]) + PAIR_CHUNK, right=True)))
            reps = count[gi[lo:hi]]
            c = torch.repeat_interleave(torch.arange(lo, hi), reps)
            m = torch.arange(c.numel()) - (torch.cumsum(reps, 0) - reps).repeat_interleave(reps)
            out += _exact(corners, nxt, normals, offs, members[start[gi[c]] + m], fj[c], k[c], eps)
            lo = hi
    return sorted(set(out))


def _exact(corners: Tensor, nxt: Tensor, normals: Tensor, offs: Tensor, i: Tensor, fj: Tensor, k: Tensor,
           eps: float) -> list[tuple[int, int]]:
    """The contact test on candidate triplets (facet ``i``, edge ``k`` of facet ``fj``), each with ``i``'s own
    plane: both ends within ``eps`` of it, ``fj`` not coplanar with ``i``, bounding boxes overlapping, the edge
    through ``i``'s interior."""
    n, o = normals[i], offs[i]
    a, b = corners[fj, k], nxt[fj, k]
    keep = (((a * n).sum(-1) - o).abs() <= eps) & (((b * n).sum(-1) - o).abs() <= eps) & (fj != i)
    keep &= (normals[fj] * n).sum(-1).abs() <= 1 - 1e-9
    lo, hi = corners[i].min(1).values, corners[i].max(1).values
    keep &= ((torch.minimum(a, b) <= hi + eps) & (torch.maximum(a, b) >= lo - eps)).all(-1)
    i, fj, a, b = i[keep], fj[keep], a[keep], b[keep]
    hit = through_interior(corners[i], normals[i], a, b, eps)
    return list(zip(i[hit].tolist(), fj[hit].tolist(), strict=True))


def split_at_contacts(scene: Scene) -> tuple[Scene, Tensor]:
    """Split every facet along the planes of the facets that stand on it (:func:`contact_pairs`).

    The pieces are convex; those with more than four corners are fanned into triangles. Pieces keep their parent's
    orientation and material, and a parent's pieces are contiguous and cover it exactly, so results on the pieces
    area-average back with :meth:`Scene.average_to_parent` (hidden pieces included: their irradiance is ~0, as
    it is under the block).

    Args:
        scene: The scene.

    Returns:
        ``(pieces, parent)`` as from :meth:`Scene.subdivide`; the scene itself and ``arange(F)`` when nothing
        stands on anything.

    Example:
        >>> import torch_interreflect as ti
        >>> box = ti.scenes.cornell_box(1, light=False)
        >>> pieces, parent = split_at_contacts(box)
        >>> box.num_facets, pieces.num_facets, int((parent == 0).sum())  # the floor, cut around both blocks
        (16, 50, 35)
    """
    pairs = contact_pairs(scene)
    F = scene.num_facets
    if not pairs:
        return scene, torch.arange(F, device=scene.device)
    sc = scene.to(torch.float64).to("cpu")
    corners, normals = sc.corners.detach().numpy(), sc.normals.detach().numpy()
    tri = sc.is_triangle.numpy()
    eps = plane_eps(scene)
    cutters: dict[int, list[int]] = {}
    for i, j in pairs:
        cutters.setdefault(i, []).append(j)
    out_corners, out_tri, parent = [], [], []
    for i in range(F):
        pieces = [corners[i, :3] if tri[i] else corners[i]]
        for j in cutters.get(i, []):
            pieces = [q for p in pieces for q in _split(p, corners[j, 0], normals[j], eps)]
        for p in pieces:
            for c, t in _as_facets(p):
                out_corners.append(c)
                out_tri.append(t)
                parent.append(i)
    c = torch.as_tensor(np.stack(out_corners), dtype=scene.dtype, device=scene.device)
    parent_t = torch.as_tensor(parent, dtype=torch.int64, device=scene.device)
    mat = scene.material[parent_t] if scene.material is not None else None
    return Scene.from_parts(c, torch.as_tensor(out_tri, device=scene.device), mat, scene.material_names), parent_t


def through_interior(poly: Tensor, normal: Tensor, a: Tensor, b: Tensor, eps: float) -> Tensor:
    """Whether each segment ``a → b`` (in its polygon's plane) has a part of positive length strictly inside the
    convex polygon (Cyrus–Beck clipping against its edges' inward half-planes), for all segments at once.

    Shape:
        - poly: ``[N, 4, 3]`` (counter-clockwise about ``normal``), normal: ``[N, 3]``, a, b: ``[N, 3]``
        - output: ``[N]`` bool
    """
    length = torch.linalg.vector_norm(b - a, dim=-1)  # [N]
    e = torch.roll(poly, -1, dims=1) - poly  # [N, 4, 3]
    e_len = torch.linalg.vector_norm(e, dim=-1)  # [N, 4]
    edge = e_len > eps  # a triangle's repeated corner gives an edge of length 0: no half-plane
    # counter-clockwise polygons: the interior is to the left of each edge
    inward = torch.linalg.cross(normal[:, None, :].expand_as(e), e / e_len.clamp_min(1e-300)[..., None])
    fa = ((a[:, None, :] - poly) * inward).sum(-1) - eps  # [N, 4]
    fb = ((b[:, None, :] - poly) * inward).sum(-1) - eps
    outside = (edge & (fa < 0) & (fb < 0)).any(-1)
    t = fa / torch.where(fa == fb, torch.ones_like(fa), fa - fb)
    t0 = torch.where(edge & (fa < 0) & (fb >= 0), t, torch.zeros_like(t)).amax(-1).clamp_min(0.0)
    t1 = torch.where(edge & (fa >= 0) & (fb < 0), t, torch.ones_like(t)).amin(-1).clamp_max(1.0)
    return (length > eps) & ~outside & ((t1 - t0) * length > eps)


def _split(poly: np.ndarray, point: np.ndarray, normal: np.ndarray, eps: float) -> list[np.ndarray]:
    """A convex polygon ``[K, 3]`` cut by a plane: both pieces, or the polygon when the plane misses it."""
    d = (poly - point) @ normal
    if (d > -eps).all() or (d < eps).all():
        return [poly]
    pos, neg = [], []
    K = len(poly)
    for k in range(K):
        a, b, da, db = poly[k], poly[(k + 1) % K], d[k], d[(k + 1) % K]
        if da >= -eps:
            pos.append(a)
        if da <= eps:
            neg.append(a)
        if (da > eps and db < -eps) or (da < -eps and db > eps):
            q = a + da / (da - db) * (b - a)
            pos.append(q)
            neg.append(q)
    return [np.array(p) for p in (pos, neg) if len(p) >= 3]


def _as_facets(poly: np.ndarray) -> list[tuple[np.ndarray, bool]]:
    """A convex polygon as facets ``([4, 3] corners, is_triangle)``: itself (3 or 4 corners) or a fan."""
    if len(poly) == 4:
        return [(poly, False)]
    tris = [np.stack([poly[0], poly[t], poly[t + 1], poly[t + 1]]) for t in range(1, len(poly) - 1)]
    return [(t, True) for t in tris]
