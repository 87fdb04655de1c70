"""Ray casting against a scene's facets with Embree (through trimesh's ``embreex`` binding).

Geometry work that is not differentiable: it runs once per scene, on numpy float32 arrays, and its results
(visibility fractions, lit fractions, hit facets) are cached by the callers. Large batches are split across
:func:`~torch_interreflect._threads.work_threads` threads (torch's count, or the caller's inside
:func:`~torch_interreflect._threads.compiled_work`; Embree's queries release the GIL), so every core casts rays.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import numpy as np

from .._threads import work_threads
from .scene import Scene

__all__ = ["RayCaster"]

#: Rays per thread below which a batch is not split (thread start-up would cost more than it saves).
_MIN_RAYS_PER_THREAD = 1 << 14


@cache
def _pool(n: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=n, thread_name_prefix="ti-raycast")


# A forked child inherits the pool object but not its threads: waiting on it would hang forever (a DataLoader's
# workers, multiprocessing). The child starts with no pool and makes its own on first use.
os.register_at_fork(after_in_child=_pool.cache_clear)


def _run_split(run, n_rays: int, *arrays: np.ndarray) -> np.ndarray:
    """``run(*arrays)`` over the rays, split into contiguous blocks across threads; results concatenated."""
    n = min(work_threads(), max(1, n_rays // _MIN_RAYS_PER_THREAD))
    if n <= 1:
        return np.asarray(run(*arrays))
    bounds = np.linspace(0, n_rays, n + 1).astype(np.int64)
    parts = _pool(n).map(lambda a, b: np.asarray(run(*(x[a:b] for x in arrays))), bounds[:-1], bounds[1:])
    return np.concatenate(list(parts))


class RayCaster:
    """Segment-occlusion and first-hit queries against the facets of a scene.

    Args:
        scene: The scene; quads are split into two triangles, each remembering its facet.

    Example:
        >>> import numpy as np, torch_interreflect as ti
        >>> rc = ti.geometry.RayCaster(ti.scenes.closed_box(divisions=1))
        >>> rc.first_hit(np.array([[0.5, 0.5, 0.5]]), np.array([[0.0, 0.0, 1.0]])).tolist()
        [1]
    """

    def __init__(self, scene: Scene) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        mesh, owner = scene.to_trimesh()
        self._owner = np.asarray(owner, dtype=np.int64)
        self._owner.flags.writeable = False
        #: the facet of each of Embree's triangles (for :meth:`hit_triangles`; read-only)
        self.owner = self._owner
        tris = np.asarray(mesh.triangles, dtype=np.float64)
        self._origin = tris.reshape(-1, 3).mean(0)  # re-centre: float32 keeps more digits near 0
        #: the point (m) that Embree's coordinates are relative to (see :meth:`occluded`)
        self.origin = self._origin
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self._scene, (tris - self._origin).astype(np.float32))
        lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
        self.size = float(np.linalg.norm(hi - lo))
        #: offset (m) that keeps a ray from hitting the facet it starts on or ends at
        self.eps = 1e-6 * self.size

    @classmethod
    def of(cls, scene: Scene) -> RayCaster:
        """The ray caster of ``scene``, built once while its corners are unchanged (:meth:`Scene.derived`; a
        render's moments, sky and shadows share one instead of building Embree's scene each). Corners that
        require grad get a new one each call.

        Example:
            >>> import torch_interreflect as ti
            >>> box = ti.scenes.closed_box(divisions=1)
            >>> ti.geometry.RayCaster.of(box) is ti.geometry.RayCaster.of(box)
            True
        """
        return scene.derived("ray_caster", lambda: cls(scene))

    def segments_blocked(self, start: np.ndarray, end: np.ndarray, batch: int = 1 << 20) -> np.ndarray:
        """Whether anything lies strictly between ``start`` and ``end``.

        Args:
            start: Segment starts in metres, ``[N, 3]``.
            end: Segment ends in metres, ``[N, 3]``.

        Returns:
            Boolean ``[N]``.
        """
        start = np.asarray(start, dtype=np.float64) - self._origin
        end = np.asarray(end, dtype=np.float64) - self._origin
        out = np.zeros(len(start), dtype=bool)
        for s in range(0, len(start), batch):
            a, b = start[s : s + batch], end[s : s + batch]
            d = b - a
            length = np.linalg.norm(d, axis=1)
            d = d / np.maximum(length, 1e-300)[:, None]
            o = a + d * self.eps
            tfar = np.maximum(length - 2 * self.eps, 0.0)
            res = _run_split(self._occluded_raw, len(a), o.astype(np.float32), d.astype(np.float32),
                             tfar.astype(np.float32))
            out[s : s + batch] = (res != -1) & (tfar > 0)
        return out

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> np.ndarray:
        """Raw occlusion query: is anything hit within ``tfar`` along each ray?

        Args:
            origins: Ray origins relative to :attr:`origin`, float32 ``[N, 3]``.
            directions: Unit directions, float32 ``[N, 3]``.
            tfar: Distances in metres, float32 ``[N]`` (non-positive: never occluded).

        Returns:
            Boolean ``[N]``.
        """
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        t = np.ascontiguousarray(tfar, dtype=np.float32)
        res = _run_split(self._occluded_raw, len(o), o, d, np.maximum(t, 0))
        return (res != -1) & (t > 0)

    def hit_facets(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Raw first-hit query: the facet each ray hits first (``-1`` when it escapes).

        Args:
            origins: Ray origins relative to :attr:`origin`, float32 ``[N, 3]`` (already offset off their facet).
            directions: Unit directions, float32 ``[N, 3]``.

        Returns:
            Facet indices ``[N]`` (int64).
        """
        tri = self.hit_triangles(origins, directions)
        return np.where(tri >= 0, self._owner[np.maximum(tri, 0)], -1)

    def hit_triangles(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """:meth:`hit_facets` before the triangles are mapped to their facets (:attr:`owner`): Embree's triangle
        index per ray, ``-1`` where it escapes.

        Args:
            origins: Ray origins relative to :attr:`origin`, float32 (already offset off their facet).
            directions: Unit directions, float32.

        Returns:
            Triangle indices (int32).

        Shape:
            - origins, directions: ``[N, 3]`` (float32, as for :meth:`hit_facets`); output ``[N]`` (int32)
        """
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        return _run_split(self._hit_raw, len(o), o, d)

    def _occluded_raw(self, o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
        return self._scene.run(np.ascontiguousarray(o), np.ascontiguousarray(d), dists=np.ascontiguousarray(t),
                               query="OCCLUDED")

    def _hit_raw(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        return self._scene.run(np.ascontiguousarray(o), np.ascontiguousarray(d), query="INTERSECT")

    def first_hit(self, origins: np.ndarray, directions: np.ndarray, batch: int = 1 << 20) -> np.ndarray:
        """Index of the first facet hit by each ray (``-1`` when it escapes).

        Args:
            origins: Ray origins in metres, ``[N, 3]`` (offset by a tiny step along the ray).
            directions: Ray directions, ``[N, 3]`` (need not be normalised).

        Returns:
            Facet indices ``[N]`` (int64).
        """
        origins = np.asarray(origins, dtype=np.float64) - self._origin
        directions = np.asarray(directions, dtype=np.float64)
        out = np.empty(len(origins), dtype=np.int64)
        for s in range(0, len(origins), batch):
            d = directions[s : s + batch]
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            o = origins[s : s + batch] + d * self.eps
            out[s : s + batch] = self.hit_facets(o.astype(np.float32), d.astype(np.float32))
        return out
