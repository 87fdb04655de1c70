"""Compiled CPU loops (numba) for the contacts of facet pairs (internal; see :mod:`.pair_contacts` and
:func:`.pairs.corner_edge_contacts`).

Each loop does per pair what the torch reference does with ``[P, 4, 4, 3]`` temporaries, with the same arithmetic
(projections summed x, y, z; Euclidean norms as square roots of summed squares), so the contacts agree with the torch
path except where a distance lies within rounding of its tolerance. The loops are serial: a scene has tens to
thousands of candidate pairs at a few hundred flops each, less than a parallel launch costs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _on_boundary(P, k, Q, tol):
    """Corner ``k`` of the quad ``P [4, 3]`` lies within ``tol`` of an edge of the quad ``Q [4, 3]``."""
    x0, x1, x2 = P[k, 0], P[k, 1], P[k, 2]
    for m in range(4):
        mb = (m + 1) % 4
        a0, a1, a2 = Q[m, 0], Q[m, 1], Q[m, 2]
        d0, d1, d2 = Q[mb, 0] - a0, Q[mb, 1] - a1, Q[mb, 2] - a2
        t = ((x0 - a0) * d0 + (x1 - a1) * d1 + (x2 - a2) * d2) / max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
        t = min(max(t, 0.0), 1.0)
        f0, f1, f2 = x0 - (a0 + t * d0), x1 - (a1 + t * d1), x2 - (a2 + t * d2)
        if math.sqrt(f0 * f0 + f1 * f1 + f2 * f2) <= tol:
            return True
    return False


@njit(cache=True, inline="always")
def _shared(A, k, B, tol):
    """Edge ``k`` of the quad ``A`` (corner ``k`` to ``k + 1``) against the edges of ``B``: ``(over, s0, s1)``, whether
    it shares a segment longer than ``tol`` with one of them (collinear within ``tol``), and that segment along it
    (0 to 1: the whole edge) from the first such edge of ``B`` (``(0, 0)`` of its first edge when none)."""
    kb = (k + 1) % 4
    a0, a1, a2 = A[k, 0], A[k, 1], A[k, 2]
    d0, d1, d2 = A[kb, 0] - a0, A[kb, 1] - a1, A[kb, 2] - a2
    L2 = d0 * d0 + d1 * d1 + d2 * d2
    den = max(L2, 1e-300)
    first0 = first1 = 0.0
    for m in range(4):
        mb = (m + 1) % 4
        c0, c1, c2 = B[m, 0] - a0, B[m, 1] - a1, B[m, 2] - a2
        e0, e1, e2 = B[mb, 0] - a0, B[mb, 1] - a1, B[mb, 2] - a2
        tc = (c0 * d0 + c1 * d1 + c2 * d2) / den
        te = (e0 * d0 + e1 * d1 + e2 * d2) / den
        s0 = max(min(tc, te), 0.0)
        s1 = min(max(tc, te), 1.0)
        if m == 0:
            first0, first1 = s0, s1
        g0, g1, g2 = c0 - tc * d0, c1 - tc * d1, c2 - tc * d2
        h0, h1, h2 = e0 - te * d0, e1 - te * d1, e2 - te * d2
        if (math.sqrt(g0 * g0 + g1 * g1 + g2 * g2) <= tol and math.sqrt(h0 * h0 + h1 * h1 + h2 * h2) <= tol
                and tol * tol < L2 and (s1 - s0) * math.sqrt(L2) > tol):
            return True, s0, s1
    return False, first0, first1


@njit(cache=True, inline="always")
def _edge_length(A, k):
    kb = (k + 1) % 4
    d0, d1, d2 = A[kb, 0] - A[k, 0], A[kb, 1] - A[k, 1], A[kb, 2] - A[k, 2]
    return math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(cache=True)
def _shortest_shared(A, B, tol, s0, s1):
    """The shortest edge of ``A`` that shares a segment with an edge of ``B`` (the first of equal ones; 0 when
    none), its length (``inf`` when none), whether there is one; ``s0, s1 [4]`` receive every edge's segment."""
    best, k_best, any_ = math.inf, 0, False
    for k in range(4):
        over, s0[k], s1[k] = _shared(A, k, B, tol)
        if over:
            any_ = True
            ln = _edge_length(A, k)
            if ln < best:
                best, k_best = ln, k
    return k_best, best, any_


@njit(cache=True)
def contacts(corners, diam, cand, dom, tgt, touch_edge, touch_vertex, shift, swapped, cut):
    """:func:`.pair_contacts.contacts` on the candidate pairs ``cand`` (near, not yet touching), in place on the
    pair arrays ``dom, tgt, touch_edge, touch_vertex, shift, swapped, cut [P, 2]``."""
    s0d, s1d, s0t, s1t = np.empty(4), np.empty(4), np.empty(4), np.empty(4)
    for p in cand:
        i, j = dom[p], tgt[p]
        cd, ct = corners[i], corners[j]
        tol = 1e-7 * max(diam[i], diam[j])
        k_d = k_t = -1
        for k in range(4):
            if k_d < 0 and _on_boundary(cd, k, ct, tol):
                k_d = k
            if k_t < 0 and _on_boundary(ct, k, cd, tol):
                k_t = k
        if k_d < 0 and k_t < 0:  # a shared segment ends at a corner of one of the two
            continue
        kd, len_d, e = _shortest_shared(cd, ct, tol, s0d, s1d)
        kt, len_t, _ = _shortest_shared(ct, cd, tol, s0t, s1t)
        if e:  # an edge of the domain on one of the target's: graded along the shorter of the two
            swap = len_t < len_d * (1 - 1e-9)
            touch_edge[p] = True
            if swap:
                dom[p], tgt[p] = j, i
                swapped[p] = True
                shift[p] = kt
                cut[p, 0], cut[p, 1] = s0t[kt], s1t[kt]
            else:
                shift[p] = kd
                cut[p, 0], cut[p, 1] = s0d[kd], s1d[kd]
        elif not touch_vertex[p]:  # only a corner on the other's boundary: graded toward it
            touch_vertex[p] = True
            if k_d >= 0:
                shift[p] = k_d
            else:
                dom[p], tgt[p] = j, i
                swapped[p] = True
                shift[p] = k_t


@njit(cache=True)
def corner_edge_turns(corners, diam, idx, dom, tgt, cut_min, turn, shift):
    """:func:`.pairs.corner_edge_contacts` on the pairs ``idx`` that share a corner: ``turn[t]`` where an edge of
    the target lies wholly on an edge of the domain (then ``shift[t]``: the turned pair's corner shared with the
    other facet, its first)."""
    s0, s1 = np.empty(4), np.empty(4)
    for t in range(idx.shape[0]):
        p = idx[t]
        cd, ct = corners[dom[p]], corners[tgt[p]]
        tol = 1e-7 * max(diam[dom[p]], diam[tgt[p]])
        wholly = False
        for k in range(4):
            over, s0[k], s1[k] = _shared(ct, k, cd, tol)
            if over and s0[k] <= cut_min and s1[k] >= 1.0 - cut_min:
                wholly = True
        turn[t] = wholly
        if not wholly:
            continue
        shift[t] = 0
        for k in range(4):  # the turned pair's domain is the old target
            hit = False
            for m in range(4):
                g0, g1, g2 = ct[k, 0] - cd[m, 0], ct[k, 1] - cd[m, 1], ct[k, 2] - cd[m, 2]
                if math.sqrt(g0 * g0 + g1 * g1 + g2 * g2) <= tol:
                    hit = True
            if hit:
                shift[t] = k
                break
