"""Compiled CPU loops (numba) for the fused form-factor quadrature (internal; see :mod:`.fused`).

One ``prange`` over pairs; each pair gathers its two facets, clips the target at the domain's horizon,
maps the rule onto the domain (bilinear points and area Jacobians) and sums Lambert's contour formula over
the points, with no temporary array. The arithmetic is that of :func:`.contour.point_polygon_factor`,
:func:`..geometry._polygon.clip_polygons` and :func:`..geometry._polygon.bilinear`, in the same order, so the
float64 results agree with the torch path to rounding.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._numba_geometry import bilinear_map, jacobian_norm

_INV_2PI = 1.0 / (2.0 * math.pi)
_TINY = float(np.finfo(np.float64).tiny ** 0.5)
#: most corners of a clipped target kept (as the torch path: ``clip_polygons(...)[:, :5]``)
_KMAX = 5

#: Cephes' atan (S. L. Moshier): rational approximation on three ranges, 2 ulp against libm's atan2 over 1e-8..1e2
_T3P8 = 2.41421356237309504880  # tan(3π/8)
_MOREBITS = 6.123233995736765886130e-17


@njit(cache=True, inline="always")
def _atan_pos(x):
    """``atan(x)`` for ``x ≥ 0`` (Cephes' ``atan``: argument reduction to ``|x| ≤ 0.66`` and a P4/Q5 rational)."""
    if x > _T3P8:
        y = 0.5 * math.pi
        flag = 1
        x = -1.0 / x
    elif x <= 0.66:
        y = 0.0
        flag = 0
    else:
        y = 0.25 * math.pi
        flag = 2
        x = (x - 1.0) / (x + 1.0)
    z = x * x
    p = ((((-8.750608600031904122785e-1 * z - 1.615753718733365076637e1) * z - 7.500855792314704667340e1) * z
          - 1.228866684490136173410e2) * z - 6.485021904942025371773e1)
    q = (((((z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2) * z + 4.328810604912902668951e2) * z
          + 4.853903996359136964868e2) * z + 1.945506571482613964425e2)
    z = x * (z * p / q) + x
    if flag == 2:
        z += 0.5 * _MOREBITS
    elif flag == 1:
        z += _MOREBITS
    return y + z


@njit(cache=True, inline="always")
def _angle(s, c):
    """``atan2(s, c)`` for ``s ≥ 0``: the angle in ``[0, π]`` whose sine and cosine are proportional to ``s, c``."""
    if c > 0:
        return _atan_pos(s / c)
    if c < 0:
        return math.pi - _atan_pos(s / -c)
    return 0.5 * math.pi


@njit(cache=True, inline="always")
def _clip(poly, count, px, py, pz, nx, ny, nz, eps, out, d):
    """Clip ``poly[:count]`` to ``(y - p)·n >= -eps``; write at most ``_KMAX`` corners to ``out``; return count."""
    for k in range(count):
        d[k] = (poly[k, 0] - px) * nx + (poly[k, 1] - py) * ny + (poly[k, 2] - pz) * nz
    m = 0
    for k in range(count):
        k1 = (k + 1) % count
        ins = d[k] >= -eps
        ins1 = d[k1] >= -eps
        if ins and m < _KMAX:
            out[m, 0] = poly[k, 0]
            out[m, 1] = poly[k, 1]
            out[m, 2] = poly[k, 2]
            m += 1
        if ins != ins1 and m < _KMAX:
            t = d[k] / (d[k] - d[k1])
            out[m, 0] = poly[k, 0] + t * (poly[k1, 0] - poly[k, 0])
            out[m, 1] = poly[k, 1] + t * (poly[k1, 1] - poly[k, 1])
            out[m, 2] = poly[k, 2] + t * (poly[k1, 2] - poly[k, 2])
            m += 1
    return m


@njit(cache=True, inline="always")
def _contour(x0, x1, x2, n0, n1, n2, poly, count):
    """Lambert's contour formula from the point ``x`` (normal ``n``) to the closed polygon ``poly[:count]``."""
    acc = 0.0
    for k in range(count):
        k1 = k + 1 if k + 1 < count else 0
        rx = poly[k, 0] - x0
        ry = poly[k, 1] - x1
        rz = poly[k, 2] - x2
        sx = poly[k1, 0] - x0
        sy = poly[k1, 1] - x1
        sz = poly[k1, 2] - x2
        cx = ry * sz - rz * sy
        cy = rz * sx - rx * sz
        cz = rx * sy - ry * sx
        cn = math.sqrt(cx * cx + cy * cy + cz * cz)
        if cn > _TINY:
            gamma = _angle(cn, rx * sx + ry * sy + rz * sz)
            acc += gamma * (cx * n0 + cy * n1 + cz * n2) / cn
    return -_INV_2PI * acc


@njit(cache=True, inline="always")
def _quad_sum(dom, n0, n1, n2, poly, count, u, v, w, vis, vrow):
    """``Σ_q F(x_q → poly) |J_q| w_q vis_q`` over the rule ``(u, v, w)`` mapped bilinearly onto ``dom [4, 3]``."""
    total = 0.0
    for q in range(u.shape[0]):
        x0, x1, x2, du0, du1, du2, dv0, dv1, dv2 = bilinear_map(dom, u[q], v[q])
        jac = jacobian_norm(du0, du1, du2, dv0, dv1, dv2)
        f = _contour(x0, x1, x2, n0, n1, n2, poly, count)
        if vrow >= 0:
            f *= vis[vrow, q]
        total += f * jac * w[q]
    return total


#: pairs per block of the parallel loop (scratch arrays are allocated once per block)
_BLOCK = 64


@njit(cache=True, inline="always")
def _pair_sum(corners, normals, cent, i, j, sh, cut, u, v, w, eps, vis, r, d, poly, dist):
    """``A_i F_ij`` by the rule ``(u, v, w)`` over facet ``i`` (corners rotated by ``sh``), the target ``j``
    clipped at ``i``'s plane when ``cut``; ``r``: row of ``vis`` (``-1``: visible); ``d, poly, dist``: scratch."""
    for k in range(4):
        kk = (k + sh) % 4
        d[k, 0] = corners[i, kk, 0]
        d[k, 1] = corners[i, kk, 1]
        d[k, 2] = corners[i, kk, 2]
    if cut:
        count = _clip(corners[j], 4, cent[i, 0], cent[i, 1], cent[i, 2],
                      normals[i, 0], normals[i, 1], normals[i, 2], eps, poly, dist)
    else:
        for k in range(4):
            poly[k, 0] = corners[j, k, 0]
            poly[k, 1] = corners[j, k, 1]
            poly[k, 2] = corners[j, k, 2]
        count = 4
    return _quad_sum(d, normals[i, 0], normals[i, 1], normals[i, 2], poly, count, u, v, w, vis, r)


@njit(cache=True, parallel=True)
def pair_sums(corners, normals, cent, dom, tgt, shift, clip, sel, u, v, w, eps, vis, vrow, out):
    """``out[p] = A_dom F_dom,tgt`` (before clamping) for the pairs ``p = sel[n]`` (whole-facet domains).

    corners ``[F, 4, 3]``, normals/cent ``[F, 3]``; per pair ``p``: ``dom, tgt, shift`` (int64; the domain's
    corners are rotated by ``shift``), ``clip`` (bool: clip the target at the domain's plane); per selected pair
    ``n``: ``vrow`` (row of ``vis`` holding its per-point visible fractions, ``-1`` for none; an empty ``vrow``:
    none for every pair); rule ``u, v, w [Q]``.
    The pairs are read where they are (no gathered copies); ``out`` is written at ``sel`` only.
    """
    N = sel.shape[0]
    for b in prange((N + _BLOCK - 1) // _BLOCK):
        d = np.empty((4, 3))
        poly = np.empty((_KMAX, 3))
        dist = np.empty(8)
        for n in range(b * _BLOCK, min(N, (b + 1) * _BLOCK)):
            p = sel[n]
            r = vrow[n] if vrow.shape[0] else -1
            out[p] = _pair_sum(corners, normals, cent, dom[p], tgt[p], shift[p], clip[p], u, v, w, eps, vis, r, d,
                               poly, dist)


@njit(cache=True)
def _pair_at(cum, bounds, size, c):
    """The first pair (index into the concatenated groups) whose cumulative point count reaches ``c``."""
    g = 0
    while g + 1 < cum.shape[0] - 1 and cum[g + 1] <= c:
        g += 1
    return min(bounds[g] + (c - cum[g] + size[g] - 1) // size[g], bounds[g + 1])


@njit(cache=True, parallel=True)
def rule_sums(corners, normals, cent, dom, tgt, shift, clip, sel, bounds, ru, rv, rw, size, eps, blocks, out):
    """:func:`pair_sums` for several rules in one launch, all points visible: the pairs ``sel[bounds[g] :
    bounds[g + 1]]`` get the rule ``(ru[g], rv[g], rw[g])[:size[g]]`` (a table ``[G, Qmax]``).

    The work is cut into ``blocks`` runs of about equal point counts (not of equal pair counts), so the threads'
    shares balance although the rules' sizes differ by 100×.
    """
    G = size.shape[0]
    cum = np.zeros(G + 1, dtype=np.int64)
    for g in range(G):
        cum[g + 1] = cum[g] + (bounds[g + 1] - bounds[g]) * size[g]
    total = cum[G]
    vis = np.ones((1, 1))
    for b in prange(blocks):
        start = _pair_at(cum, bounds, size, total * b // blocks)
        stop = _pair_at(cum, bounds, size, total * (b + 1) // blocks) if b + 1 < blocks else bounds[G]
        d = np.empty((4, 3))
        poly = np.empty((_KMAX, 3))
        dist = np.empty(8)
        g = 0
        for n in range(start, stop):
            while n >= bounds[g + 1]:
                g += 1
            q = size[g]
            p = sel[n]
            out[p] = _pair_sum(corners, normals, cent, dom[p], tgt[p], shift[p], clip[p], ru[g, :q], rv[g, :q],
                               rw[g, :q], eps, vis, -1, d, poly, dist)


@njit(cache=True, parallel=True)
def polygon_sums(domain, normal, target, count, u, v, w, vis, vrow, out):
    """``out[p] = Σ_q F(x_q → target_p) |J_q| w_q vis_q`` for explicit domain quads ``[P, 4, 3]`` (normals
    ``[P, 3]``) and target polygons ``target[p, :count[p]]`` (``[P, K, 3]``)."""
    for p in prange(domain.shape[0]):
        out[p] = _quad_sum(domain[p], normal[p, 0], normal[p, 1], normal[p, 2], target[p], count[p],
                           u, v, w, vis, vrow[p])



@njit(cache=True, parallel=True)
def point_factors(x, normal, rows, poly, which, centre, axis, out, ahead):
    """Per pair ``n``: ``out[n] = F(x_r → poly[which[n]])`` with ``r = rows[n]`` (Lambert's contour formula from
    points ``x [P, 3]`` with unit normals ``[P, 3]`` to padded polygons ``poly [Q, K, 3]``; repeated corners add
    nothing), and ``ahead[n] = (x_r − centre_w)·axis_w > 0`` with ``w = which[n]`` (``centre``, ``axis``:
    ``[Q, 3]``)."""
    K = poly.shape[1]
    for n in prange(rows.shape[0]):
        r = rows[n]
        w = which[n]
        out[n] = _contour(x[r, 0], x[r, 1], x[r, 2], normal[r, 0], normal[r, 1], normal[r, 2], poly[w], K)
        ahead[n] = ((x[r, 0] - centre[w, 0]) * axis[w, 0] + (x[r, 1] - centre[w, 1]) * axis[w, 1]
                    + (x[r, 2] - centre[w, 2]) * axis[w, 2]) > 0


@njit(cache=True, parallel=True)
def horizon_point_factors(x, normal, base, rows, corners, which, centre, axis, eps, blocks, out, ahead):
    """:func:`point_factors` with each target facet clipped in the loop: ``corners[which[n]]`` (``[F, 4, 3]``, a
    triangle's last corner repeated) clipped to the horizon ``(y − base_r)·normal_r >= −eps`` of point ``r =
    rows[n]`` (``base [P, 3]``: a point of its plane), as :func:`..geometry._polygon.clip_polygons` does. The
    pairs are cut into ``blocks`` runs (scratch arrays per run)."""
    N = rows.shape[0]
    for b in prange(blocks):
        poly = np.empty((_KMAX, 3))
        d = np.empty(4)
        for n in range(N * b // blocks, N * (b + 1) // blocks):
            r = rows[n]
            w = which[n]
            m = _clip(corners[w], 4, base[r, 0], base[r, 1], base[r, 2], normal[r, 0], normal[r, 1], normal[r, 2],
                      eps, poly, d)
            out[n] = _contour(x[r, 0], x[r, 1], x[r, 2], normal[r, 0], normal[r, 1], normal[r, 2], poly, m)
            ahead[n] = ((x[r, 0] - centre[w, 0]) * axis[w, 0] + (x[r, 1] - centre[w, 1]) * axis[w, 1]
                        + (x[r, 2] - centre[w, 2]) * axis[w, 2]) > 0


@njit(cache=True, inline="always")
def _edge_grad(ax, ay, az, bx, by, bz, n0, n1, n2, coef, out):
    """``coef ·`` gradients of one edge term ``γ (c·n)/|c|`` (``c = a × b``, ``γ = ∠(a, b)``) of the contour formula
    with respect to ``a``, ``b`` and ``n``: written to ``out[0:3]``, ``out[3:6]``, ``out[6:9]`` (zero for a
    degenerate edge, which the forward skips)."""
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    s = math.sqrt(cx * cx + cy * cy + cz * cz)
    if s <= _TINY:
        for k in range(9):
            out[k] = 0.0
        return
    d = ax * bx + ay * by + az * bz
    gamma = math.atan2(s, d)
    cn = cx * n0 + cy * n1 + cz * n2
    h = cn / s
    # ∇_a s = (b × c)/s, ∇_b s = (c × a)/s
    sax = (by * cz - bz * cy) / s
    say = (bz * cx - bx * cz) / s
    saz = (bx * cy - by * cx) / s
    sbx = (cy * az - cz * ay) / s
    sby = (cz * ax - cx * az) / s
    sbz = (cx * ay - cy * ax) / s
    den = s * s + d * d
    # ∇γ = (d ∇s − s ∇d)/(s² + d²), ∇_a d = b, ∇_b d = a
    gax = (d * sax - s * bx) / den
    gay = (d * say - s * by) / den
    gaz = (d * saz - s * bz) / den
    gbx = (d * sbx - s * ax) / den
    gby = (d * sby - s * ay) / den
    gbz = (d * sbz - s * az) / den
    # ∇_a h = (b × n)/s − h ∇_a s / s, ∇_b h = (n × a)/s − h ∇_b s / s
    hax = (by * n2 - bz * n1) / s - h * sax / s
    hay = (bz * n0 - bx * n2) / s - h * say / s
    haz = (bx * n1 - by * n0) / s - h * saz / s
    hbx = (n1 * az - n2 * ay) / s - h * sbx / s
    hby = (n2 * ax - n0 * az) / s - h * sby / s
    hbz = (n0 * ay - n1 * ax) / s - h * sbz / s
    out[0] = coef * (h * gax + gamma * hax)
    out[1] = coef * (h * gay + gamma * hay)
    out[2] = coef * (h * gaz + gamma * haz)
    out[3] = coef * (h * gbx + gamma * hbx)
    out[4] = coef * (h * gby + gamma * hby)
    out[5] = coef * (h * gbz + gamma * hbz)
    out[6] = coef * gamma * cx / s
    out[7] = coef * gamma * cy / s
    out[8] = coef * gamma * cz / s


@njit(cache=True, parallel=True)
def polygon_sums_grad(domain, normal, target, count, u, v, w, vis, vrow, gout, gdom, gnorm, gtgt):
    """Adjoint of :func:`polygon_sums`: ``gout [P]`` (∂loss/∂out) → ∂loss/∂domain ``[P, 4, 3]``, ∂loss/∂normal
    ``[P, 3]``, ∂loss/∂target ``[P, K, 3]`` (written, not accumulated). The visible fractions are constants."""
    for p in prange(domain.shape[0]):
        dom = domain[p]
        n0 = normal[p, 0]
        n1 = normal[p, 1]
        n2 = normal[p, 2]
        poly = target[p]
        cnt = count[p]
        e = np.empty(9)
        gd = np.zeros((4, 3))
        gn = np.zeros(3)
        gt = np.zeros((poly.shape[0], 3))
        for q in range(u.shape[0]):
            uu = u[q]
            vv = v[q]
            a = (1 - uu) * (1 - vv)
            b = uu * (1 - vv)
            c = uu * vv
            ee = (1 - uu) * vv
            x0, x1, x2, du0, du1, du2, dv0, dv1, dv2 = bilinear_map(dom, uu, vv)
            j0 = du1 * dv2 - du2 * dv1
            j1 = du2 * dv0 - du0 * dv2
            j2 = du0 * dv1 - du1 * dv0
            jac = math.sqrt(j0 * j0 + j1 * j1 + j2 * j2)
            wq = w[q] * gout[p]
            if vrow[p] >= 0:
                wq *= vis[vrow[p], q]
            f = _contour(x0, x1, x2, n0, n1, n2, poly, cnt)
            # ∂/∂|J|: w f → ∇_du |J| = dv × m, ∇_dv |J| = m × du (m = J/|J|)
            if jac > 0:
                m0 = j0 / jac
                m1 = j1 / jac
                m2 = j2 / jac
                cj = wq * f
                gu0 = cj * (dv1 * m2 - dv2 * m1)
                gu1 = cj * (dv2 * m0 - dv0 * m2)
                gu2 = cj * (dv0 * m1 - dv1 * m0)
                gv0 = cj * (m1 * du2 - m2 * du1)
                gv1 = cj * (m2 * du0 - m0 * du2)
                gv2 = cj * (m0 * du1 - m1 * du0)
                for k, (cu, cv) in enumerate(((-(1 - vv), -(1 - uu)), ((1 - vv), -uu), (vv, uu), (-vv, (1 - uu)))):
                    gd[k, 0] += cu * gu0 + cv * gv0
                    gd[k, 1] += cu * gu1 + cv * gv1
                    gd[k, 2] += cu * gu2 + cv * gv2
            # ∂/∂f: w |J|; f = −(1/2π) Σ_k γ_k (c_k·n)/|c_k| with a = v_k − x, b = v_{k+1} − x
            coef = -_INV_2PI * wq * jac
            gx0 = 0.0
            gx1 = 0.0
            gx2 = 0.0
            for k in range(cnt):
                k1 = k + 1 if k + 1 < cnt else 0
                _edge_grad(poly[k, 0] - x0, poly[k, 1] - x1, poly[k, 2] - x2, poly[k1, 0] - x0, poly[k1, 1] - x1,
                           poly[k1, 2] - x2, n0, n1, n2, coef, e)
                gt[k, 0] += e[0]
                gt[k, 1] += e[1]
                gt[k, 2] += e[2]
                gt[k1, 0] += e[3]
                gt[k1, 1] += e[4]
                gt[k1, 2] += e[5]
                gx0 -= e[0] + e[3]
                gx1 -= e[1] + e[4]
                gx2 -= e[2] + e[5]
                gn[0] += e[6]
                gn[1] += e[7]
                gn[2] += e[8]
            for k, wk in enumerate((a, b, c, ee)):
                gd[k, 0] += wk * gx0
                gd[k, 1] += wk * gx1
                gd[k, 2] += wk * gx2
        for k in range(4):
            for i in range(3):
                gdom[p, k, i] = gd[k, i]
        for i in range(3):
            gnorm[p, i] = gn[i]
        for k in range(poly.shape[0]):
            for i in range(3):
                gtgt[p, k, i] = gt[k, i]


@njit(cache=True, parallel=True)
def point_polygon_sums(x, normal, poly, count, out):
    """``out[p] = F(x_p → poly[p, :count[p]])`` (Lambert's contour formula; ``x``, ``normal``: ``[P, 3]``)."""
    for p in prange(x.shape[0]):
        out[p] = _contour(x[p, 0], x[p, 1], x[p, 2], normal[p, 0], normal[p, 1], normal[p, 2], poly[p], count[p])


@njit(cache=True, parallel=True)
def point_polygon_grad(x, normal, poly, count, gout, gx, gn, gpoly):
    """Adjoint of :func:`point_polygon_sums`: ``gout [P]`` → ∂loss/∂x ``[P, 3]``, ∂loss/∂normal ``[P, 3]``,
    ∂loss/∂poly ``[P, K, 3]`` (written, not accumulated)."""
    for p in prange(x.shape[0]):
        e = np.empty(9)
        x0 = x[p, 0]
        x1 = x[p, 1]
        x2 = x[p, 2]
        coef = -_INV_2PI * gout[p]
        for i in range(3):
            gx[p, i] = 0.0
            gn[p, i] = 0.0
        for k in range(poly.shape[1]):
            for i in range(3):
                gpoly[p, k, i] = 0.0
        cnt = count[p]
        for k in range(cnt):
            k1 = k + 1 if k + 1 < cnt else 0
            _edge_grad(poly[p, k, 0] - x0, poly[p, k, 1] - x1, poly[p, k, 2] - x2, poly[p, k1, 0] - x0,
                       poly[p, k1, 1] - x1, poly[p, k1, 2] - x2, normal[p, 0], normal[p, 1], normal[p, 2], coef, e)
            for i in range(3):
                gpoly[p, k, i] += e[i]
                gpoly[p, k1, i] += e[3 + i]
                gx[p, i] -= e[i] + e[3 + i]
                gn[p, i] += e[6 + i]


@njit(cache=True, parallel=True)
def quad_points(quads, u, v, out):
    """``out[p, q]`` = the point ``x(u_q, v_q)`` of the bilinear map of ``quads[p] [4, 3]`` (as
    :func:`..geometry._polygon.bilinear`, without the Jacobian)."""
    for p in prange(quads.shape[0]):
        for q in range(u.shape[0]):
            x0, x1, x2, _, _, _, _, _, _ = bilinear_map(quads[p], u[q], v[q])
            out[p, q, 0] = x0
            out[p, q, 1] = x1
            out[p, q, 2] = x2
