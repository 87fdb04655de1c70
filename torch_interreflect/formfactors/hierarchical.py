"""Hierarchical (clustered) form factors for large scenes: exact near field, separable far field.

The dense kernel (:func:`~torch_interreflect.form_factors`) costs ``O(F²)`` memory and time; at 20,000 facets its
pair lists alone exceed 20 GB. :func:`hierarchical_form_factors` instead builds a binary tree over the facets
(split by normal direction until a cluster's normals are coherent, then spatially at the median) and splits
the interaction of the root with itself recursively, as in hierarchical radiosity:

- **Zero blocks** (exact): every point of one cluster lies on or behind every facet plane of the other; such
  facets never exchange light (coplanar walls, back-to-back faces).
- **Far blocks** (approximated): clusters A and B whose radii are small against their distance,
  ``r_A + r_B ≤ eta·d``, and each lying entirely on or in front of every facet plane of the other (so the
  exact kernel needs no clipping between them). With ``ω = (c_B − c_A)/d``:

      F_ij ≈ (n_i·ω) (−n_j·ω) A_j V_AB / (π d²),     i ∈ A, j ∈ B   (and the same with i, j swapped)

  which is separable: its product with ``x`` needs only the cluster moments ``M_B = Σ_j n_j A_j x_j`` (one
  upward pass over the tree) and one downward pass, ``O(F + blocks)`` per product. ``A_i F_ij = A_j F_ji``
  holds exactly, so the symmetric form used by conjugate gradients stays symmetric. ``V_AB`` is a
  kernel-weighted visible fraction from ``visibility_samples²`` Embree rays between sample facets of the two
  clusters, cast only where a third facet could block (the plane-group test of the dense kernel, on cluster
  bounds); a partly visible block is split further until both sides are leaves.
- **Near field** (exact): leaf pairs that are neither zero nor far: every facet pair is evaluated by the dense
  kernel's quadrature (Lambert's contour formula, graded rules at shared edges, per-point visibility) and stored
  as a sparse CSR matrix.

Memory is ``O(F·leaf_size·(near leaves))`` for the near field plus ``O(blocks)`` for the far field, nothing
``[F, F]``. After construction every product is plain torch (CPU or CUDA, float32 or float64).

Lights: :func:`~torch_interreflect.layers.light_geometry` (``"sky"`` from the row sums, area lights from one
product) and :func:`~torch_interreflect.lights.sky` accept the operator as they accept a
:class:`~torch_interreflect.FormFactors`; ``lights.sky``'s default back-face test builds an ``[F, F]`` facing
matrix and casts rays from every facet with ray-cast visibility, so above ~20,000 facets pass ``backfaces=False``
or use ``light_geometry("sky", ...)``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..errors import ShapeError, ValueRangeError
from ..geometry.scene import Scene

__all__ = ["HierarchicalFormFactors", "hierarchical_form_factors"]

#: Clusters whose normals deviate from their mean by more than this (``max |n_i − axis|``) are split by normal.
_NORMAL_SPLIT = 0.3


# --------------------------------------------------------------------------------------------------- tree
@dataclass
class _Tree:
    """Binary cluster tree; facets permuted (``perm[position] = facet``) so each node is a contiguous range."""

    perm: np.ndarray
    start: np.ndarray
    end: np.ndarray
    parent: np.ndarray
    child: np.ndarray  # [nodes, 2], -1 for leaves
    depth: np.ndarray
    centre: np.ndarray  # area-weighted centroid [nodes, 3]
    radius: np.ndarray  # bounding sphere of the corners about the centre
    axis: np.ndarray  # unit mean normal
    delta: np.ndarray  # max |n_i − axis|
    smin: np.ndarray  # min / max of axis·corner
    smax: np.ndarray
    lo: np.ndarray  # corner bounding box
    hi: np.ndarray


def _build_tree(corners: np.ndarray, normals: np.ndarray, areas: np.ndarray, leaf_size: int) -> _Tree:
    F = len(areas)
    cent = corners.mean(1)
    order = np.arange(F)
    rec: dict[str, list] = {k: [] for k in
                            ("start", "end", "parent", "depth", "centre", "radius", "axis", "delta", "smin", "smax",
                             "lo", "hi")}
    child: list[list[int]] = []
    stack = [(0, F, -1, 0, 0)]
    while stack:
        s, e, par, dep, which = stack.pop()
        node = len(child)
        child.append([-1, -1])
        if par >= 0:
            child[par][which] = node
        idx = order[s:e]
        c, n, a = corners[idx], normals[idx], areas[idx]
        centre = (cent[idx] * a[:, None]).sum(0) / a.sum()
        axis = (n * a[:, None]).sum(0)
        norm = np.linalg.norm(axis)
        axis = axis / norm if norm > 1e-12 else n[0]
        proj = c.reshape(-1, 3) @ axis
        flat = c.reshape(-1, 3)
        for key, val in (("start", s), ("end", e), ("parent", par), ("depth", dep), ("centre", centre),
                         ("radius", np.linalg.norm(flat - centre, axis=1).max()), ("axis", axis),
                         ("delta", np.linalg.norm(n - axis, axis=1).max()), ("smin", proj.min()),
                         ("smax", proj.max()), ("lo", flat.min(0)), ("hi", flat.max(0))):
            rec[key].append(val)
        size = e - s
        if size <= leaf_size:
            continue
        if rec["delta"][-1] > _NORMAL_SPLIT:
            # split by normal: along the main direction of the normals' spread, at the gap nearest the middle
            _, v = np.linalg.eigh(np.cov(n.T))
            key = n @ v[:, -1]
            srt = np.argsort(key, kind="stable")
            gaps = np.nonzero(np.diff(key[srt]) > 0.05)[0] + 1
            cut = int(gaps[np.argmin(np.abs(gaps - size / 2))]) if gaps.size else size // 2
        else:
            ext = cent[idx].max(0) - cent[idx].min(0)
            srt = np.argsort(cent[idx, int(np.argmax(ext))], kind="stable")
            cut = size // 2
        order[s:e] = idx[srt]
        stack.append((s + cut, e, node, dep + 1, 1))
        stack.append((s, s + cut, node, dep + 1, 0))
    arr = {k: np.asarray(v) for k, v in rec.items()}
    return _Tree(perm=order, child=np.asarray(child, dtype=np.int64), **arr)


# ----------------------------------------------------------------------------------------------- traversal
def _support(tree: _Tree, b: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Upper bound of ``direction·y`` over the corners ``y`` of nodes ``b`` (exact for coplanar clusters)."""
    box = np.maximum(direction * tree.lo[b], direction * tree.hi[b]).sum(1)
    ab = tree.axis[b]
    own = tree.smax[b] + ((direction - ab) * tree.centre[b]).sum(1) + np.linalg.norm(direction - ab, axis=1) * \
        tree.radius[b]
    return np.minimum(box, own)


def _behind(tree: _Tree, a: np.ndarray, b: np.ndarray, dist: np.ndarray, eps: float) -> np.ndarray:
    """Every corner of node b lies on or behind (within ``eps``) the plane of every facet of node a."""
    reach = dist + tree.radius[a] + tree.radius[b]
    return _support(tree, b, tree.axis[a]) - tree.smin[a] + tree.delta[a] * reach <= eps


def _in_front(tree: _Tree, a: np.ndarray, b: np.ndarray, dist: np.ndarray, eps: float) -> np.ndarray:
    """Every corner of node b lies on or in front of (within ``eps``) the plane of every facet of node a, so the
    kernel needs no clipping between the two clusters."""
    reach = dist + tree.radius[a] + tree.radius[b]
    low_b = -_support(tree, b, -tree.axis[a])  # lower bound of axis_a·y over b
    return low_b - tree.smax[a] - tree.delta[a] * reach >= -eps


@dataclass
class _Blocks:
    a: list[np.ndarray] = field(default_factory=list)
    b: list[np.ndarray] = field(default_factory=list)
    vis: list[np.ndarray] = field(default_factory=list)


def _traverse(
    tree: _Tree, eta: float, eps: float, visibility: Any, progress: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """Split (root, root) into zero, far and near-leaf pairs. Returns far ``(a, b, V)`` and near leaf ``(a, b)``."""
    leaf = tree.child[:, 0] < 0
    pa = np.zeros(1, dtype=np.int64)
    pb = np.zeros(1, dtype=np.int64)
    far = _Blocks()
    near_a: list[np.ndarray] = []
    near_b: list[np.ndarray] = []
    stats = {"zero_blocks": 0, "visited": 0, "refined_for_visibility": 0}
    bar = tqdm(desc="cluster pairs", unit="pair", leave=False, disable=None if progress else True, mininterval=1.0)
    while pa.size:
        stats["visited"] += pa.size
        bar.update(pa.size)
        same = pa == pb
        dvec = tree.centre[pb] - tree.centre[pa]
        dist = np.linalg.norm(dvec, axis=1)
        zero = ~same & (_behind(tree, pa, pb, dist, eps) | _behind(tree, pb, pa, dist, eps))
        stats["zero_blocks"] += int(zero.sum())
        rsum = tree.radius[pa] + tree.radius[pb]
        omega = dvec / np.maximum(dist, 1e-300)[:, None]
        cos_a = (tree.axis[pa] * omega).sum(1) - tree.delta[pa]
        cos_b = -(tree.axis[pb] * omega).sum(1) - tree.delta[pb]
        adm = ~same & ~zero & (rsum <= eta * dist) & (cos_a > 0) & (cos_b > 0)
        if adm.any():
            idx = np.nonzero(adm)[0]
            ok = _in_front(tree, pa[idx], pb[idx], dist[idx], eps) & _in_front(tree, pb[idx], pa[idx], dist[idx], eps)
            adm[idx[~ok]] = False
        both_leaves = leaf[pa] & leaf[pb]
        split = ~zero & ~adm & ~both_leaves
        near = ~zero & ~adm & both_leaves
        if adm.any():
            ia, ib = pa[adm], pb[adm]
            v = visibility(ia, ib)
            partly = (v > 0) & (v < 1)
            partial = partly & ~both_leaves[adm]
            keep = ~partly & (v > 0)
            far.a.append(ia[keep])
            far.b.append(ib[keep])
            far.vis.append(v[keep])
            stats["zero_blocks"] += int((v <= 0).sum())
            stats["refined_for_visibility"] += int(partial.sum())
            where = np.nonzero(adm)[0]
            split[where[partial]] = True
            # partly visible leaf pairs: exact near field (per-point visibility) rather than one averaged V
            near[where[partly & both_leaves[adm]]] = True
        near_a.append(pa[near])
        near_b.append(pb[near])
        # children of the pairs to split
        sa, sb = pa[split], pb[split]
        self_pair = sa == sb
        new_a, new_b = [], []
        if self_pair.any():
            c = tree.child[sa[self_pair]]
            new_a += [c[:, 0], c[:, 0], c[:, 1]]
            new_b += [c[:, 0], c[:, 1], c[:, 1]]
        oa, ob = sa[~self_pair], sb[~self_pair]
        split_a = ~leaf[oa] & (leaf[ob] | (tree.radius[oa] >= tree.radius[ob]))
        ca = tree.child[oa[split_a]]
        new_a += [ca[:, 0], ca[:, 1]]
        new_b += [ob[split_a], ob[split_a]]
        cb = tree.child[ob[~split_a]]
        new_a += [oa[~split_a], oa[~split_a]]
        new_b += [cb[:, 0], cb[:, 1]]
        pa, pb = np.concatenate(new_a), np.concatenate(new_b)
    bar.close()
    cat = lambda x, dt: np.concatenate(x) if x else np.zeros(0, dtype=dt)  # noqa: E731
    return (cat(far.a, np.int64), cat(far.b, np.int64), cat(far.vis, np.float64), cat(near_a, np.int64),
            cat(near_b, np.int64), stats)


class _ClusterVisibility:
    """Visible fraction ``V_AB`` of cluster pairs from rays between sample facets, where a third facet could block."""

    def __init__(self, sc: Scene, tree: _Tree, occlusion: Literal["auto"] | bool, samples: int, eps: float,
                 caster: Any) -> None:
        from ..geometry._polygon import plane_groups

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


# ---------------------------------------------------------------------------------------------- container
class HierarchicalFormFactors:
    """Form factors of a large scene as an operator: exact sparse near field plus separable far blocks.

    Built by :func:`hierarchical_form_factors`. It stores no ``[F, F]`` tensor; :meth:`matmul` applies ``F`` in
    ``O(nnz + F + blocks)`` per column, with plain torch operations (any device, float32 or float64).
    ``A_i F_ij = A_j F_ji`` holds exactly (the far blocks are reciprocal by construction), so
    :func:`~torch_interreflect.solve` can use conjugate gradients on the symmetric form.

    Attributes:
        near: Near-field ``F_ij`` (exact quadrature), sparse CSR ``[F, F]`` in the scene's facet order.
        areas: Facet areas in m², ``[F]``.
        normals: Unit facet normals, ``[F, 3]``.
        info: Seconds per stage, near-field nnz, far blocks, rays, bytes used, estimated error of a product.

    Shape:
        - near: ``[F, F]`` (sparse)
        - areas: ``[F]``
        - matmul input/output: ``[..., F, K]``

    Example:
        >>> import torch_interreflect as ti
        >>> K = ti.hierarchical_form_factors(ti.scenes.closed_box(divisions=6), leaf_size=8)
        >>> K.num_facets, K.info["far_blocks"] > 0
        (216, True)
        >>> abs(float(K.row_sums().mean()) - 1.0) < 0.01  # closed box: rows sum to 1 (within the far-field error)
        True
    """

    #: names of the tensors that make up the operator (all moved together by :meth:`to`)
    _NAMES = ("near", "areas", "normals", "points", "perm", "leaf_of", "parent", "child", "centre", "block_a",
              "block_b", "omega", "coef", "dist")

    def __init__(self, tensors: dict[str, Tensor], levels: list[Tensor], info: dict[str, Any], order: int = 1) -> None:
        for k in self._NAMES:
            setattr(self, k, tensors[k])
        # near: CSR F (exact); areas, normals [F]; points: facet centroids relative to the scene centre [F, 3];
        # perm: position -> facet; leaf_of: position -> leaf node; parent/child: tree links (child 0 at leaves);
        # centre: node centres (relative) [nodes, 3]; block_a/b, omega (unit a→b), coef = V/(π d²), dist d [K]
        self.levels = levels  # internal nodes by depth (root first)
        self.order = order
        self.info = info
        self.num_nodes = int(self.parent.numel())

    # ------------------------------------------------------------------ properties
    @property
    def num_facets(self) -> int:
        return int(self.areas.numel())

    @property
    def dtype(self) -> torch.dtype:
        return self.areas.dtype

    @property
    def device(self) -> torch.device:
        return self.areas.device

    @property
    def num_far_blocks(self) -> int:
        return int(self.block_a.numel())

    def _tensors(self) -> dict[str, Tensor]:
        return {k: getattr(self, k) for k in self._NAMES}

    def nbytes(self) -> int:
        """Bytes held by the operator's tensors (near field, far blocks, tree)."""
        total = 0
        for t in [*self._tensors().values(), *self.levels]:
            if t.layout == torch.sparse_csr:
                total += sum(x.numel() * x.element_size() for x in (t.crow_indices(), t.col_indices(), t.values()))
            else:
                total += t.numel() * t.element_size()
        return total

    # ------------------------------------------------------------------ products
    def far_matmul(self, x: Tensor) -> Tensor:
        """The far-field part of ``F @ x`` for ``x`` of shape ``[F, N]``.

        Order 0: ``F_ij ≈ A_j V n_iᵀ W n_j`` with ``W = −ωωᵀ/(π d²)``. Order 1 adds the first-order Taylor terms in
        the positions of both facets about their cluster centres, ``A_j V n_iᵀ (G(δ_j) − G(δ_i)) n_j`` with
        ``G(v) = (−vωᵀ − ωvᵀ + 4(ω·v)ωωᵀ)/(π d³)``, which is still separable (cluster moments ``Σ A_j x_j n_j`` and
        ``Σ A_j x_j δ_j n_jᵀ``) and still reciprocal (``G`` is odd in ω).
        """
        n_cols = x.shape[1]
        dt, dev = x.dtype, x.device
        perm = self.perm
        xp = x[perm]  # positions
        nrm = self.normals[perm]
        w = nrm * self.areas[perm, None]  # [F, 3]
        first = self.order >= 1
        m = torch.zeros(self.num_nodes, 3, n_cols, dtype=dt, device=dev)
        m.index_add_(0, self.leaf_of, w[:, :, None] * xp[:, None, :])
        if first:
            pts = self.points[perm]
            # P = Σ A_j x_j y_j n_jᵀ  [nodes, 3 (y), 3 (n), N]
            p = torch.zeros(self.num_nodes, 3, 3, n_cols, dtype=dt, device=dev)
            p.index_add_(0, self.leaf_of, (pts[:, :, None] * w[:, None, :])[..., None] * xp[:, None, None, :])
        for idx in reversed(self.levels):  # deepest internal nodes first: children are complete
            c0, c1 = self._children_of(idx)
            m[idx] = m[c0] + m[c1]
            if first:
                p[idx] = p[c0] + p[c1]
        t = torch.zeros_like(m)
        q = torch.zeros(self.num_nodes, 3, 3, n_cols, dtype=dt, device=dev) if first else None
        if first:
            s_mom = p - self.centre[:, :, None, None] * m[:, None, :, :]  # Σ A x δ nᵀ, δ = y − c
        chunk = max(1, (1 << 22) // max(9 * n_cols, 1))
        eye = torch.eye(3, dtype=dt, device=dev)
        for s in range(0, self.num_far_blocks, chunk):
            a, b = self.block_a[s : s + chunk], self.block_b[s : s + chunk]
            om, c = self.omega[s : s + chunk], self.coef[s : s + chunk]
            for src, dst, o in ((b, a, om), (a, b, -om)):
                ms = m[src]  # [k, 3, N]
                wm = torch.einsum("kx,kxn->kn", o, ms)  # ω·M
                contrib = o[:, :, None] * (-c[:, None] * wm)[:, None, :]
                if first:
                    kap = (c / self.dist[s : s + chunk])[:, None]  # V / (π d³)
                    sb = s_mom[src]  # [k, 3, 3, N]
                    sw = torch.einsum("kynN,kn->kyN", sb, o)  # S ω
                    tr = sb.diagonal(dim1=1, dim2=2).sum(-1)  # [k, N]
                    wsw = torch.einsum("ky,kyN->kN", o, sw)
                    ca = self.centre[dst]
                    oc = (o * ca).sum(-1)[:, None]  # ω·c_A
                    cm = torch.einsum("kx,kxn->kn", ca, ms)  # c_A·M
                    vec = (-sw - o[:, :, None] * tr[:, None, :] + 4 * o[:, :, None] * wsw[:, None, :]
                           - ca[:, :, None] * wm[:, None, :] - o[:, :, None] * cm[:, None, :]
                           + 4 * (oc * wm)[:, None, :] * o[:, :, None])
                    contrib = contrib + kap[:, :, None] * vec
                    qq = (o[:, :, None, None] * ms[:, None, :, :]
                          + wm[:, None, None, :] * (eye - 4 * o[:, :, None] * o[:, None, :])[..., None])
                    q.index_add_(0, dst, kap[:, :, None, None] * qq)
                t.index_add_(0, dst, contrib)
        for idx in self.levels:  # root first: push every node's field down to its children
            c0, c1 = self._children_of(idx)
            t[c0] += t[idx]
            t[c1] += t[idx]
            if first:
                q[c0] += q[idx]
                q[c1] += q[idx]
        yp = torch.einsum("fx,fxn->fn", nrm, t[self.leaf_of])
        if first:
            yp = yp + torch.einsum("fx,fxyn,fy->fn", nrm, q[self.leaf_of], pts)
        y = torch.empty_like(yp)
        y[perm] = yp
        return y

    def _children_of(self, idx: Tensor) -> tuple[Tensor, Tensor]:
        return self.child[idx, 0], self.child[idx, 1]

    def matmul(self, x: Tensor) -> Tensor:
        """``F @ x`` for ``x`` of shape ``[..., F, K]`` (one pass with all columns); differentiable in ``x``.

        Example:
            >>> import torch, torch_interreflect as ti
            >>> K = ti.hierarchical_form_factors(ti.scenes.closed_box(divisions=3))
            >>> K.matmul(torch.ones(54, 2, dtype=K.dtype)).shape
            torch.Size([54, 2])
        """
        if not isinstance(x, Tensor) or x.ndim < 2 or x.shape[-2] != self.num_facets:
            shape = list(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ShapeError(f"x must be a tensor [..., F, K] with F = {self.num_facets} facets; got {shape}")
        if x.dtype != self.dtype or x.device != self.device:
            raise ValueError(f"x must have the operator's dtype {self.dtype} and device {self.device}; got "
                             f"{x.dtype} on {x.device} (use .to())")
        lead = x.shape[:-2]
        cols = x.movedim(-2, 0).reshape(self.num_facets, -1)
        out = self.near @ cols + self.far_matmul(cols)
        return out.reshape(self.num_facets, *lead, x.shape[-1]).movedim(0, -2)

    def rmatmul(self, x: Tensor) -> Tensor:
        """``Fᵀ @ x = A F (x / A)`` (reciprocity) for ``x`` of shape ``[F, N]``."""
        a = self.areas[:, None]
        return a * self.matmul(x / a)

    def row_sums(self) -> Tensor:
        """``Σ_j F_ij`` per facet ``[F]`` (the operator applied to ones; cached)."""
        cached = self.info.get("_row_sums")
        if isinstance(cached, Tensor) and cached.dtype == self.dtype and cached.device == self.device:
            return cached
        rs = self.matmul(torch.ones(self.num_facets, 1, dtype=self.dtype, device=self.device)).reshape(-1)
        self.info["_row_sums"] = rs
        return rs

    def to_dense(self) -> Tensor:
        """The operator as a dense ``[F, F]`` matrix (small scenes and tests only: ``O(F²)`` memory)."""
        return self.matmul(torch.eye(self.num_facets, dtype=self.dtype, device=self.device))

    def to(self, *args: Any, **kwargs: Any) -> HierarchicalFormFactors:
        """Move/cast like :meth:`torch.Tensor.to` (index tensors keep their integer dtype)."""
        probe = torch.empty(0, dtype=self.dtype, device=self.device).to(*args, **kwargs)

        def conv(t: Tensor) -> Tensor:
            return t.to(device=probe.device, dtype=probe.dtype if t.is_floating_point() else t.dtype)

        near = self.near.to(probe.device)
        if near.dtype != probe.dtype:
            near = near.to(probe.dtype)
        info = {k: v for k, v in self.info.items() if k != "_row_sums"}
        tensors = {k: conv(v) for k, v in self._tensors().items() if k != "near"}
        tensors["near"] = near
        return HierarchicalFormFactors(tensors, [conv(t) for t in self.levels], info, self.order)

    def __repr__(self) -> str:
        return (f"HierarchicalFormFactors(num_facets={self.num_facets}, near_nnz={self.info.get('near_nnz')}, "
                f"far_blocks={self.num_far_blocks}, dtype={self.dtype}, device={self.device})")


# ---------------------------------------------------------------------------------------------- builder
def hierarchical_form_factors(
    scene: Scene,
    *,
    eta: float = 0.5,
    leaf_size: int = 16,
    occlusion: Literal["auto"] | bool = "auto",
    quadrature_tol: float = 1e-6,
    visibility_samples: int = 3,
    cluster_samples: int = 4,
    order: int = 1,
    error_samples: int = 2000,
    chunk_pairs: int = 1 << 21,
    progress: bool | None = None,
) -> HierarchicalFormFactors:
    """Hierarchical form factors of a (large) scene: exact near field, separable far field (module docstring).

    Args:
        scene: The scene.
        eta: Admissibility: two clusters interact through one far block when ``r_A + r_B ≤ eta·d`` (bounding
            radii against the distance of their centres). Smaller is more accurate and slower
            (benchmarks/results/hierarchical.md, ~5,000 facets: relative RMS error of products and row sums
            1.1–1.3 % at eta = 0.5 and 0.26–0.43 % at eta = 0.3, for 1.3–1.6× the time). In a closed, bright
            scene the solved irradiance amplifies row-sum errors by about ``r / (1 − r)``.
        leaf_size: Facets per leaf cluster. Leaf pairs that are not far are evaluated exactly.
        occlusion: ``"auto"`` casts rays only where a third facet could block (near pairs and far blocks);
            ``True`` everywhere, ``False`` never.
        quadrature_tol: Relative accuracy of the near-field quadrature (as ``tol`` of
            :func:`~torch_interreflect.form_factors`).
        visibility_samples: Per-point visibility samples per direction for near pairs (as in the dense kernel).
        cluster_samples: Sample facets per cluster for a far block's visibility: where a third facet could
            block, every facet of each cluster casts ``cluster_samples`` rays to sample facets of the other, and a
            block with any blocked ray is split further (exact near field at leaf level).
        order: Far-field expansion order: 0 (the separable centre-to-centre kernel) or 1 (adds the first-order
            terms in each facet's offset from its cluster centre: about ``eta`` times smaller errors for ~3× the
            cost of a far-field product).
        error_samples: Far-block facet pairs evaluated exactly to estimate the error of a product
            (``info["estimated_rel_error"]``); 0 skips it.
        chunk_pairs: Near-field facet pairs evaluated per chunk (bounds the temporary memory).
        progress: Show progress bars (default: from 5,000 facets).

    Returns:
        A :class:`HierarchicalFormFactors` in the scene's dtype and device. ``info`` holds ``seconds_tree``,
        ``seconds_traversal``, ``seconds_far_visibility``, ``seconds_near``, ``seconds_error_estimate``,
        ``seconds``, ``near_nnz``, ``near_pairs``, ``far_blocks``, ``zero_blocks``, ``rays``, ``bytes``,
        ``estimated_rel_error`` (relative RMS error of ``F @ 1`` estimated from sampled far entries), ...

    Raises:
        TypeError: ``scene`` is not a Scene.
        ValueRangeError: a parameter outside its range.

    Shape:
        - output ``.matmul(x)``: ``[F, K] -> [F, K]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> scene = ti.scenes.cornell_box(divisions=3, dtype=torch.float64)
        >>> K = ti.hierarchical_form_factors(scene, leaf_size=8)
        >>> E = ti.solve(K, torch.full((scene.num_facets,), 0.5, dtype=torch.float64),
        ...              ti.layers.light_geometry("light", K, scene)[:, None])
        >>> E.shape
        torch.Size([153, 1])
    """
    from ..geometry._polygon import plane_eps
    from ..geometry.raycast import RayCaster
    from .quadrature import pair_values
    from .visibility import PointVisibility

    if not isinstance(scene, Scene):
        raise TypeError(f"hierarchical_form_factors expects a Scene; got {type(scene).__name__}")
    if not (isinstance(eta, (int, float)) and 0.0 < eta < 2.0):
        raise ValueRangeError(f"eta must lie in (0, 2) (cluster radii against distance); got {eta!r}")
    if isinstance(leaf_size, bool) or not isinstance(leaf_size, int) or leaf_size < 1:
        raise ValueRangeError(f"leaf_size must be an integer >= 1; got {leaf_size!r}")
    if occlusion not in ("auto", True, False):
        raise ValueError(f"occlusion must be 'auto', True or False; got {occlusion!r}")
    if not (0.0 < quadrature_tol < 1.0):
        raise ValueRangeError(f"quadrature_tol must lie in (0, 1); got {quadrature_tol}")
    for name, val in (("visibility_samples", visibility_samples), ("cluster_samples", cluster_samples)):
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ValueRangeError(f"{name} must be an integer >= 1; got {val!r}")
    if order not in (0, 1) or isinstance(order, bool):
        raise ValueRangeError(f"order must be 0 or 1; got {order!r}")
    if isinstance(error_samples, bool) or not isinstance(error_samples, int) or error_samples < 0:
        raise ValueRangeError(f"error_samples must be an integer >= 0; got {error_samples!r}")
    t_all = time.perf_counter()
    F = scene.num_facets
    if progress is None:
        progress = F >= 5000
    sc = scene.to(torch.float64).to("cpu")
    eps = plane_eps(scene)
    info: dict[str, Any] = {"eta": float(eta), "leaf_size": leaf_size, "num_facets": F}

    t = time.perf_counter()
    corners, normals, areas = (t.detach().numpy() for t in (sc.corners, sc.normals, sc.areas))
    tree = _build_tree(corners, normals, areas, leaf_size)
    info["seconds_tree"] = time.perf_counter() - t
    info["nodes"] = int(tree.parent.size)

    t = time.perf_counter()
    caster = RayCaster(sc) if occlusion is not False else None
    cvis = _ClusterVisibility(sc, tree, occlusion, cluster_samples, eps, caster)
    fa, fb, fv, na, nb, stats = _traverse(tree, float(eta), eps, cvis, progress)
    info.update(stats)
    info["seconds_traversal"] = time.perf_counter() - t - cvis.seconds
    info["seconds_far_visibility"] = cvis.seconds
    info["far_rays"] = cvis.rays

    # ------------------------------------------------------------------ near field (exact quadrature)
    t = time.perf_counter()
    perm = torch.as_tensor(tree.perm)
    qinfo: dict[str, Any] = {}
    vis = PointVisibility(sc, visibility_samples, caster) if caster is not None else None
    rows_l, cols_l, vals_l = [], [], []
    occluded = torch.zeros(F, dtype=torch.bool)
    sizes_a = tree.end[na] - tree.start[na]
    sizes_b = tree.end[nb] - tree.start[nb]
    per_pair = sizes_a * sizes_b
    n_pairs_total = 0
    bar = tqdm(total=int(per_pair.sum()), desc="near field", unit="pair", leave=False,
               disable=None if progress else True, mininterval=1.0)
    s = 0
    cum = np.cumsum(per_pair)
    while s < na.size:
        # leaf pairs until about chunk_pairs facet pairs
        base = cum[s - 1] if s else 0
        e = int(np.searchsorted(cum, base + chunk_pairs, side="right"))
        e = max(e, s + 1)
        iu, ju = _leaf_pairs(tree, na[s:e], nb[s:e])
        bar.update(int(cum[e - 1] - base))
        s = e
        iu, ju = perm[iu], perm[ju]
        iu, ju = torch.minimum(iu, ju), torch.maximum(iu, ju)  # as the dense kernel orders its pairs
        keep = _mutual_facing(sc, iu, ju, eps)
        iu, ju = iu[keep], ju[keep]
        if iu.numel() == 0:
            continue
        n_pairs_total += int(iu.numel())
        dom, tgt, value, need, vis = pair_values(
            sc, iu, ju, occlusion, quadrature_tol, None, visibility_samples, 1 << 18, False, qinfo, eps, vis
        )
        occluded[dom[need]] = True
        occluded[tgt[need]] = True
        a = sc.areas
        rows_l += [dom, tgt]
        cols_l += [tgt, dom]
        vals_l += [value / a[dom], value / a[tgt]]
    bar.close()
    if rows_l:
        rows, cols, vals = torch.cat(rows_l), torch.cat(cols_l), torch.cat(vals_l)
        nz = vals > 0
        rows, cols, vals = rows[nz], cols[nz], vals[nz]
    else:
        rows = cols = torch.zeros(0, dtype=torch.int64)
        vals = torch.zeros(0, dtype=torch.float64)
    del rows_l, cols_l, vals_l
    near = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, (F, F)).coalesce().to_sparse_csr()
    info["seconds_near"] = time.perf_counter() - t
    info.update(near_pairs=n_pairs_total, near_nnz=int(vals.numel()), near_leaf_pairs=int(na.size),
                near_points=qinfo.get("points", 0), near_rays=vis.rays if vis is not None else 0,
                seconds_near_visibility=qinfo.get("seconds_visibility", 0.0), occluded_facets=occluded)
    info["rays"] = info["near_rays"] + info["far_rays"]

    # ------------------------------------------------------------------ far blocks as tensors
    dvec = tree.centre[fb] - tree.centre[fa]
    dist = np.linalg.norm(dvec, axis=1)
    omega = dvec / np.maximum(dist, 1e-300)[:, None]
    coef = fv / (math.pi * dist * dist)
    leaf_of = np.empty(F, dtype=np.int64)
    leaves = np.nonzero(tree.child[:, 0] < 0)[0]
    for lf in leaves:
        leaf_of[tree.start[lf] : tree.end[lf]] = lf
    internal = tree.child[:, 0] >= 0
    depths = range(int(tree.depth.max()) + 1)
    levels = [torch.as_tensor(np.nonzero(internal & (tree.depth == d))[0]) for d in depths]
    levels = [lv for lv in levels if lv.numel()]
    origin = sc.centroids.detach().mean(0)
    tensors = {
        "near": near, "areas": sc.areas.detach().clone(), "normals": sc.normals.detach().clone(),
        "points": sc.centroids.detach() - origin, "perm": perm, "leaf_of": torch.as_tensor(leaf_of),
        "parent": torch.as_tensor(tree.parent), "child": torch.as_tensor(np.where(tree.child < 0, 0, tree.child)),
        "centre": torch.as_tensor(tree.centre) - origin, "block_a": torch.as_tensor(fa),
        "block_b": torch.as_tensor(fb), "omega": torch.as_tensor(omega), "coef": torch.as_tensor(coef),
        "dist": torch.as_tensor(dist),
    }
    out = HierarchicalFormFactors(tensors, levels, info, order)
    info["far_blocks"] = out.num_far_blocks

    # ------------------------------------------------------------------ error estimate from sampled far entries
    t = time.perf_counter()
    info["estimated_rel_error"] = _estimate_error(out, sc, tree, fa, fb, fv, error_samples, eps) if (
        error_samples and fa.size) else 0.0
    info["seconds_error_estimate"] = time.perf_counter() - t
    out = out.to(dtype=scene.dtype, device=scene.device)
    info = out.info
    info["bytes"] = out.nbytes()
    info["seconds"] = time.perf_counter() - t_all
    return out


def _leaf_pairs(tree: _Tree, la: np.ndarray, lb: np.ndarray) -> tuple[Tensor, Tensor]:
    """All position pairs ``(p, q)`` of the leaf pairs ``(la, lb)`` (``p < q`` within a leaf paired with itself)."""
    na = tree.end[la] - tree.start[la]
    nb = tree.end[lb] - tree.start[lb]
    cnt = na * nb
    pair_id = np.repeat(np.arange(la.size), cnt)
    off = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    p = tree.start[la][pair_id] + off // nb[pair_id]
    q = tree.start[lb][pair_id] + off % nb[pair_id]
    keep = (la[pair_id] != lb[pair_id]) | (p < q)
    return torch.as_tensor(p[keep]), torch.as_tensor(q[keep])


def _mutual_facing(sc: Scene, i: Tensor, j: Tensor, eps: float) -> Tensor:
    """Some corner of j strictly in front of i's plane and some corner of i in front of j's (the dense cull)."""
    c, n, cent = sc.corners, sc.normals, sc.centroids
    dij = torch.einsum("px,pkx->pk", n[i], c[j]) - (n[i] * cent[i]).sum(-1)[:, None]
    dji = torch.einsum("px,pkx->pk", n[j], c[i]) - (n[j] * cent[j]).sum(-1)[:, None]
    return (dij > eps).any(-1) & (dji > eps).any(-1)


def _estimate_error(K: HierarchicalFormFactors, sc: Scene, tree: _Tree, fa: np.ndarray, fb: np.ndarray,
                    fv: np.ndarray, samples: int, eps: float) -> float:
    """Relative RMS error of ``F @ 1`` from the far field, estimated by evaluating sampled far entries exactly.

    Blocks are drawn with probability proportional to their share of ``Σ_ij A_i F_ij`` (far), then one facet pair
    per draw; the relative error of those entries (unoccluded, against the dense quadrature) times the far
    share of the row sums estimates the relative error of a product with a smooth vector.
    """
    from .quadrature import pair_values

    rng = np.random.default_rng(0)
    areas, normals = sc.areas.detach().numpy(), sc.normals.detach().numpy()
    # block mass: Σ_{i∈a, j∈b} A_i F_ij = c (ω·N_a)(−ω·N_b), N = Σ n_k A_k
    wn = normals * areas[:, None]
    pref = np.concatenate([np.zeros((1, 3)), np.cumsum(wn[tree.perm], axis=0)])
    na_ = pref[tree.end] - pref[tree.start]
    om = K.omega.numpy()
    mass = K.coef.numpy() * (om * na_[fa]).sum(1) * -(om * na_[fb]).sum(1) * 2
    total_far = float(mass.sum())
    if total_far <= 0:
        return 0.0
    pick = rng.choice(fa.size, size=samples, p=mass / total_far)
    ra = rng.integers(tree.start[fa[pick]], tree.end[fa[pick]])
    rb = rng.integers(tree.start[fb[pick]], tree.end[fb[pick]])
    i, j = tree.perm[ra], tree.perm[rb]
    o, d = om[pick], K.dist.numpy()[pick]
    ni, nj = normals[i], normals[j]
    oi, oj = (ni * o).sum(1), (nj * o).sum(1)
    kern = oi * -oj / (math.pi * d * d)
    if K.order >= 1:
        pts, cen = K.points.numpy(), K.centre.numpy()

        def ngn(v: np.ndarray) -> np.ndarray:
            return (-(ni * v).sum(1) * oj - oi * (v * nj).sum(1) + 4 * (o * v).sum(1) * oi * oj) / (math.pi * d**3)

        kern = kern + ngn(pts[j] - cen[fb[pick]]) - ngn(pts[i] - cen[fa[pick]])
    approx = areas[j] * kern
    it, jt = torch.as_tensor(i), torch.as_tensor(j)
    keep = _mutual_facing(sc, it, jt, eps)
    exact = np.zeros(samples)
    if bool(keep.any()):
        _, _, value, _, _ = pair_values(sc, it[keep], jt[keep], False, 1e-4, None, 1, 1 << 18, False, {}, eps)
        # value = A_dom F_dom,tgt; we want F_ij = value / A_i
        exact[keep.numpy()] = value.numpy() / areas[i[keep.numpy()]]
    rel = float(np.sqrt(np.mean((approx - exact) ** 2) / max(np.mean(approx**2), 1e-300)))
    # far share of Σ A_i (F 1)_i
    rs = K.row_sums().numpy()
    total = float((areas * rs).sum())
    share = total_far / total if total > 0 else 0.0
    return float(rel * share)
