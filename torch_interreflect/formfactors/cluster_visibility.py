"""Visible fraction of far blocks of the hierarchical kernel: rays between sample facets of two clusters, cast
only where a third facet could block (the dense kernel's plane-group test on cluster bounds)."""

from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np

from ..geometry._polygon import plane_groups
from ..geometry.scene import Scene
from .cluster_tree import ClusterTree

__all__ = ["ClusterVisibility"]


class ClusterVisibility:
    """Visible fraction ``V_AB`` of cluster pairs from rays between sample facets, where a third facet could block."""

    def __init__(self, sc: Scene, tree: ClusterTree, occlusion: Literal["auto"] | bool, samples: int, eps: float,
                 caster: Any) -> None:
        self.tree, self.occlusion, self.samples, self.eps = tree, occlusion, samples, eps
        self.groups = plane_groups(sc, eps) if occlusion == "auto" else None
        self.caster = caster
        self.cent, self.normals, self.areas = (t.detach().numpy() for t in (sc.centroids, sc.normals, sc.areas))
        self.rays = 0
        self.blocks = 0
        self.seconds = 0.0

    def candidates(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Pairs that some plane group could block (the dense kernel's test on cluster spheres and boxes)."""
        if self.occlusion is False:
            return np.zeros(a.size, dtype=bool)
        if self.occlusion is True:
            return np.ones(a.size, dtype=bool)
        if self.groups is None:
            return np.zeros(a.size, dtype=bool)
        pn, po, plo, phi = (g.numpy() for g in self.groups)
        t = self.tree
        gc, gr = 0.5 * (plo + phi), 0.5 * np.linalg.norm(phi - plo, axis=1)
        out = np.zeros(a.size, dtype=bool)
        eps = self.eps
        chunk = max(1, (1 << 21) // max(len(pn), 1))
        for s in range(0, a.size, chunk):
            ia, ib = a[s : s + chunk], b[s : s + chunk]
            da = t.centre[ia] @ pn.T - po  # [c, G]
            db = t.centre[ib] @ pn.T - po
            ra, rb = t.radius[ia][:, None], t.radius[ib][:, None]
            straddle = (np.maximum(da + ra, db + rb) > eps) & (np.minimum(da - ra, db - rb) < -eps)
            blo = np.minimum(t.lo[ia], t.lo[ib])
            bhi = np.maximum(t.hi[ia], t.hi[ib])
            overlap = ((plo[None] < bhi[:, None] - eps) & (phi[None] > blo[:, None] + eps)).all(-1)
            ca, seg = t.centre[ia], t.centre[ib] - t.centre[ia]
            tt = ((gc[None] - ca[:, None]) * seg[:, None]).sum(-1) / np.maximum((seg * seg).sum(-1), 1e-300)[:, None]
            closest = ca[:, None] + np.clip(tt, 0, 1)[..., None] * seg[:, None]
            reach = np.linalg.norm(gc[None] - closest, axis=-1) <= np.maximum(ra, rb) + gr[None] + eps
            out[s : s + chunk] = (straddle & overlap & reach).any(-1)
        return out

    def _sample(self, nodes: np.ndarray) -> np.ndarray:
        """``samples`` facets per node, spread over its (spatially sorted) range: ``[n, S]`` facet indices."""
        t = self.tree
        k = (np.arange(self.samples) + 0.5) / self.samples
        pos = t.start[nodes][:, None] + (k[None, :] * (t.end - t.start)[nodes][:, None]).astype(np.int64)
        return t.perm[pos]

    def _members(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(k, facet)``: every facet of every node ``nodes[k]``."""
        t = self.tree
        size = t.end[nodes] - t.start[nodes]
        k = np.repeat(np.arange(nodes.size), size)
        pos = np.arange(int(size.sum())) - np.repeat(np.cumsum(size) - size, size) + t.start[nodes][k]
        return k, t.perm[pos]

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Kernel-weighted visible fraction per block; every facet of each side casts ``samples`` rays to sample
        facets of the other side, so a facet hidden from the other cluster makes the block partly visible."""
        t0 = time.perf_counter()
        v = np.ones(a.size)
        need = np.nonzero(self.candidates(a, b))[0]
        if need.size and self.caster is not None:
            t = self.tree
            S = self.samples
            sizes = (t.end - t.start)[a[need]] + (t.end - t.start)[b[need]]
            budget = max(1, (1 << 22) // S)
            s = 0
            cum = np.cumsum(sizes)
            while s < need.size:
                base = cum[s - 1] if s else 0
                e = max(s + 1, int(np.searchsorted(cum, base + budget, side="right")))
                blk = need[s:e]
                num = np.zeros(blk.size)
                den = np.zeros(blk.size)
                hid = []
                for src, dst in ((a[blk], b[blk]), (b[blk], a[blk])):
                    k, fi = self._members(src)
                    fj = self._sample(dst)[k]  # [n, S]
                    xi = np.repeat(fi[:, None], S, axis=1)
                    pa, pb = self.cent[xi], self.cent[fj]
                    r = pb - pa
                    d2 = np.maximum((r * r).sum(-1), 1e-300)
                    w = (np.maximum((self.normals[xi] * r).sum(-1), 0) * np.maximum(-(self.normals[fj] * r).sum(-1), 0)
                         / (d2 * d2) * self.areas[xi] * self.areas[fj])
                    blocked = self.caster.segments_blocked(pa.reshape(-1, 3), pb.reshape(-1, 3)).reshape(w.shape)
                    np.add.at(num, k, (w * ~blocked).sum(1))
                    np.add.at(den, k, w.sum(1))
                    # a facet with every weighted ray blocked (or none) while the block is visible: partly visible
                    self.rays += int(w.size)
                    hidden = np.zeros(blk.size, dtype=bool)
                    np.logical_or.at(hidden, k, ((w > 0) & blocked).any(1))
                    hid.append(hidden)
                vis = np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)
                # any blocked ray makes a visible block "partly visible" (split further / exact near field)
                partly = (hid[0] | hid[1]) & (vis > 0)
                v[blk] = np.where(partly, np.minimum(vis, 1.0 - 1e-9), vis)
                s = e
            self.blocks += int(need.size)
        self.seconds += time.perf_counter() - t0
        return v

