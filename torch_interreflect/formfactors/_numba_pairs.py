"""Compiled CPU loops (numba) over facet pairs: culling, classification and blocker tests (internal; see
:mod:`.pairs` and :func:`.visibility.blocker_candidates`).

Each loop does per pair what the torch reference does with ``[P, ...]`` temporaries, with the same arithmetic
(signed distances ``((p − o)·n)`` summed x, y, z; Euclidean norms as square roots of summed squares), so the
boolean classes agree with the torch path except where a quantity lies within rounding of its threshold.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _front(corners, normals, off, i, j, eps):
    """Some corner of facet ``j`` lies strictly in front of facet ``i``'s plane (``n_i·x = off_i``)."""
    for k in range(4):
        d = (normals[i, 0] * corners[j, k, 0] + normals[i, 1] * corners[j, k, 1]
             + normals[i, 2] * corners[j, k, 2]) - off[i]
        if d > eps:
            return True
    return False


@njit(cache=True)
def _facing_row(corners, normals, off, eps, i, mask):
    """Mark ``mask[i, j]`` for the facets ``j > i`` facing ``i`` (each partly in front of the other); the count."""
    F = corners.shape[0]
    c = 0
    for j in range(i + 1, F):
        m = _front(corners, normals, off, i, j, eps) and _front(corners, normals, off, j, i, eps)
        mask[i, j] = m
        if m:
            c += 1
    return c


@njit(cache=True, parallel=True)
def facing_mask(corners, normals, cent, eps, mask, counts):
    """Pairs ``i < j`` of facets each partly in front of the other: ``mask[i, j]`` (the upper triangle of the
    ``[F, F]`` bool ``mask`` is written) and ``counts[i]``, the pairs of row ``i``.

    Rows are taken in pairs ``(r, F − 1 − r)`` so every thread gets the same share of the triangle.
    """
    F = corners.shape[0]
    off = np.empty(F)
    for i in range(F):
        off[i] = normals[i, 0] * cent[i, 0] + normals[i, 1] * cent[i, 1] + normals[i, 2] * cent[i, 2]
    half = (F + 1) // 2
    for r in prange(half):
        lo = np.int64(r)
        hi = np.int64(F - 1 - r)
        counts[lo] = _facing_row(corners, normals, off, eps, lo, mask)
        if hi != lo:
            counts[hi] = _facing_row(corners, normals, off, eps, hi, mask)


@njit(cache=True)
def _mask_row(mask, i, m, iu, ju):
    for j in range(i + 1, mask.shape[0]):
        if mask[i, j]:
            iu[m] = i
            ju[m] = j
            m += 1


@njit(cache=True, parallel=True)
def mask_pairs(mask, start, iu, ju):
    """The pairs of :func:`facing_mask`: row ``i``'s written from ``start[i]``, ``j`` ascending."""
    F = mask.shape[0]
    half = (F + 1) // 2
    for r in prange(half):
        lo = np.int64(r)
        hi = np.int64(F - 1 - r)
        _mask_row(mask, lo, start[lo], iu, ju)
        if hi != lo:
            _mask_row(mask, hi, start[hi], iu, ju)


@njit(cache=True, inline="always")
def _dist(ax, ay, az, bx, by, bz):
    dx = ax - bx
    dy = ay - by
    dz = az - bz
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, inline="always")
def _behind(corners, cent, normals, j, i, eps):
    """Some corner of facet ``j`` lies strictly behind facet ``i``'s plane (signed distance < −eps)."""
    for k in range(4):
        d = ((corners[j, k, 0] - cent[i, 0]) * normals[i, 0] + (corners[j, k, 1] - cent[i, 1]) * normals[i, 1]
             + (corners[j, k, 2] - cent[i, 2]) * normals[i, 2])
        if d < -eps:
            return True
    return False


@njit(cache=True, parallel=True)
def classify(corners, normals, cent, diam, radius, dom, tgt, eps, digits, rho, order, has_edge, has_vertex, shift,
             clip_t, clip_d):
    """Per pair ``(dom, tgt)``: ``rho`` (centroid distance / larger diameter) and the Gauss order for ``digits``
    (:func:`gauss_order`), shared edge / shared vertex and the rotation of the domain's corners that puts it first,
    and whether the target (domain) crosses the domain's (target's) plane. See :func:`.pairs.classify_pairs`."""
    P = dom.shape[0]
    for p in prange(P):
        a = dom[p]
        b = tgt[p]
        dist = _dist(cent[a, 0], cent[a, 1], cent[a, 2], cent[b, 0], cent[b, 1], cent[b, 2])
        rho[p] = dist / max(diam[a], diam[b])
        order[p] = gauss_order(rho[p], digits)
        e = False
        vtx = False
        sh = 0
        if dist <= (radius[a] + radius[b]) * (1 + 1e-6):
            tol_v = 1e-7 * diam[a]
            mask = 0  # bit k: domain corner k coincides with a target corner
            for k in range(4):
                for l in range(4):
                    if _dist(corners[a, k, 0], corners[a, k, 1], corners[a, k, 2],
                             corners[b, l, 0], corners[b, l, 1], corners[b, l, 2]) <= tol_v:
                        mask |= 1 << k
            first_edge = -1
            first_vert = -1
            for k in range(4):
                k1 = (k + 1) % 4
                mk = (mask >> k) & 1 == 1
                mk1 = (mask >> k1) & 1 == 1
                distinct = _dist(corners[a, k, 0], corners[a, k, 1], corners[a, k, 2],
                                 corners[a, k1, 0], corners[a, k1, 1], corners[a, k1, 2]) > tol_v
                if mk and first_vert < 0:
                    first_vert = k
                if mk and mk1 and distinct and first_edge < 0:
                    first_edge = k
            e = first_edge >= 0
            vtx = first_vert >= 0 and not e
            if e:
                sh = first_edge
            elif vtx:
                sh = first_vert
        has_edge[p] = e
        has_vertex[p] = vtx
        shift[p] = sh
        clip_t[p] = _behind(corners, cent, normals, b, a, eps)
        clip_d[p] = _behind(corners, cent, normals, a, b, eps)


@njit(cache=True, inline="always")
def _corner(corners, a, b, i, k, e1, e2):
    """Coordinate ``k`` of the pair's corner ``i`` (``a``'s four, then ``b``'s): x, y, z, then along ``e1``, ``e2``."""
    f = a if i < 4 else b
    c = i % 4
    if k < 3:
        return corners[f, c, k]
    e = e1 if k == 3 else e2
    return corners[f, c, 0] * e[0] + corners[f, c, 1] * e[1] + corners[f, c, 2] * e[2]


@njit(cache=True, inline="always")
def _section_meets_box(corners, a, b, dd, half, eps, glo, ghi, e1, e2, rect, pos):
    """Whether the part of the pair's convex hull within ``half`` of a plane (the corners' signed distances
    ``dd [8]``: ``a``'s corners, then ``b``'s) can meet the plane group: its bounding box reaches the group's box
    ``glo, ghi [3]`` and its bounding rectangle in the plane's axes ``e1, e2`` reaches the group's ``rect [4]``
    (within ``eps``). ``pos [8, 5]``: scratch.

    The hull's part in the slab ``|d| ≤ half`` is the hull of the corners inside it and of the crossings of the
    segments between corners with its two faces. Every ray between the two facets lies in the hull, so where it
    meets a member of the group (all within ``half`` of the plane) lies in that part: a group outside its box
    blocks nothing. The crossings' coordinates (x, y, z and along the plane's axes, which are linear) are
    interpolated from the corners'.
    """
    for i in range(8):
        for k in range(5):
            pos[i, k] = _corner(corners, a, b, i, k, e1, e2)
    for k in range(5):
        lo = math.inf
        hi = -math.inf
        for i in range(8):
            di = dd[i]
            if abs(di) <= half:
                lo = min(lo, pos[i, k])
                hi = max(hi, pos[i, k])
            for j in range(8):
                dj = dd[j]
                for c in (half, -half):
                    if di > c > dj:
                        x = pos[i, k] + (di - c) / (di - dj) * (pos[j, k] - pos[i, k])
                        lo = min(lo, x)
                        hi = max(hi, x)
        g_lo = glo[k] if k < 3 else rect[2 * (k - 3)]
        g_hi = ghi[k] if k < 3 else rect[2 * (k - 3) + 1]
        if g_lo > hi + eps or g_hi < lo - eps:
            return False
    return True


#: pairs per block of :func:`blockers` (scratch allocated once per block)
_BLOCKER_BLOCK = 256


@njit(cache=True, parallel=True)
def blockers(corners, cent, lo, hi, radius, pn, po, plo, phi, e1, e2, rect, thick, g_centre, g_radius, dom, tgt, eps,
             need):
    """``need[p]``: some plane group could block pair ``(dom, tgt)`` (see
    :func:`.visibility.blocker_candidates`)."""
    P = dom.shape[0]
    G = pn.shape[0]
    for blk in prange((P + _BLOCKER_BLOCK - 1) // _BLOCKER_BLOCK):
        dd = np.empty(8)
        pos = np.empty((8, 5))
        for p in range(blk * _BLOCKER_BLOCK, min(P, (blk + 1) * _BLOCKER_BLOCK)):
            a = dom[p]
            b = tgt[p]
            ca0, ca1, ca2 = cent[a, 0], cent[a, 1], cent[a, 2]
            s0, s1, s2 = cent[b, 0] - ca0, cent[b, 1] - ca1, cent[b, 2] - ca2
            ss = max(s0 * s0 + s1 * s1 + s2 * s2, 1e-300)
            rr = max(radius[a], radius[b])
            found = False
            for g in range(G):
                # the group's box overlaps the pair's
                ok = True
                for x in range(3):
                    blo = min(lo[a, x], lo[b, x])
                    bhi = max(hi[a, x], hi[b, x])
                    if not (plo[g, x] < bhi - eps and phi[g, x] > blo + eps):
                        ok = False
                        break
                if not ok:
                    continue
                # the group's bounding sphere within reach of the capsule around the centroids' segment
                t = ((g_centre[g, 0] - ca0) * s0 + (g_centre[g, 1] - ca1) * s1 + (g_centre[g, 2] - ca2) * s2) / ss
                t = min(max(t, 0.0), 1.0)
                if _dist(g_centre[g, 0], g_centre[g, 1], g_centre[g, 2], ca0 + t * s0, ca1 + t * s1,
                         ca2 + t * s2) > rr + g_radius[g] + eps:
                    continue
                # some member's plane (all within thick of the group's) strictly separates corners of the pair
                dmin = math.inf
                dmax = -math.inf
                for i in range(8):
                    f = a if i < 4 else b
                    k = i % 4
                    d = (corners[f, k, 0] * pn[g, 0] + corners[f, k, 1] * pn[g, 1]
                         + corners[f, k, 2] * pn[g, 2]) - po[g]
                    dd[i] = d
                    dmin = min(dmin, d)
                    dmax = max(dmax, d)
                split = dmax > -thick[g] + eps and dmin < thick[g] - eps and dmax - dmin > 2 * eps
                # ... and the rays' crossings of the group's slab can reach its box
                if split and _section_meets_box(corners, a, b, dd, thick[g] + eps, eps, plo[g], phi[g], e1[g],
                                                e2[g], rect[g], pos):
                    found = True
                    break
            need[p] = found


@njit(cache=True, inline="always")
def gauss_order(rho, digits):
    """The Gauss order of :func:`.rules.order_for` for one pair's ``rho`` (same formula)."""
    n = math.ceil(digits / (2.0 * math.log10(1.0 + 2.0 * max(rho, 0.05))))
    return min(max(n, 1), 40)


@njit(cache=True, parallel=True)
def order_pairs(areas, iu, ju, tie, dom, tgt):
    """Each pair ``(iu, ju)`` as ``(dom, tgt)`` with the smaller facet (the integration domain) first; ties (areas
    within ``tie`` of one another, relative) keep ``iu`` first."""
    for p in prange(iu.shape[0]):
        if areas[iu[p]] > areas[ju[p]] * (1.0 + tie):
            dom[p] = ju[p]
            tgt[p] = iu[p]
        else:
            dom[p] = iu[p]
            tgt[p] = ju[p]


#: pairs per block of the parallel counting sort
_SORT_BLOCK = 1 << 16


@njit(cache=True, parallel=True)
def rule_buckets(has_edge, has_vertex, order, clip_d, idx, counts):
    """The pairs by rule key (0 edge-graded, 1 vertex-graded, ``1 + order`` plain, 64 clipped domain), ascending
    within a key, in ``idx``; ``counts[k]`` is the size of bucket ``k`` (a parallel counting sort over blocks)."""
    P = order.shape[0]
    nb = (P + _SORT_BLOCK - 1) // _SORT_BLOCK
    hist = np.zeros((nb + 1, 65), dtype=np.int64)
    key = np.empty(P, dtype=np.int64)
    for b in prange(nb):
        for p in range(b * _SORT_BLOCK, min(P, (b + 1) * _SORT_BLOCK)):
            k = 64 if clip_d[p] else 0 if has_edge[p] else 1 if has_vertex[p] else 1 + order[p]
            key[p] = k
            hist[b + 1, k] += 1
    base = 0
    for k in range(65):  # hist[b, k] becomes the start of block b's run of key k (hist[b + 1, k] its count)
        first = base
        for b in range(nb):
            c = hist[b + 1, k]
            hist[b, k] = base
            base += c
        counts[k] = base - first
    for b in prange(nb):
        start = hist[b].copy()
        for p in range(b * _SORT_BLOCK, min(P, (b + 1) * _SORT_BLOCK)):
            k = key[p]
            idx[start[k]] = p
            start[k] += 1


#: pairs per block of :func:`pair_entries` (each block's kept pairs are counted, then written from its offset)
_ENTRY_BLOCK = 1 << 16


@njit(cache=True, parallel=True)
def pair_entries(areas, dom, tgt, value):
    """``(rows, cols, vals)``: both directions of the pairs with ``value > 0``, ``F_dom,tgt = value / A_dom`` first
    (in pair order), then ``F_tgt,dom = value / A_tgt``. Blocks of pairs are counted, then filled, in parallel."""
    P = dom.shape[0]
    nb = (P + _ENTRY_BLOCK - 1) // _ENTRY_BLOCK
    counts = np.zeros(nb + 1, dtype=np.int64)
    for b in prange(nb):
        c = 0
        for p in range(b * _ENTRY_BLOCK, min(P, (b + 1) * _ENTRY_BLOCK)):
            if value[p] > 0:
                c += 1
        counts[b + 1] = c
    for b in range(nb):
        counts[b + 1] += counts[b]
    m = counts[nb]
    rows = np.empty(2 * m, dtype=np.int64)
    cols = np.empty(2 * m, dtype=np.int64)
    vals = np.empty(2 * m, dtype=value.dtype)
    for b in prange(nb):
        k = counts[b]
        for p in range(b * _ENTRY_BLOCK, min(P, (b + 1) * _ENTRY_BLOCK)):
            if value[p] > 0:
                a = dom[p]
                t = tgt[p]
                rows[k] = a
                cols[k] = t
                vals[k] = value[p] / areas[a]
                rows[m + k] = t
                cols[m + k] = a
                vals[m + k] = value[p] / areas[t]
                k += 1
    return rows, cols, vals


@njit(cache=True, parallel=True)
def scatter_dense(rows, cols, vals, mat):
    """``mat[rows[n], cols[n]] = vals[n]`` (cast to ``mat``'s dtype); the ``(row, col)`` are distinct."""
    N = rows.shape[0]
    nb = (N + _ENTRY_BLOCK - 1) // _ENTRY_BLOCK
    for b in prange(nb):
        for n in range(b * _ENTRY_BLOCK, min(N, (b + 1) * _ENTRY_BLOCK)):
            mat[rows[n], cols[n]] = vals[n]


@njit(cache=True, parallel=True)
def dense_entries(areas, dom, tgt, value, mat, sums):
    """Both directions of the pairs with ``value > 0`` written straight into the dense matrix ``mat`` (cast to its
    dtype): ``mat[dom, tgt] = value / A_dom``, ``mat[tgt, dom] = value / A_tgt``; ``sums [nb, F]`` (zeros, ``nb``
    blocks of pairs) receives each block's float64 row sums. Returns the entries written."""
    P = dom.shape[0]
    nb = sums.shape[0]
    per = (P + nb - 1) // nb
    counts = np.zeros(nb, dtype=np.int64)
    for b in prange(nb):
        c = 0
        for p in range(b * per, min(P, (b + 1) * per)):
            v = value[p]
            if v > 0:
                a = dom[p]
                t = tgt[p]
                x = v / areas[a]
                y = v / areas[t]
                mat[a, t] = x
                mat[t, a] = y
                sums[b, a] += x
                sums[b, t] += y
                c += 2
        counts[b] = c
    return counts.sum()
