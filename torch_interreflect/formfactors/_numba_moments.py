"""Compiled CPU loops (numba) for the Galerkin moments of the kernel on a polynomial basis (internal; see
:mod:`.moments`).

For a pair of facets ``(dom, tgt)`` the loops accumulate ``Σ_o w_o m_c(x_o) ∫_tgt k(x_o, y) m_d(y) dA_y`` over
an outer rule on ``dom``, where ``m`` are the monomials ``1, p, q, p², pq, q²`` of each facet's own frame
(``p, q`` in units of ``sqrt(area)`` from the centroid) and ``k = cos θ_x cos θ_y / (π r²)``. The inner integral
is either

- **exact in the radius** (near pairs; :func:`._numba_contour.inner_exact`, Lambert's point-to-polygon factor for
  ``m = 1``);
- **a product Gauss rule** (far pairs, where the kernel is smooth over both facets).

Visibility: for occluded pairs, the blocked part is subtracted, estimated from Embree rays cast outside the loops
(:func:`build_rays`) to jittered target samples.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._numba_contour import KMAX, clip_polygon, frame_coords, inner_exact
from ._numba_geometry import bilinear_map, jacobian_norm

_INV_PI = 1.0 / math.pi


@njit(cache=True, inline="always")
def _monomials(p, q, deg, m):
    m[0] = 1.0
    if deg >= 1:
        m[1] = p
        m[2] = q
    if deg >= 2:
        m[3] = p * p
        m[4] = p * q
        m[5] = q * q


@njit(cache=True, inline="always")
def _point_kernel(x0, x1, x2, nx, y0, y1, y2, ny):
    """``cos θ_x cos θ_y / (π r²)`` between two points (0 where either faces away)."""
    r0, r1, r2 = y0 - x0, y1 - x1, y2 - x2
    r2s = r0 * r0 + r1 * r1 + r2 * r2
    cx = nx[0] * r0 + nx[1] * r1 + nx[2] * r2
    cy = -(ny[0] * r0 + ny[1] * r1 + ny[2] * r2)
    if cx <= 0.0 or cy <= 0.0:
        return 0.0
    return cx * cy * _INV_PI / (r2s * r2s)


@njit(cache=True, inline="always")
def _map(Cq, u, v):
    """Bilinear point and area Jacobian of the quad ``Cq [4, 3]`` at ``(u, v)``."""
    x0, x1, x2, du0, du1, du2, dv0, dv1, dv2 = bilinear_map(Cq, u, v)
    return x0, x1, x2, jacobian_norm(du0, du1, du2, dv0, dv1, dv2)


@njit(cache=True, inline="always")
def _accumulate(acc, wt, mx, mom, nb):
    for c in range(nb):
        f = wt * mx[c]
        for d in range(nb):
            acc[c, d] += f * mom[d]


@njit(cache=True)
def _rule_points(Cq, r0, r1, rule_u, rule_v, rule_w, X, Wt, n):
    """Append the rule ``[r0, r1)`` mapped onto the quad ``Cq`` to ``X, Wt`` from position ``n``; the new count."""
    for q in range(r0, r1):
        x0, x1, x2, jac = _map(Cq, rule_u[q], rule_v[q])
        X[n, 0], X[n, 1], X[n, 2] = x0, x1, x2
        Wt[n] = rule_w[q] * jac
        n += 1
    return n


@njit(cache=True)
def outer_points(p, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule, corners,
                 normals, X, Wt):
    """The outer points ``X [n, 3]`` and area weights ``Wt [n]`` (m²) of pair ``p`` on its domain; returns ``n``.

    Kinds 0 and 1: the pair's rule on the domain quad (its corners rotated by ``shift``: the shared edge or
    vertex first). Kind 2: the domain clipped to the target's plane, as a fan of triangles from a vertex on that
    plane, the first triangle (whose edge lies on the plane) with the edge-graded rule, the others vertex-graded.
    """
    i, j = dom[p], tgt[p]
    Cq = np.empty((4, 3))
    if kind[p] != 2:
        for k in range(4):
            kk = (k + shift[p]) % 4
            Cq[k, 0], Cq[k, 1], Cq[k, 2] = corners[i, kk, 0], corners[i, kk, 1], corners[i, kk, 2]
        return _rule_points(Cq, rule_off[rule[p]], rule_off[rule[p] + 1], rule_u, rule_v, rule_w, X, Wt, 0)
    V = np.empty((KMAX, 3))
    W = np.empty((KMAX, 3))
    for k in range(4):
        V[k, 0], V[k, 1], V[k, 2] = corners[i, k, 0], corners[i, k, 1], corners[i, k, 2]
    nP = normals[j]
    o = corners[j, 0]
    nd = clip_polygon(V, 4, o, nP, W)
    start = 0
    best = 1e300
    for k in range(nd):
        kb = k + 1 if k + 1 < nd else 0
        da = abs(nP[0] * (W[k, 0] - o[0]) + nP[1] * (W[k, 1] - o[1]) + nP[2] * (W[k, 2] - o[2]))
        db = abs(nP[0] * (W[kb, 0] - o[0]) + nP[1] * (W[kb, 1] - o[1]) + nP[2] * (W[kb, 2] - o[2]))
        if da + db < best:
            best = da + db
            start = k
    n = 0
    for t in range(1, nd - 1):
        a, b, c = start, (start + t) % nd, (start + t + 1) % nd
        for k in range(3):
            Cq[0, k], Cq[1, k], Cq[2, k], Cq[3, k] = W[a, k], W[b, k], W[c, k], W[c, k]
        rr = edge_rule if t == 1 else vertex_rule
        n = _rule_points(Cq, rule_off[rr], rule_off[rr + 1], rule_u, rule_v, rule_w, X, Wt, n)
    return n


@njit(cache=True)
def max_points(kind, rule, rule_off, edge_rule, vertex_rule):
    """An upper bound on the outer points of any pair (for the per-pair buffers)."""
    m = 0
    for p in range(kind.shape[0]):
        if kind[p] == 2:
            c = rule_off[edge_rule + 1] - rule_off[edge_rule]
            c += 3 * (rule_off[vertex_rule + 1] - rule_off[vertex_rule])
        else:
            c = rule_off[rule[p] + 1] - rule_off[rule[p]]
        m = max(m, c)
    return m


@njit(cache=True, inline="always")
def _mix(a):
    """splitmix64 finaliser: a well-mixed 64-bit integer from ``a`` (counter-based jitter, the same on any thread)."""
    a = (a ^ (a >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    a = (a ^ (a >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return a ^ (a >> np.uint64(31))


@njit(cache=True, inline="always")
def _uniform(seed, p, o, s, axis):
    key = (np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(p) * np.uint64(0xD1B54A32D192ED03)
           + np.uint64(o) * np.uint64(0x8CB92BA72F3D8DD7) + np.uint64(s * 2 + axis) * np.uint64(0xABC98388FB8FAC03))
    return (_mix(key) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always")
def _sample(Cj, tri, ns, s, seed, p, o):
    """Sample ``s`` of ``ns²`` jittered strata on the target (bilinear map; a triangle's strata spread evenly):
    its point and its area weight (m²)."""
    a, b = s // ns, s % ns
    u = (a + _uniform(seed, p, o, s, 0)) / ns
    v = (b + _uniform(seed, p, o, s, 1)) / ns
    scale = 1.0
    if tri:
        vv = 1.0 - math.sqrt(max(1.0 - v, 0.0))
        scale = 1.0 / (2.0 * max(1.0 - vv, 1e-300))
        v = vv
    y0, y1, y2, jac = _map(Cj, u, v)
    return y0, y1, y2, jac * scale / (ns * ns)


@njit(parallel=True, cache=True)
def count_rays(sel, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule, corners,
               normals, buf, counts):
    """Outer points of each selected pair ``sel`` (``counts``, for the offsets of its rays)."""
    for t in prange(sel.shape[0]):
        X = np.empty((buf, 3))
        Wt = np.empty(buf)
        counts[t] = outer_points(sel[t], dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule,
                                 vertex_rule, corners, normals, X, Wt)


@njit(parallel=True, cache=True)
def build_rays(sel, start, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule,
               corners, normals, triangle, ns, seed, eps, origin, buf, ro, rd, rt):
    """Rays from every outer point of the selected pairs to its ``ns²`` jittered target samples: origins (relative
    to ``origin``, nudged ``eps`` along the ray), unit directions and lengths (float32, ``rt ≤ 0``: no ray)."""
    n2 = ns * ns
    for t in prange(sel.shape[0]):
        p = sel[t]
        X = np.empty((buf, 3))
        Wt = np.empty(buf)
        n = outer_points(p, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule,
                         corners, normals, X, Wt)
        Cj = corners[tgt[p]]
        tri = triangle[tgt[p]]
        for o in range(n):
            for s in range(n2):
                y0, y1, y2, _ = _sample(Cj, tri, ns, s, seed, p, o)
                d0, d1, d2 = y0 - X[o, 0], y1 - X[o, 1], y2 - X[o, 2]
                ln = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                k = start[t] + o * n2 + s
                inv = 1.0 / max(ln, 1e-300)
                rd[k, 0], rd[k, 1], rd[k, 2] = d0 * inv, d1 * inv, d2 * inv
                ro[k, 0] = X[o, 0] - origin[0] + eps * d0 * inv
                ro[k, 1] = X[o, 1] - origin[1] + eps * d1 * inv
                ro[k, 2] = X[o, 2] - origin[2] + eps * d2 * inv
                rt[k] = ln - 2.0 * eps


@njit(cache=True, inline="always")
def _outer_scratch(p, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule, corners,
                   normals, buf, nb):
    """The outer points of pair ``p`` (``X [buf, 3]``, weights ``Wt``, their count ``n``, :func:`outer_points`) and
    the per-pair scratch of the moment loops: a point ``x [3]`` and three vectors of ``nb`` monomials."""
    X = np.empty((buf, 3))
    Wt = np.empty(buf)
    n = outer_points(p, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule,
                     corners, normals, X, Wt)
    return n, X, Wt, np.empty(3), np.empty(nb), np.empty(nb), np.empty(nb)


@njit(parallel=True, cache=True)
def pair_moments(todo, dom, tgt, kind, rule, shift, fine, rule_off, rule_u, rule_v, rule_w, edge_rule, vertex_rule,
                 corners, normals, cent, e1, e2, inv_l, triangle, deg, gx, gw, gx_fine, gw_fine, u_panel, buf, sel_of,
                 ray_start, blocked, ns, seed, out, exact_out):
    """``out[p, c, d] = Σ_o w_o m_c(x_o) ∫_tgt k(x_o, y) V(x_o, y) m_d(y) dA`` (monomials of ``dom`` and ``tgt``; m²)
    for the pairs ``p`` in ``todo``.

    ``kind``: 0 exact inner on the whole domain, 1 product Gauss (the rule on both facets; far pairs), 2 exact
    inner on the domain clipped to the target's plane (:func:`outer_points`). ``fine[p]``: the angular rule
    ``gx_fine, gw_fine`` (pairs that touch) instead of ``gx, gw``, on panels at most ``u_panel`` wide
    (:func:`._numba_contour.inner_exact`). Occluded pairs (``sel_of[p] ≥ 0``): the
    exact unoccluded moments less the blocked part, estimated from the ``ns²`` jittered samples per outer point
    (``blocked`` from ``ray_start[sel_of[p]]``, in :func:`build_rays`' order): an unbiased estimate, exact where
    nothing is blocked. Their exact unoccluded moments go to ``exact_out[sel_of[p]]`` as well, so that rays drawn
    again need only the blocked part (:func:`blocked_moments`; ``out = exact − blocked`` in both, the same bits).
    (The ratio estimator that scales the blocked part by the exact over the sampled kernel, as the constant basis's
    visible fraction does, was biased here: on the Cornell box with its floor's leaves split, 3 × 3 rays per point
    moved every facet by −1.8 % on average, against −0.15 % unscaled.)
    """
    nb = 1 if deg == 0 else (3 if deg == 1 else 6)
    n2 = ns * ns
    for t_ in prange(todo.shape[0]):
        p = todo[t_]
        i, j = dom[p], tgt[p]
        acc = np.zeros((nb, nb))
        W = np.empty((KMAX, 3))
        V = np.empty((KMAX, 3))
        n, X, Wt, x, mx, my, mom = _outer_scratch(p, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w,
                                                  edge_rule, vertex_rule, corners, normals, buf, nb)
        ni, nj = normals[i], normals[j]
        if kind[p] == 1:
            Cj = corners[j]
            r = rule[p]
            nq = rule_off[r + 1] - rule_off[r]
            ys = np.empty((nq, 3))
            wy = np.empty(nq)
            my_all = np.empty((nq, nb))
            for qy in range(nq):  # the target's points once
                y0, y1, y2, jy = _map(Cj, rule_u[rule_off[r] + qy], rule_v[rule_off[r] + qy])
                ys[qy, 0], ys[qy, 1], ys[qy, 2] = y0, y1, y2
                wy[qy] = rule_w[rule_off[r] + qy] * jy
                py, qq = frame_coords(y0, y1, y2, cent[j], e1[j], e2[j], inv_l[j])
                _monomials(py, qq, deg, my)
                for d in range(nb):
                    my_all[qy, d] = my[d]
            for o in range(n):
                for d in range(nb):
                    mom[d] = 0.0
                for qy in range(nq):
                    kv = _point_kernel(X[o, 0], X[o, 1], X[o, 2], ni, ys[qy, 0], ys[qy, 1], ys[qy, 2], nj) * wy[qy]
                    for d in range(nb):
                        mom[d] += kv * my_all[qy, d]
                px, qx_ = frame_coords(X[o, 0], X[o, 1], X[o, 2], cent[i], e1[i], e2[i], inv_l[i])
                _monomials(px, qx_, deg, mx)
                _accumulate(acc, Wt[o], mx, mom, nb)
        else:
            ax, aw = (gx_fine, gw_fine) if fine[p] else (gx, gw)
            for k in range(4):
                V[k, 0], V[k, 1], V[k, 2] = corners[j, k, 0], corners[j, k, 1], corners[j, k, 2]
            t = sel_of[p]
            acc_b = np.zeros((nb, nb))
            for o in range(n):
                x[0], x[1], x[2] = X[o, 0], X[o, 1], X[o, 2]
                inner_exact(x, ni, V, 4, nj, cent[j], e1[j], e2[j], inv_l[j], deg, ax, aw, u_panel, W, mom)
                px, qx_ = frame_coords(x[0], x[1], x[2], cent[i], e1[i], e2[i], inv_l[i])
                _monomials(px, qx_, deg, mx)
                _accumulate(acc, Wt[o], mx, mom, nb)
                if t >= 0:
                    _blocked_point(x, ni, nj, corners[j], triangle[j], cent[j], e1[j], e2[j], inv_l[j], deg, ns,
                                   seed, p, o, blocked, ray_start[t] + o * n2, my, mom, acc_b, Wt[o], mx, nb)
            if t >= 0:
                for c in range(nb):
                    for d in range(nb):
                        exact_out[t, c, d] = acc[c, d]
                        acc[c, d] -= acc_b[c, d]
        for c in range(nb):
            for d in range(nb):
                out[p, c, d] = acc[c, d]


@njit(cache=True, inline="always")
def _blocked_point(x, ni, nj, Cj, tri, cj, e1j, e2j, inv_lj, deg, ns, seed, p, o, blocked, base, my, mom, acc_b, wt,
                   mx, nb):
    """Add to ``acc_b`` the blocked part of the outer point ``x`` (its monomials ``mx``, weight ``wt``): the kernel
    times the target's monomials at its blocked samples (``blocked[base + s]``). The kernel is 0 at samples the
    point does not face, so no exact integral is needed to skip them."""
    hit = False
    for d in range(nb):
        mom[d] = 0.0
    for s in range(ns * ns):
        if blocked[base + s]:
            y0, y1, y2, w = _sample(Cj, tri, ns, s, seed, p, o)
            kv = _point_kernel(x[0], x[1], x[2], ni, y0, y1, y2, nj) * w
            if kv > 0.0:
                hit = True
                py, qq = frame_coords(y0, y1, y2, cj, e1j, e2j, inv_lj)
                _monomials(py, qq, deg, my)
                for d in range(nb):
                    mom[d] += kv * my[d]
    if hit:
        _accumulate(acc_b, wt, mx, mom, nb)


@njit(parallel=True, cache=True)
def blocked_moments(sel, ray_start, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w, edge_rule,
                    vertex_rule, corners, normals, cent, e1, e2, inv_l, triangle, deg, buf, blocked, ns, seed, out):
    """``out[t] = Σ_o w_o m(x_o) ⊗ Σ_(blocked s) k(x_o, y_s) m(y_s) w_s``: the blocked part of the occluded pair
    ``sel[t]`` alone (its rays from ``ray_start[t]``), which :func:`pair_moments` subtracts from the exact moments;
    no exact inner integral is evaluated."""
    nb = 1 if deg == 0 else (3 if deg == 1 else 6)
    n2 = ns * ns
    for t in prange(sel.shape[0]):
        p = sel[t]
        i, j = dom[p], tgt[p]
        acc_b = np.zeros((nb, nb))
        n, X, Wt, x, mx, my, mom = _outer_scratch(p, dom, tgt, kind, rule, shift, rule_off, rule_u, rule_v, rule_w,
                                                  edge_rule, vertex_rule, corners, normals, buf, nb)
        ni, nj = normals[i], normals[j]
        for o in range(n):
            x[0], x[1], x[2] = X[o, 0], X[o, 1], X[o, 2]
            px, qx_ = frame_coords(x[0], x[1], x[2], cent[i], e1[i], e2[i], inv_l[i])
            _monomials(px, qx_, deg, mx)
            _blocked_point(x, ni, nj, corners[j], triangle[j], cent[j], e1[j], e2[j], inv_l[j], deg, ns, seed, p, o,
                           blocked, ray_start[t] + o * n2, my, mom, acc_b, Wt[o], mx, nb)
        for c in range(nb):
            for d in range(nb):
                out[t, c, d] = acc_b[c, d]


@njit(parallel=True, cache=True)
def scatter_blocks(dom, tgt, acc, transform, areas, out):
    """The dense moment matrix ``out [F·nb, F·nb]`` from the pairs' monomial sums ``acc [P, nb, nb]``:
    ``G[(i, a), (j, b)] = (T_i acc T_jᵀ)[a, b] / A_i`` and its reciprocal block ``G[(j, b), (i, a)]`` (``/ A_j``);
    ``transform [F, nb, nb]`` maps a facet's monomials to its orthonormal basis. Each unordered pair once, so the
    parallel writes never meet."""
    nb = acc.shape[1]
    for p in prange(dom.shape[0]):
        i, j = dom[p], tgt[p]
        tmp = np.zeros((nb, nb))
        for a in range(nb):
            for d in range(nb):
                s = 0.0
                for c in range(nb):
                    s += transform[i, a, c] * acc[p, c, d]
                tmp[a, d] = s
        ai, aj = 1.0 / areas[i], 1.0 / areas[j]
        for a in range(nb):
            for b in range(nb):
                s = 0.0
                for d in range(nb):
                    s += tmp[a, d] * transform[j, b, d]
                out[i * nb + a, j * nb + b] = s * ai
                out[j * nb + b, i * nb + a] = s * aj


@njit(cache=True, inline="always")
def _pair_key(p, dom, tgt, kind, rule, shift, fine, corners, triangle, quantum, k):
    """The key of pair ``p`` in ``k [30]`` (int64): its two facets' corners relative to the domain's first corner in
    steps of ``quantum`` (m), then its kind, rule, rotation, angular rule and the facets' triangle flags. Everything
    the loops compute from a pair but its position: the frames, normals and outer points follow from the corners."""
    i, j = dom[p], tgt[p]
    n = 0
    for s in range(2):
        f = i if s == 0 else j
        for c in range(4):
            for x in range(3):
                k[n] = np.int64(round((corners[f, c, x] - corners[i, 0, x]) / quantum))
                n += 1
    k[24], k[25], k[26], k[27] = kind[p], rule[p], shift[p], fine[p]
    k[28], k[29] = triangle[i], triangle[j]


@njit(cache=True, parallel=True)
def pair_hashes(todo, dom, tgt, kind, rule, shift, fine, corners, triangle, quantum, out):
    """``out[t]``: a 64-bit hash of the key of pair ``todo[t]`` (:func:`_pair_key`); pairs that are translated copies
    of one another (to within ``quantum``) hash alike."""
    for t in prange(todo.shape[0]):
        k = np.empty(30, dtype=np.int64)
        _pair_key(todo[t], dom, tgt, kind, rule, shift, fine, corners, triangle, quantum, k)
        h = np.uint64(0x84222325CBF29CE4)
        for n in range(30):
            h = _mix(h ^ (np.uint64(k[n] & 0x7FFFFFFFFFFFFFFF) + np.uint64(n) * np.uint64(0x9E3779B97F4A7C15)))
        out[t] = h


@njit(cache=True, parallel=True)
def same_pairs(todo, rep, dom, tgt, kind, rule, shift, fine, corners, triangle, quantum, out):
    """``out[t]``: pair ``todo[t]`` has the key of pair ``rep[t]`` (a hash match that is a real copy)."""
    for t in prange(todo.shape[0]):
        a = np.empty(30, dtype=np.int64)
        b = np.empty(30, dtype=np.int64)
        _pair_key(todo[t], dom, tgt, kind, rule, shift, fine, corners, triangle, quantum, a)
        _pair_key(rep[t], dom, tgt, kind, rule, shift, fine, corners, triangle, quantum, b)
        same = True
        for n in range(30):
            if a[n] != b[n]:
                same = False
                break
        out[t] = same
