"""Compiled CPU loop (numba) of the visibility gradient's shadow edges (internal; see :mod:`.visibility_grad`):
for (pair, edge) combinations and domain points, the part of the edge between the point and the target's plane,
projected from the point onto that plane and clipped to the target. The same maths as the torch path of
:func:`.visibility_grad.shadow_spans`, without its ``[M, Q]`` temporaries.
"""

from __future__ import annotations

import math

from numba import njit, prange

from ._numba_geometry import bilinear_map


@njit(cache=True, inline="always")
def _clip(lo, hi, a, b):
    """``[lo, hi] ∩ {s : a + s b >= 0}``."""
    if b > 0:
        lo = max(lo, -a / b)
    elif b < 0:
        hi = min(hi, -a / b)
    elif a < 0:
        hi = -1.0
    return lo, hi


@njit(cache=True, parallel=True)
def edge_spans(corners, normals, uq, vq, pe, ee, dom, tgt, e0, e1, eps, sa, sb, la, lb, ok):
    """For combination ``m`` (pair ``pe[m]``, edge ``ee[m]``) and domain point ``q``: the edge parameters
    ``[sa, sb]`` of its part strictly between the point and the target's plane (in front of the point's plane too)
    and ``[la, lb]``, the part of that part's projection (from the point onto the target's plane) inside the target
    quad; ``ok`` where it is longer than ``eps``.

    corners ``[F, 4, 3]``, normals ``[F, 3]``, uq/vq ``[P, Q]``, pe/ee ``[M]``, dom/tgt ``[P]``, e0/e1 ``[E, 3]``;
    outputs ``[M, Q]``.
    """
    M = pe.shape[0]
    Q = uq.shape[1]
    for m in prange(M):
        p = pe[m]
        a = dom[p]
        b = tgt[p]
        e = ee[m]
        for q in range(Q):
            ok[m, q] = False
            x0, x1, x2, _, _, _, _, _, _ = bilinear_map(corners[a], uq[p, q], vq[p, q])
            n0, n1, n2 = normals[b, 0], normals[b, 1], normals[b, 2]
            o0, o1, o2 = corners[b, 0, 0], corners[b, 0, 1], corners[b, 0, 2]
            D = (x0 - o0) * n0 + (x1 - o1) * n1 + (x2 - o2) * n2
            d0 = (e0[e, 0] - o0) * n0 + (e0[e, 1] - o1) * n1 + (e0[e, 2] - o2) * n2
            d1 = (e1[e, 0] - o0) * n0 + (e1[e, 1] - o1) * n1 + (e1[e, 2] - o2) * n2
            h0 = ((e0[e, 0] - x0) * normals[a, 0] + (e0[e, 1] - x1) * normals[a, 1]
                  + (e0[e, 2] - x2) * normals[a, 2])
            h1 = ((e1[e, 0] - x0) * normals[a, 0] + (e1[e, 1] - x1) * normals[a, 1]
                  + (e1[e, 2] - x2) * normals[a, 2])
            lo, hi = _clip(0.0, 1.0, d0 - eps, d1 - d0)  # in front of the target's plane
            lo, hi = _clip(lo, hi, D - eps - d0, d0 - d1)  # behind the point
            lo, hi = _clip(lo, hi, h0 - eps, h1 - h0)  # in front of the point's plane
            if hi <= lo:
                continue
            # the projections of the two ends from x onto the target's plane
            ya0, ya1, ya2, yb0, yb1, yb2 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for end in range(2):
                s = lo if end == 0 else hi
                b0 = e0[e, 0] + s * (e1[e, 0] - e0[e, 0])
                b1 = e0[e, 1] + s * (e1[e, 1] - e0[e, 1])
                b2 = e0[e, 2] + s * (e1[e, 2] - e0[e, 2])
                d = d0 + s * (d1 - d0)
                f = D / (D - d)
                if end == 0:
                    ya0, ya1, ya2 = x0 + (b0 - x0) * f, x1 + (b1 - x1) * f, x2 + (b2 - x2) * f
                else:
                    yb0, yb1, yb2 = x0 + (b0 - x0) * f, x1 + (b1 - x1) * f, x2 + (b2 - x2) * f
            l0, l1 = 0.0, 1.0
            for k in range(4):
                k1 = (k + 1) % 4
                t0 = corners[b, k1, 0] - corners[b, k, 0]
                t1 = corners[b, k1, 1] - corners[b, k, 1]
                t2 = corners[b, k1, 2] - corners[b, k, 2]
                i0 = n1 * t2 - n2 * t1  # inward: n × edge
                i1 = n2 * t0 - n0 * t2
                i2 = n0 * t1 - n1 * t0
                fa = ((ya0 - corners[b, k, 0]) * i0 + (ya1 - corners[b, k, 1]) * i1
                      + (ya2 - corners[b, k, 2]) * i2)
                fb = ((yb0 - corners[b, k, 0]) * i0 + (yb1 - corners[b, k, 1]) * i1
                      + (yb2 - corners[b, k, 2]) * i2)
                l0, l1 = _clip(l0, l1, fa, fb - fa)
            length = math.sqrt((yb0 - ya0) ** 2 + (yb1 - ya1) ** 2 + (yb2 - ya2) ** 2)
            if (l1 - l0) * length > eps:
                ok[m, q] = True
                sa[m, q] = lo
                sb[m, q] = hi
                la[m, q] = l0
                lb[m, q] = l1


@njit(cache=True, parallel=True)
def pair_edge_mask(corners, normals, dom, tgt, e0, e1, eps, out):
    """``out[p, e]``: edge ``e`` reaches in front of both planes of pair ``p`` (facets ``dom[p]``, ``tgt[p]``) and
    its bounding box meets the pair's. corners ``[F, 4, 3]``, normals ``[F, 3]``, dom/tgt ``[P]``, e0/e1
    ``[E, 3]``, out ``[P, E]`` (bool)."""
    P = dom.shape[0]
    E = e0.shape[0]
    for p in prange(P):
        a = dom[p]
        b = tgt[p]
        lo = [0.0, 0.0, 0.0]
        hi = [0.0, 0.0, 0.0]
        for k in range(3):
            lo[k] = min(corners[a, :, k].min(), corners[b, :, k].min()) - eps
            hi[k] = max(corners[a, :, k].max(), corners[b, :, k].max()) + eps
        for e in range(E):
            hit = True
            for k in range(3):
                if min(e0[e, k], e1[e, k]) > hi[k] or max(e0[e, k], e1[e, k]) < lo[k]:
                    hit = False
            if hit:
                for f in (a, b):
                    da = ((e0[e, 0] - corners[f, 0, 0]) * normals[f, 0] + (e0[e, 1] - corners[f, 0, 1]) * normals[f, 1]
                          + (e0[e, 2] - corners[f, 0, 2]) * normals[f, 2])
                    db = ((e1[e, 0] - corners[f, 0, 0]) * normals[f, 0] + (e1[e, 1] - corners[f, 0, 1]) * normals[f, 1]
                          + (e1[e, 2] - corners[f, 0, 2]) * normals[f, 2])
                    if max(da, db) <= eps:
                        hit = False
            out[p, e] = hit
