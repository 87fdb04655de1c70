"""The openings of a scene: the faces of its convex hull that no facet covers, where a sky can shine in.

Every ray that leaves a scene crosses the boundary of its convex hull once, on the way out. Where a face of the
hull lies under facets of the scene (a wall on the hull), the ray is stopped there; where no facet lies in it, the
ray escapes. So the part of the sky a point sees is the form factor, with occlusion, from the point to the hull
faces no facet covers: :func:`openings` returns them as facets that face into the scene, for
:func:`torch_interreflect.sky_openings.sky_through_openings`.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from ..errors import GeometryError
from ._polygon import plane_eps, scene_size
from .scene import Scene

__all__ = ["COVERED", "ON_FACE", "facing_out", "openings"]

#: A hull face counts as covered where the coplanar facets' area is at least this share of its own, and as open
#: where it is at most ``1 − COVERED``; anything between is a partly covered face (:func:`openings` returns None).
COVERED = 1.0 - 1e-6

#: Distance under which a point counts as on a hull face, relative to the scene's size: float32's rounding of the
#: corners (the scene may come in float32 and be converted), whatever dtype the computation is in.
ON_FACE = 2e-6


def _faces(points: np.ndarray, eps: float) -> list[tuple[np.ndarray, float, np.ndarray]] | None:
    """The hull's faces as ``(outward unit normal [3], offset d with n·x + d = 0, corners [k, 3] in order)``;
    ``None`` where the points span no volume. Hull triangles whose corners lie within ``eps`` of one's plane are one
    face."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):
        return None
    eq = hull.equations
    tri = points[hull.simplices]
    size = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    group = np.full(len(eq), -1)
    faces = []
    for s in np.argsort(-size, kind="stable"):  # each face's plane from its largest triangle, not a sliver's
        if group[s] >= 0:
            continue
        far = np.abs(tri @ eq[s, :3] + eq[s, 3]).max(1)  # each triangle's corners off this plane
        same = (group < 0) & (far < eps) & (eq[:, :3] @ eq[s, :3] > 0.5)  # float noise splits a face in slivers
        group[same] = len(faces)
        n, d = eq[s, :3], float(eq[s, 3])
        corners = np.unique(points[hull.simplices[same].reshape(-1)], axis=0)
        centre = corners.mean(0)
        t1 = corners[0] - centre
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        order = np.argsort(np.arctan2((corners - centre) @ t2, (corners - centre) @ t1))  # counter-clockwise about n
        faces.append((n, d, corners[order]))
    return faces


def _corners_only(polygon: np.ndarray, eps: float) -> np.ndarray:
    """``polygon [k, 3]`` without the points on its edges (where the hull keeps points along a straight edge)."""
    prev, nxt = np.roll(polygon, 1, axis=0), np.roll(polygon, -1, axis=0)
    bend = np.linalg.norm(np.cross(polygon - prev, nxt - polygon), axis=1)
    span = np.linalg.norm(nxt - prev, axis=1)
    return polygon[bend > eps * np.maximum(span, 1e-300)]


def _area(polygon: np.ndarray) -> float:
    c = polygon - polygon[0]
    return 0.5 * float(np.linalg.norm(np.cross(c[1:-1], c[2:]).sum(0)))


def _wedged(polygon: np.ndarray, sc: Scene, eps: float) -> bool:
    """Whether facets of two planes lie along one stretch of an edge of the opening ``polygon [k, 3]`` (the valley of
    a W shape on its hull's floor): the one in front hides the opening from the other right up to the edge, where
    the kernel is singular, and the blocked part that the rays sample there does not converge."""
    corners = sc.corners.numpy()
    a = corners.reshape(-1, 3)
    b = np.roll(corners, -1, axis=1).reshape(-1, 3)  # each facet edge; a triangle's repeated corner has length 0
    normal = np.repeat(sc.normals.numpy(), 4, axis=0)
    for p, q in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        length = float(np.linalg.norm(q - p))
        u = (q - p) / length
        ta, tb = (a - p) @ u, (b - p) @ u
        off_a = np.linalg.norm(a - p - ta[:, None] * u, axis=1)
        off_b = np.linalg.norm(b - p - tb[:, None] * u, axis=1)
        lo, hi = np.maximum(np.minimum(ta, tb), 0.0), np.minimum(np.maximum(ta, tb), length)
        on = (off_a < eps) & (off_b < eps) & (hi - lo > eps)
        idx = np.nonzero(on)[0]
        for m in range(idx.size):
            for k in idx[m + 1:]:
                other_plane = abs(float(normal[idx[m]] @ normal[k])) < 1.0 - 1e-6
                if other_plane and min(hi[idx[m]], hi[k]) - max(lo[idx[m]], lo[k]) > eps:
                    return True
    return False


def openings(scene: Scene) -> Scene | None:
    """The faces of the scene's convex hull that no facet covers, as facets facing into the scene.

    A hull face is covered where facets of the scene lie in its plane over all of its area, and open where none
    does; the open ones are returned (a face of three or four corners as one facet, a larger one as a fan of
    triangles), their corners in the order that makes their normals point into the hull. A sky of radiance ``L``
    then gives a point ``x`` of the scene the irradiance ``π L Σ_o F(x → o)``, ``F`` with occlusion.

    Args:
        scene: The scene (its corners in metres).

    Returns:
        The openings as a :class:`Scene` in the scene's dtype (on the CPU), or None where there is none (a closed
        scene) or they cannot be told from the hull: a hull face only partly covered (or by coplanar facets that
        overlap), an edge of an opening
        along which facets of two planes meet (a W shape's valleys on its hull's floor), or a scene that spans no
        volume (flat).

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.geometry.openings import openings
        >>> box = ti.scenes.cornell_box(light=False, dtype=torch.float64)   # open at the front, z = 0
        >>> o = openings(box)
        >>> o.num_facets, float(o.normals[0, 2])              # one opening, facing into the box (+z)
        (1, 1.0)
    """
    sc = scene.detach().to(torch.float64).to("cpu")
    eps = max(plane_eps(scene), ON_FACE * scene_size(sc))
    points = sc.corners.reshape(-1, 3).numpy()
    faces = _faces(points, eps)
    if faces is None:
        return None
    normals, centroids, areas = sc.normals.numpy(), sc.centroids.numpy(), sc.areas.numpy()
    tris, quads = [], []
    for n, d, corners in faces:
        inside = (np.abs(np.abs(normals @ n) - 1.0) < 1e-6) & (np.abs(centroids @ n + d) < eps)
        out = normals @ n > 0  # facets back to back (a two-sided panel) cover the same part once
        shares = [float(areas[inside & side].sum()) / _area(corners) for side in (out, ~out)]
        if max(shares) > 2.0 - COVERED:  # coplanar facets overlap: the coverage cannot be told
            return None
        if max(shares) >= COVERED:
            continue
        if max(shares) > 1.0 - COVERED:
            return None
        if _wedged(corners, sc, eps):
            return None
        inward = _corners_only(corners[::-1], eps)
        if len(inward) == 4:
            quads.append(inward)
        else:  # a triangle, or a fan of them
            tris += [np.stack([inward[0], inward[k], inward[k + 1]]) for k in range(1, len(inward) - 1)]
    try:
        parts = [Scene.from_polygons(torch.as_tensor(np.stack(p), dtype=scene.dtype)) for p in (quads, tris) if p]
    except GeometryError:  # a sliver of the hull too thin for a facet
        return None
    if not parts:
        return None
    return parts[0] if len(parts) == 1 else Scene.concatenate(parts)


def facing_out(scene: Scene) -> torch.Tensor:
    """Which facets have nothing of the scene in front of them: their plane supports the scene (a cabinet's back
    against the wall of a room, facing out). Nothing can block their view, so a sky fills all of it; the
    openings do not see them (rays from there leave through the face they lie on).

    Returns:
        A mask ``[F]`` (bool, CPU).

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.geometry.openings import facing_out
        >>> bool(facing_out(ti.scenes.cornell_box(light=False, dtype=torch.float64)).any())   # all face inward
        False
    """
    from scipy.spatial import ConvexHull, QhullError

    sc = scene.detach().to(torch.float64).to("cpu")
    points = sc.corners.reshape(-1, 3)
    with contextlib.suppress(QhullError, ValueError):  # a plane's farthest point is a hull vertex
        points = points[torch.from_numpy(ConvexHull(points.numpy()).vertices)]
    ahead = ((points[None] - sc.centroids[:, None]) * sc.normals[:, None]).sum(-1).amax(1)
    return ahead <= max(plane_eps(scene), ON_FACE * scene_size(sc))
