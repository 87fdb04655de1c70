"""The cosine-weighted hemisphere of facets by Embree rays: the fraction that escapes the scene (the sky's open
part) and the fraction whose first hit is a facet's back (:func:`~torch_interreflect.lights.sky`,
:func:`~torch_interreflect.lights.back_coverage`). Deterministic low-discrepancy samples; compiled ray set-up
(``_numba_visibility``) where numba is present, a numpy twin with the same samples elsewhere."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .._checks import check_count
from ..geometry._polygon import bilinear, tangent_frame
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from .compiled import launch, loops
from .sampling import KRONECKER_STEP, R2_STEP, pair_seeds

__all__ = ["hemisphere_fractions", "hemisphere_point_fractions"]



def _rotation(f: Tensor, seed: int) -> Tensor:
    """The rotation ``[k, 2]`` in ``[0, 1)`` of facets ``f``'s samples: seed 0 is the facets' own
    (:func:`~.sampling.pair_seeds` of the facet with itself); another seed draws every facet's rotation afresh from a
    splitmix64 hash of (facet, seed), so that estimates with different seeds are independent replicas (a linear
    hash would shift every facet by the same amount)."""
    if seed == 0:
        return pair_seeds(f, f)
    with np.errstate(over="ignore"):
        z = f.cpu().numpy().astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(seed) * np.uint64(
            0xD1B54A32D192ED03)
        out = []
        for salt in (np.uint64(0), np.uint64(0x632BE59BD9B4E019)):
            x = z ^ salt
            x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            x = x ^ (x >> np.uint64(31))
            out.append((x >> np.uint64(11)).astype(np.float64) / 9007199254740992.0)
    return torch.from_numpy(np.stack(out, -1))


def _hemisphere_hits(scene: Scene, idx: Tensor, samples: int, points: int, escape: bool, back: bool,
                     caster: Any, seed: int = 0) -> Iterator[tuple[int, int, np.ndarray, np.ndarray,
                                                                    dict[str, np.ndarray]]]:
    """Rays of :func:`hemisphere_fractions` in chunks of facets: ``(start, count, origin, area, counts)`` with
    ``origin [k·P·D, 3]`` (relative to the caster's origin), ``area [k, P]`` the points' area weights and ``counts``
    the ``"escape"`` / ``"back"`` rays per point ``[k, P]`` (int) asked for. ``seed``: the samples' rotation
    (:func:`_rotation`)."""
    check_count(samples, "samples")
    check_count(points, "points")
    sc = scene.to(torch.float64).to("cpu")
    kern = loops("visibility")
    K, P, D = idx.numel(), points * points, samples * samples
    normals = sc.normals.detach()
    t1, t2 = tangent_frame(normals)
    corners = sc.corners.detach() - torch.as_tensor(caster.origin)
    per = max(1, (1 << 20) // (P * D))  # about a million rays at a time
    for s in range(0, K, per):
        f = idx[s : s + per]
        k = f.numel()
        rotation = _rotation(f, int(seed))
        origin = np.empty((k * P * D, 3), dtype=np.float32)
        direction = np.empty((k * P * D, 3), dtype=np.float32)
        area = np.empty((k, P), dtype=np.float64)
        args = [t.contiguous().numpy() for t in (corners[f], normals[f], t1[f], t2[f])]
        if kern is None:
            _hemisphere_rays_numpy(*args, points, samples, rotation.numpy(), caster.eps, origin, direction, area)
        else:
            launch(kern.hemisphere_rays, *args, points, samples, rotation.numpy(), float(caster.eps), origin,
                   direction, area)
        counts: dict[str, np.ndarray] = {}
        if escape and not back:
            free = ~caster.occluded(origin, direction, np.full(len(origin), 4.0 * caster.size, dtype=np.float32))
            counts["escape"] = free.reshape(k, P, D).sum(-1)
        elif kern is not None:  # both from one first-hit cast, counted per point in one compiled pass
            tri = caster.hit_triangles(origin, direction)
            esc, bck = np.empty((k, P), dtype=np.int64), np.empty((k, P), dtype=np.int64)
            launch(kern.hit_counts, tri, caster.owner, direction, normals.numpy(), D, esc.reshape(-1),
                   bck.reshape(-1))
            counts["back"] = bck
            if escape:
                counts["escape"] = esc
        else:  # a ray escapes where it hits nothing
            facet = caster.hit_facets(origin, direction)
            nrm = normals.numpy()[np.maximum(facet, 0)]
            counts["back"] = ((facet >= 0) & ((direction * nrm).sum(-1) > 0)).reshape(k, P, D).sum(-1)
            if escape:
                counts["escape"] = (facet < 0).reshape(k, P, D).sum(-1)
        yield s, k, origin, area, counts


def hemisphere_fractions(scene: Scene, idx: Tensor, *, samples: int, points: int, escape: bool = True,
                         back: bool = True, caster: Any = None) -> tuple[Tensor | None, Tensor | None]:
    """Cosine-weighted fractions of the hemispheres of facets ``idx`` whose rays escape the scene, and whose first
    hit is the back of a facet (used for the sky's open part and back coverage, :func:`~torch_interreflect.lights.sky`).

    From ``points²`` points per facet (one per cell of the unit square, jittered by a low-discrepancy sequence
    rotated per facet) ``samples²`` stratified cosine-weighted directions each (the direction grid rotated per
    point), area weighted; deterministic. Escape rays use Embree's occlusion query, back rays its first-hit query
    (about twice the cost), each only when asked for (both asked for: one first-hit query gives both). Compiled ray
    set-up where numba is present.

    Args:
        scene: The scene.
        idx: Facets. Shape ``[K]`` (int64).
        samples: Directions per axis.
        points: Points per axis on each facet.
        escape, back: Which fraction to compute (the other comes back as None).
        caster: A :class:`~torch_interreflect.geometry.raycast.RayCaster` of the scene to reuse (built when None).

    Returns:
        ``(escape [K], back [K])``: float64 on the CPU (or None where not asked for).

    Raises:
        ValueRangeError: ``samples`` or ``points`` is not an integer ≥ 1.
    """
    caster = caster if caster is not None else RayCaster.of(scene.to(torch.float64).to("cpu"))
    kern = loops("visibility")
    K, D = idx.numel(), samples * samples
    out = {"escape": torch.empty(K, dtype=torch.float64) if escape else None,
           "back": torch.empty(K, dtype=torch.float64) if back else None}
    for s, k, _, area, counts in _hemisphere_hits(scene, idx, samples, points, escape, back, caster):
        for flag, count in counts.items():
            res = torch.empty(k, dtype=torch.float64)
            if kern is None:
                res = torch.as_tensor((area * (count / D)).sum(-1))
            else:
                launch(kern.hemisphere_count_sums, area, count, D, res.numpy())
            out[flag][s : s + k] = res  # type: ignore[index]
    return out["escape"], out["back"]


def hemisphere_point_fractions(scene: Scene, idx: Tensor, *, samples: int, points: int, escape: bool = True,
                               back: bool = True, caster: Any = None, seed: int = 0) -> dict[str, Tensor]:
    """The fractions of :func:`hemisphere_fractions` at each of its points, with the points and their weights
    (the same rays): for moments of the sky's open part over a facet. ``seed``: another rotation of every facet's
    points and directions (``0``: the rotation of :func:`hemisphere_fractions`); estimates with different seeds are
    independent replicas (a randomised quasi-Monte Carlo rule), whose spread measures their error.

    Returns:
        ``{"points": [K, P, 3] (m), "weights": [K, P] (area weights summing to 1 per facet), "escape": [K, P],
        "back": [K, P]}`` (the fractions only where asked for), float64 on the CPU, ``P = points²``.
    """
    sc = scene.to(torch.float64).to("cpu")
    caster = caster if caster is not None else RayCaster.of(sc)
    K, P, D = idx.numel(), points * points, samples * samples
    out = {"points": torch.empty(K, P, 3, dtype=torch.float64), "weights": torch.empty(K, P, dtype=torch.float64)}
    for flag, want in (("escape", escape), ("back", back)):
        if want:
            out[flag] = torch.empty(K, P, dtype=torch.float64)
    nrm = sc.normals.detach()
    for s, k, origin, area, counts in _hemisphere_hits(sc, idx, samples, points, escape, back, caster, seed):
        first = torch.from_numpy(origin.reshape(k, P, D, 3)[:, :, 0].astype(np.float64))
        out["points"][s : s + k] = first + torch.as_tensor(caster.origin) - caster.eps * nrm[idx[s : s + k], None, :]
        out["weights"][s : s + k] = torch.from_numpy(area)
        for flag, count in counts.items():
            out[flag][s : s + k] = torch.from_numpy(count / D)
    return out


def _hemisphere_rays_numpy(corners, normals, t1, t2, points, n, seed, eps, origin, direction, area) -> None:
    """:func:`._numba_visibility.hemisphere_rays` in numpy (the path without numba), same samples."""
    P, D = points * points, n * n
    p = np.arange(P)
    a = np.mod(seed[:, :1] + (p + 1) * R2_STEP[0], 1.0)
    b = np.mod(seed[:, 1:] + (p + 1) * R2_STEP[1], 1.0)
    u = (p // points + a) / points  # [K, P]
    v = (p % points + b) / points
    x, jac = bilinear(torch.as_tensor(corners), torch.as_tensor(u), torch.as_tensor(v))
    x, jac = x.numpy() + eps * normals[:, None, :], jac.numpy()
    tot = jac.sum(1, keepdims=True)
    area[:] = np.where(tot > 0, jac / np.where(tot > 0, tot, 1.0), 1.0 / P)
    ou = np.mod(seed[:, 1:] + (p + 1) * KRONECKER_STEP[0], 1.0)[..., None]  # [K, P, 1]
    ov = np.mod(seed[:, :1] + (p + 1) * KRONECKER_STEP[1], 1.0)[..., None]
    d = np.arange(D)
    s1 = (d // n + ou) / n
    s2 = (d % n + ov) / n
    rad, ang = np.sqrt(s1), 2.0 * math.pi * s2
    lx, ly, lz = rad * np.cos(ang), rad * np.sin(ang), np.sqrt(np.maximum(1.0 - s1, 0.0))
    dirs = (lx[..., None] * t1[:, None, None] + ly[..., None] * t2[:, None, None]
            + lz[..., None] * normals[:, None, None])
    origin[:] = np.broadcast_to(x[:, :, None, :], dirs.shape).reshape(-1, 3)
    direction[:] = dirs.reshape(-1, 3)
