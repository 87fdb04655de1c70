"""Point-to-facet form factors with occlusion: ``F(x → j) V(x, j)`` from points on facets of a scene.

Lambert's contour formula (the facet clipped to the point's tangent plane, in the compiled loop of
:func:`~torch_interreflect.formfactors.fused_points.point_sums`) times a kernel-weighted visible fraction from jittered
stratified Embree rays, cast only for facet pairs a third facet could block. Used per pixel by :mod:`.gather`.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from torch import Tensor

from .._checks import check_count
from .._sparse import sparse_matrix
from ..errors import ShapeError
from ..formfactors.fused_points import horizon_point_sums, point_sums
from ..formfactors.visibility import blocker_candidates
from ..geometry._polygon import bilinear, clip_polygons, facing_others, plane_eps
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene

__all__ = ["PAIR_CHUNK", "point_form_factors"]

#: Largest number of (point, facet) pairs whose visibility rays are set up at once (memory ~ 1 kB per pair).
PAIR_CHUNK = 1 << 16



def _real_vertices(poly: Tensor, eps: float) -> Tensor:
    """Number of leading vertices of padded polygons ``[P, K, 3]`` before the padding (copies of vertex 0)."""
    same = (poly - poly[:, :1]).norm(dim=-1) <= eps
    same[:, 0] = False
    idx = torch.arange(poly.shape[1]).expand_as(same)
    return torch.where(same, idx, torch.full_like(idx, poly.shape[1])).amin(1)


def _target_samples(corners: Tensor, triangle: Tensor, n: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Jittered stratified points ``[F, n², 3]`` and their area weights ``[F, n²]`` on every facet (bilinear map).

    On a triangle (corners ``c0, c1, c2, c2``) the bilinear map crowds equal strata toward ``c2``; ``v = 1 −
    √(1 − v')`` spreads them evenly over its area (each stratum the same area, weight ``J / (2 (1 − v))``)."""
    F = corners.shape[0]
    cells = torch.arange(n, dtype=torch.float64)
    u = (cells.repeat_interleave(n)[None] + torch.rand(F, n * n, dtype=torch.float64, generator=gen)) / n
    v = (cells.repeat(n)[None] + torch.rand(F, n * n, dtype=torch.float64, generator=gen)) / n
    tri = triangle.to(torch.bool)[:, None].expand_as(v)
    v = torch.where(tri, 1.0 - (1.0 - v).clamp_min(0.0).sqrt(), v)
    y, jac = bilinear(corners, u, v)
    jac = torch.where(tri, jac / (2.0 * (1.0 - v).clamp_min(1e-300)), jac)
    return y, jac / (n * n)


def _visibility(caster: RayCaster, x: Tensor, nx: Tensor, y: Tensor, w: Tensor, ny: Tensor) -> Tensor:
    """Kernel-weighted visible fraction ``[c]`` of targets sampled at ``y [c, Q, 3]`` (area weights ``w [c, Q]``,
    normals ``ny [c, 3]``) from points ``x [c, 3]`` (normals ``nx``), float32 relative to the caster's origin.

    Each sample is weighted by ``cos θ_x |cos θ_y| w / |x − y|²`` (either side of the target) and gets one Embree
    occlusion ray.
    """
    r = y - x[:, None, :]
    d2 = (r * r).sum(-1).clamp_min(1e-30)
    length = d2.sqrt()
    direction = r / length[..., None]
    k = (direction @ nx[:, :, None])[..., 0].clamp_min(0) * (direction @ ny[:, :, None])[..., 0].abs() * w / d2
    origin = x[:, None, :] + caster.eps * direction
    blocked = torch.from_numpy(
        caster.occluded(origin.reshape(-1, 3).numpy(), direction.reshape(-1, 3).numpy(),
                        (length - 2 * caster.eps).reshape(-1).numpy())
    ).reshape(k.shape)
    den = k.sum(-1)
    return torch.where(den > 0, (k * ~blocked).sum(-1) / den.clamp_min(1e-30), torch.ones_like(den)).double()


def point_form_factors(
    scene: Scene,
    points: Tensor,
    facet: Tensor,
    *,
    samples: int = 4,
    seed: int = 0,
    caster: RayCaster | None = None,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Exact point-to-facet form factors with occlusion, from points lying on facets of the scene.

    ``F(x → j)`` by Lambert's contour formula (facet ``j`` clipped to the tangent plane of ``x``), times the
    kernel-weighted visible fraction ``V(x, j)`` from ``samples²`` jittered stratified Embree rays, cast only for
    facet pairs that a third facet could block (:func:`~torch_interreflect.formfactors.visibility.blocker_candidates`).

    Args:
        scene: The scene.
        points: Points in metres, each on (or just above) the reflecting side of its facet. Shape ``[P, 3]``.
        facet: The facet of each point (its normal is the point's normal). Shape ``[P]`` (int64).
        samples: Visibility rays per side of the target facet (``samples²`` rays per blockable pair).
        seed: Seed of the jitter (the result is deterministic for a given seed).
        caster: A :class:`~torch_interreflect.geometry.raycast.RayCaster` of the scene to reuse.

    Returns:
        ``(factors, covered, info)``: ``factors`` sparse COO ``[P, F]`` float64 (CPU) of ``F(x → j) V(x, j)`` over
        the facets whose reflecting side ``x`` sees; ``covered [P]`` float64, the part of the cosine-weighted
        hemisphere of each point that sees any facet, front or back (the sky sees ``1 − covered``); ``info`` with
        ``pairs``, ``rays`` and ``seconds``.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.camera import point_form_factors
        >>> sq = torch.tensor([[[-.5, -.5, 0.], [.5, -.5, 0.], [.5, .5, 0.], [-.5, .5, 0.]],      # floor, up
        ...                    [[-.5, -.5, 1.], [-.5, .5, 1.], [.5, .5, 1.], [.5, -.5, 1.]]],     # ceiling, down
        ...                   dtype=torch.float64)
        >>> f, covered, _ = point_form_factors(ti.Scene.from_polygons(sq), torch.zeros(1, 3), torch.tensor([0]))
        >>> round(float(f.to_dense()[0, 1]), 7), round(float(covered[0]), 7)
        (0.2394565, 0.2394565)
    """
    t0 = time.perf_counter()
    sc = scene.to(torch.float64).to("cpu")
    x = torch.as_tensor(points, dtype=torch.float64).detach().cpu().reshape(-1, 3)
    h = torch.as_tensor(facet, dtype=torch.int64).cpu().reshape(-1)
    if h.shape[0] != x.shape[0]:
        raise ShapeError(f"points [P, 3] and facet [P] must agree; got {list(x.shape)} and {list(h.shape)}")
    if h.numel() and (int(h.min()) < 0 or int(h.max()) >= sc.num_facets):
        raise ShapeError(f"facet indices must lie in [0, {sc.num_facets}); got [{int(h.min())}, {int(h.max())}]")
    check_count(samples, "samples", note=" (rays per side of a target facet)")
    eps = plane_eps(scene)
    front = facing_others(scene)  # [F, F]: some corner of j strictly in front of i's plane
    fi, fj = torch.nonzero(front, as_tuple=True)
    need = blocker_candidates(sc, fi, fj, eps) if fi.numel() else torch.zeros(0, dtype=torch.bool)
    caster = caster if caster is not None else RayCaster.of(sc)
    gen = torch.Generator().manual_seed(int(seed))
    o = torch.as_tensor(caster.origin)
    # pairs (point, facet in front of its facet), point by point; facet pairs (fi, fj) are row-major, so the pairs
    # of facet i are fi's run starting at first[i]
    per_facet = front.sum(1)
    first = torch.cumsum(per_facet, 0) - per_facet
    counts = per_facet[h]
    pi = torch.repeat_interleave(torch.arange(x.shape[0]), counts)
    start = torch.cumsum(counts, 0) - counts
    pid = first[h][pi] + torch.arange(pi.numel()) - start[pi]
    pj = fj[pid]
    vals_ahead = horizon_point_sums(x, sc.normals[h], sc.centroids[h], pi, sc.corners, pj, (sc.centroids, sc.normals),
                                    eps)
    if vals_ahead is None:  # the torch path: every point of facet i has i's tangent plane, so each target is
        # clipped once per facet pair, not per point
        cpoly = clip_polygons(sc.corners[fj], sc.centroids[fi], sc.normals[fi], eps)
        cpoly = cpoly[:, : max(3, int(_real_vertices(cpoly, eps).max()) if fi.numel() else 3)]
        vals_ahead = point_sums(x, sc.normals[h], pi, cpoly, pid, (sc.centroids[fj], sc.normals[fj]))
    vals, in_front = vals_ahead
    blocked = torch.nonzero(need[pid] & (vals != 0)).reshape(-1)
    if blocked.numel():  # the targets' samples only where some pair can be blocked
        ys, ws = _target_samples(sc.corners, sc.is_triangle.cpu(), int(samples), gen)
        ys, ws, nf, xf = (ys - o).float(), ws.float(), sc.normals.float(), (x - o).float()
    for s in range(0, blocked.numel(), PAIR_CHUNK):
        k = blocked[s : s + PAIR_CHUNK]
        a, t = pi[k], pj[k]
        vals[k] = vals[k] * _visibility(caster, xf[a], nf[h[a]], ys[t], ws[t], nf[t])
    rays = int(blocked.numel()) * int(samples) ** 2
    covered = torch.zeros(x.shape[0], dtype=torch.float64).index_add_(0, pi, vals.abs())
    keep = in_front & (vals > 0)
    # pairs run point by point, facets ascending within a point: already coalesced
    factors = sparse_matrix(pi[keep], pj[keep], vals[keep], (x.shape[0], sc.num_facets), None, ordered=True)
    return factors, covered, {"pairs": int(pi.numel()), "rays": rays, "seconds": time.perf_counter() - t0}
