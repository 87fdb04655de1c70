"""The cluster tree of the hierarchical kernel and the traversal that splits (root, root) into blocks.

:func:`build_tree` builds a binary tree over the facets (split by normal direction until a cluster's normals are
coherent, then spatially at the median); :func:`traverse` classifies cluster pairs as zero blocks (exact: one
lies behind the other's facet planes), far blocks (separable kernel, with a visible fraction) or near leaf pairs
(exact quadrature). See :mod:`torch_interreflect.formfactors.hierarchical` for the method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

__all__ = ["NORMAL_SPLIT", "ClusterTree", "build_tree", "leaf_pairs", "traverse"]

#: Clusters whose normals deviate from their mean by more than this (``max |n_i − axis|``) are split by normal.
NORMAL_SPLIT = 0.3

# --------------------------------------------------------------------------------------------------- tree
@dataclass
class ClusterTree:
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


def build_tree(corners: np.ndarray, normals: np.ndarray, areas: np.ndarray, leaf_size: int) -> ClusterTree:
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
        if rec["delta"][-1] > NORMAL_SPLIT:
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
    return ClusterTree(perm=order, child=np.asarray(child, dtype=np.int64), **arr)


# ----------------------------------------------------------------------------------------------- traversal
def _support(tree: ClusterTree, b: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Upper bound of ``direction·y`` over the corners ``y`` of nodes ``b`` (exact for coplanar clusters)."""
    box = np.maximum(direction * tree.lo[b], direction * tree.hi[b]).sum(1)
    ab = tree.axis[b]
    own = tree.smax[b] + ((direction - ab) * tree.centre[b]).sum(1) + np.linalg.norm(direction - ab, axis=1) * \
        tree.radius[b]
    return np.minimum(box, own)


def _behind(tree: ClusterTree, a: np.ndarray, b: np.ndarray, dist: np.ndarray, eps: float) -> np.ndarray:
    """Every corner of node b lies on or behind (within ``eps``) the plane of every facet of node a."""
    reach = dist + tree.radius[a] + tree.radius[b]
    return _support(tree, b, tree.axis[a]) - tree.smin[a] + tree.delta[a] * reach <= eps


def _in_front(tree: ClusterTree, a: np.ndarray, b: np.ndarray, dist: np.ndarray, eps: float) -> np.ndarray:
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


def traverse(
    tree: ClusterTree, eta: float, eps: float, visibility: Any, progress: bool
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



def leaf_pairs(tree: ClusterTree, la: np.ndarray, lb: np.ndarray) -> tuple[Tensor, Tensor]:
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

