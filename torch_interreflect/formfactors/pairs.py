"""Facet pairs of the quadrature: which pairs exchange light (culling), and how each is integrated
(classification into shared-edge, shared-vertex, straddling and regular pairs, and the Gauss order of each).

On the CPU both run as compiled loops over pairs (:mod:`._numba_pairs`, every core, no ``[P, 4, 4]``
temporaries; the facing test fills one ``[F, F]`` bool mask in a single pass, then lists its pairs); elsewhere,
or without numba (``TI_DISABLE_NUMBA=1``), in torch, which is the reference the loops follow
(``tests/formfactors/test_pairs.py`` checks they agree).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..geometry._polygon import facing_matrix, signed_distances
from ..geometry.scene import Scene
from .compiled import launch, loops
from .memory import check_memory, dense_kernel_bytes
from .pair_contacts import CUT_MIN, shared_segments
from .rules import default_adjacent_order, order_for

__all__ = ["SPARSE_DENSITY", "PairClasses", "classify_pairs", "copy_tie", "corner_edge_contacts", "facing_pairs",
           "order_pairs", "rule_groups"]

#: With ``layout="auto"``, a matrix is stored sparse only when at most this share of its entries is nonzero.
SPARSE_DENSITY = 0.25


def facing_pairs(sc: Scene, eps: float, output: tuple[str, int]) -> tuple[Tensor, Tensor]:
    """Pairs ``i < j`` of mutually facing facets (float64 CPU scene); checks the memory before each big step.

    ``output``: the layout of the result (``"auto"`` is dense when more than ``SPARSE_DENSITY`` is nonzero) and
    the bytes per entry of its dtype.
    """
    F = sc.num_facets
    layout, itemsize = output
    dense = layout == "dense"
    remedy = ("use ti.hierarchical_form_factors(scene) (no [F, F] matrix: memory grows like F·leaf_size), or a "
              "coarser mesh")
    what = f"form_factors on {F} facets"
    check_memory(dense_kernel_bytes(F, None, dense, itemsize), what + " ([F, F] facing matrices)", remedy)
    kern = loops("pairs")
    if kern is None:
        front = facing_matrix(sc.corners, sc.normals, sc.centroids, eps)
        upper = torch.triu(front & front.T, diagonal=1)
        del front
        pairs = int(upper.sum())
    else:
        c, n, m = (t.detach().contiguous().numpy() for t in (sc.corners, sc.normals, sc.centroids))
        counts = np.zeros(F, dtype=np.int64)
        mask = np.empty((F, F), dtype=np.bool_)  # upper triangle written: one pass of the facing tests
        launch(kern.facing_mask, c, n, m, float(eps), mask, counts)
        pairs = int(counts.sum())
    dense = dense or (layout == "auto" and 2 * pairs > SPARSE_DENSITY * F * F)
    check_memory(dense_kernel_bytes(F, pairs, dense, itemsize), what + f" ({pairs} facet pairs)", remedy)
    if kern is None:
        iu, ju = torch.nonzero(upper, as_tuple=True)
        return iu, ju
    start = np.zeros(F, dtype=np.int64)
    np.cumsum(counts[:-1], out=start[1:])
    iu, ju = np.empty(pairs, dtype=np.int64), np.empty(pairs, dtype=np.int64)
    launch(kern.mask_pairs, mask, start, iu, ju)
    return torch.from_numpy(iu), torch.from_numpy(ju)


@dataclass
class PairClasses:
    """How each pair ``(dom, tgt)`` is integrated: shared edge / vertex (graded rules), straddling (clipped),
    or regular (Gauss order from the distance / size ratio). All fields ``[P]``."""

    order: Tensor  # Gauss order per direction for a regular pair
    rho: Tensor  # centroid distance / larger diameter
    has_edge: Tensor  # the pair shares an edge (edge-graded rule)
    has_vertex: Tensor  # the pair shares a vertex only (vertex-graded rule)
    shift: Tensor  # rotation of the domain's corners that puts the shared edge / vertex first
    clip_t: Tensor  # a target corner lies behind the domain's plane: clip the target
    clip_d: Tensor  # a domain corner lies behind the target's plane: integrate over the clipped domain
    n_adj: int  # Gauss order of the graded rules


def order_pairs(areas: Tensor, iu: Tensor, ju: Tensor, tie: float = 0.0) -> tuple[Tensor, Tensor]:
    """``(dom, tgt)``: each pair ``(iu, ju)`` with its smaller facet (the integration domain) first; ties keep
    ``iu`` first.

    Args:
        areas: Facet areas (m²).
        iu, ju: The pairs' facets.
        tie: Areas within this of one another (relative, in float64) are a tie. The moments pass the rounding
            between translated copies of a facet (:func:`copy_tie`), so that copies keep the same domain; 0 (the
            constant basis): only equal areas.

    Returns:
        ``(dom, tgt)``.

    Shape:
        - areas: ``[F]`` (m²); iu, ju and the outputs: ``[P]``
    """
    kern = loops("pairs")
    if kern is None or areas.device.type != "cpu":
        swap = areas[iu].double() > areas[ju].double() * (1.0 + tie)  # as the compiled loop: in float64
        return torch.where(swap, ju, iu), torch.where(swap, iu, ju)
    dom, tgt = torch.empty_like(iu), torch.empty_like(ju)
    launch(kern.order_pairs, *(t.detach().contiguous().numpy() for t in (areas, iu, ju)), float(tie), dom.numpy(),
           tgt.numpy())
    return dom, tgt


def copy_tie(dtype: torch.dtype) -> float:
    """The relative rounding between translated copies of a facet in a scene of ``dtype``: of their areas, and of
    their corners relative to one of them over the scene's size.

    Args:
        dtype: The scene's floating dtype.

    Returns:
        1e-12 in float64 (a piece far from the origin loses digits in its corners' differences), 16 ulp (1.9e-6) in
        float32; at most 2e-6, so that coarser dtypes (float16, bfloat16) find only copies that agree to that.
    """
    return min(max(1e-12, 16.0 * torch.finfo(dtype).eps), 2e-6)


def classify_pairs(sc: Scene, dom: Tensor, tgt: Tensor, tol: float, adjacent_order: int | None,
                   eps: float) -> PairClasses:
    """Classify pairs ``(dom, tgt)``: shared edge / shared vertex / straddling / regular, and the Gauss orders."""
    corners, normals, cent, diam = sc.corners, sc.normals, sc.centroids, sc.diameters
    P = dom.numel()
    radius = (corners - cent[:, None, :]).norm(dim=-1).max(dim=1).values
    n_adj = adjacent_order or default_adjacent_order(tol)
    kern = loops("pairs")
    if kern is not None and corners.device.type == "cpu":
        rho = torch.empty(P, dtype=torch.float64)
        has_edge, has_vertex, clip_t, clip_d = (torch.empty(P, dtype=torch.bool) for _ in range(4))
        shift, order = torch.empty(P, dtype=torch.int64), torch.empty(P, dtype=torch.int64)
        args = [t.detach().contiguous().numpy() for t in (corners, normals, cent, diam, radius, dom, tgt)]
        launch(kern.classify, *args, float(eps), max(-math.log10(tol), 1.0),
               *(t.numpy() for t in (rho, order, has_edge, has_vertex, shift, clip_t, clip_d)))
        return PairClasses(order, rho, has_edge, has_vertex, shift, clip_t, clip_d, n_adj)
    dist = (cent[dom] - cent[tgt]).norm(dim=-1)
    rho = dist / torch.maximum(diam[dom], diam[tgt])
    order = order_for(rho, tol)
    # shared edges / vertices are only possible where the bounding spheres touch
    has_edge = torch.zeros(P, dtype=torch.bool)
    has_vertex = torch.zeros(P, dtype=torch.bool)
    shift = torch.zeros(P, dtype=torch.int64)
    near = torch.nonzero(dist <= (radius[dom] + radius[tgt]) * (1 + 1e-6)).reshape(-1)
    if near.numel():
        cd, ct = corners[dom[near]], corners[tgt[near]]
        tol_v = 1e-7 * diam[dom[near]]
        match = ((cd[:, :, None, :] - ct[:, None, :, :]).norm(dim=-1) <= tol_v[:, None, None]).any(-1)
        nxt_distinct = (cd - torch.roll(cd, -1, 1)).norm(dim=-1) > tol_v[:, None]
        edge_k = match & torch.roll(match, -1, 1) & nxt_distinct  # edge k→k+1 of the domain is shared
        e, vtx = edge_k.any(1), match.any(1) & ~edge_k.any(1)
        has_edge[near], has_vertex[near] = e, vtx
        first_edge = torch.argmax(edge_k.to(torch.int8), dim=1)
        first_vert = torch.argmax(match.to(torch.int8), dim=1)
        shift[near] = torch.where(e, first_edge, torch.where(vtx, first_vert, torch.zeros_like(first_edge)))
    # straddling: a target corner strictly behind the domain's plane, or a domain corner behind the target's
    clip_t = torch.zeros(P, dtype=torch.bool)
    clip_d = torch.zeros(P, dtype=torch.bool)
    for s in range(0, P, 1 << 20):
        a, b = dom[s : s + (1 << 20)], tgt[s : s + (1 << 20)]
        clip_t[s : s + (1 << 20)] = (signed_distances(corners[b], cent[a], normals[a]) < -eps).any(1)
        clip_d[s : s + (1 << 20)] = (signed_distances(corners[a], cent[b], normals[b]) < -eps).any(1)
    return PairClasses(order, rho, has_edge, has_vertex, shift, clip_t, clip_d, n_adj)


def corner_edge_contacts(sc: Scene, dom: Tensor, tgt: Tensor, cls: PairClasses) -> tuple[Tensor, Tensor, PairClasses]:
    """Pairs that share one corner and, from it, lie along the same line (a plate cut at other places than its
    neighbour: the shorter edge lies wholly on the longer one) touch along that edge: the facet of the shorter edge
    becomes the domain (the pair turned around where need be, its straddling flags with it), so that the rule graded
    toward the shared corner (toward both edges from it) is graded along the whole contact. Returns
    ``(dom, tgt, cls)``.

    Measured on a unit floor and a 0.6 m wall along its edge from the floor's corner to 1.5 m (the exchange against
    the two cut at each other's ends): 2.5e-2 / 4.0e-3 off at quadrature tol 1e-3 / 1e-6 with the floor's corner
    graded on the wall (the contact beyond the floor's edge not graded), 9.5e-8 / 2.3e-9 turned around; the edge rule
    there left 7.9e-6 / 1.2e-7.
    """
    idx = torch.nonzero(cls.has_vertex).reshape(-1)
    if idx.numel() == 0:
        return dom, tgt, cls
    c = sc.corners.detach()
    kern = loops("contacts") if c.dtype == torch.float64 and c.device.type == "cpu" else None
    if kern is not None:  # the same per pair in a compiled loop (float64 on the CPU, as the moments take it)
        wholly = torch.zeros(idx.numel(), dtype=torch.bool)
        first = torch.zeros(idx.numel(), dtype=torch.int64)
        kern.corner_edge_turns(c.contiguous().numpy(), sc.diameters.detach().contiguous().numpy(), idx.numpy(),
                               dom.contiguous().numpy(), tgt.contiguous().numpy(), CUT_MIN, wholly.numpy(),
                               first.numpy())
        first = first[wholly]
    else:
        tol = 1e-7 * torch.maximum(sc.diameters[dom[idx]], sc.diameters[tgt[idx]]).detach()
        over, s0, s1 = shared_segments(c[tgt[idx]], c[dom[idx]], tol)
        wholly = (over & (s0 <= CUT_MIN) & (s1 >= 1.0 - CUT_MIN)).any(1)  # a target edge wholly on the domain's
        cd, ct = c[tgt[idx[wholly]]], c[dom[idx[wholly]]]  # the turned pairs' domain is the old target
        shared = ((cd[:, :, None, :] - ct[:, None, :, :]).norm(dim=-1) <= tol[wholly][:, None, None]).any(-1)
        first = torch.argmax(shared.to(torch.int8), 1)
    turn = idx[wholly]
    if turn.numel() == 0:
        return dom, tgt, cls
    dom, tgt = dom.clone(), tgt.clone()
    dom[turn], tgt[turn] = tgt[turn], dom[turn].clone()
    clip_t, clip_d, shift = cls.clip_t.clone(), cls.clip_d.clone(), cls.shift.clone()
    clip_t[turn], clip_d[turn] = cls.clip_d[turn], cls.clip_t[turn]
    shift[turn] = first  # the shared corner first, as classify_pairs puts it
    return dom, tgt, PairClasses(cls.order, cls.rho, cls.has_edge, cls.has_vertex, shift, clip_t, clip_d, cls.n_adj)


def rule_groups(cls: PairClasses) -> tuple[list[tuple[str, Tensor, int]], Tensor]:
    """``(groups, clipped)``: ``(rule kind, pair indices, order)`` for the unclipped pairs (edge-graded, then
    vertex-graded, then plain Gauss by ascending order; indices ascending in each), and the clipped pairs."""
    # one key per pair and one stable sort: 0 edge, 1 vertex, 1 + n plain of order n, 64 clipped
    kern = loops("pairs")
    if kern is not None and cls.order.device.type == "cpu":
        idx = torch.empty(cls.order.numel(), dtype=torch.int64)
        counts_np = np.zeros(65, dtype=np.int64)
        launch(kern.rule_buckets, *(t.contiguous().numpy() for t in (cls.has_edge, cls.has_vertex, cls.order,
                                                                     cls.clip_d)), idx.numpy(), counts_np)
        counts = counts_np.tolist()
    else:
        key = torch.where(cls.has_edge, 0, torch.where(cls.has_vertex, 1, 1 + cls.order))
        key = torch.where(cls.clip_d, 64, key)
        keys, idx = torch.sort(key, stable=True)
        counts = torch.bincount(keys, minlength=65).tolist()
    parts = torch.split(idx, counts)
    groups: list[tuple[str, Tensor, int]] = []
    for k, sel in enumerate(parts[:64]):
        if sel.numel():
            kind, n = ("edge", cls.n_adj) if k == 0 else ("vertex", cls.n_adj) if k == 1 else ("plain", k - 1)
            groups.append((kind, sel, n))
    return groups, parts[64]
