"""Compiled exact inner integral of the moments (internal; see :mod:`._numba_moments`): the point-to-polygon kernel
times a monomial of the target, ``∫_P k(x, y) m_d(y) dA_y``, exact in the radius.

The target, clipped at the horizon of ``x``, is swept in polar coordinates around the foot ``y*`` of ``x`` on the
target's plane; along each ray the integrand is a polynomial of degree ≤ 3 in the distance ``ρ`` from ``y*`` over
``(h² + ρ²)²`` (``h`` the height of ``x``), whose radial integrals are elementary (:func:`_radial`); the angle is
integrated by Gauss-Legendre per edge under ``σ = d sinh(u)`` (``σ`` the position along the edge, ``d`` its distance
from ``y*``), which makes the angular integrand smooth at every scale, in panels at most ``panel`` wide in ``u``
(:func:`~torch_interreflect.formfactors.moments.angular_panel`: 2 to 4; a point 1e-3 above a unit target, its horizon
cutting the target 1e-3 away: 8 points per panel 2 wide leave 9e-12 where one panel of 8 left 2e-3). For ``m = 1``
this is Lambert's point-to-polygon factor.
"""

from __future__ import annotations

import math

from numba import njit

__all__ = ["KMAX", "clip_polygon", "frame_coords", "inner_exact"]

_INV_PI = 1.0 / math.pi

#: most vertices of a clipped polygon (a quad clipped once: 5, plus one spare)
KMAX = 8

#: below this ``R / h`` the radial integrals are summed as series (:func:`_radial`)
_SERIES_X = 0.1


@njit(cache=True, inline="always")
def frame_coords(x0, x1, x2, c, e1, e2, inv_l):
    """The coordinates ``(p, q)`` of ``x`` in a facet's frame (centroid ``c``, axes ``e1, e2``, ``1 / L``)."""
    d0, d1, d2 = x0 - c[0], x1 - c[1], x2 - c[2]
    return (d0 * e1[0] + d1 * e1[1] + d2 * e1[2]) * inv_l, (d0 * e2[0] + d1 * e2[1] + d2 * e2[2]) * inv_l


@njit(cache=True)
def clip_polygon(V, nv, x, nx, W):
    """Clip the convex polygon ``V[:nv]`` to ``nx·(y − x) ≥ 0`` into ``W``; the vertex count (0 if < 3)."""
    nW = 0
    for k in range(nv):
        a0, a1, a2 = V[k, 0], V[k, 1], V[k, 2]
        kb = k + 1 if k + 1 < nv else 0
        b0, b1, b2 = V[kb, 0], V[kb, 1], V[kb, 2]
        da = nx[0] * (a0 - x[0]) + nx[1] * (a1 - x[1]) + nx[2] * (a2 - x[2])
        db = nx[0] * (b0 - x[0]) + nx[1] * (b1 - x[1]) + nx[2] * (b2 - x[2])
        if da >= 0.0:
            W[nW, 0], W[nW, 1], W[nW, 2] = a0, a1, a2
            nW += 1
        if (da >= 0.0) != (db >= 0.0):
            t = da / (da - db)
            W[nW, 0] = a0 + t * (b0 - a0)
            W[nW, 1] = a1 + t * (b1 - a1)
            W[nW, 2] = a2 + t * (b2 - a2)
            nW += 1
    return nW if nW >= 3 else 0


@njit(cache=True, inline="always")
def _series(x):
    """The series parts of :func:`_radial` for ``x = R / h`` below :data:`_SERIES_X`: the closed forms cancel for a
    target small against its height (t3 lost all digits at R/h = 1e-4), so ``s^m / (1 + s²)² = Σ (−1)^k (k + 1)
    s^(m + 2k)`` is integrated termwise, 12 terms (x^24 < 1e-24)."""
    x2 = x * x
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    p = x2 * x  # x^(3 + 2k)
    sign = 1.0
    for k in range(12):
        s1 += sign * (k + 1) * p / (3 + 2 * k)
        s2 += sign * (k + 1) * p * x / (4 + 2 * k)
        s3 += sign * (k + 1) * p * x2 / (5 + 2 * k)
        p *= x2
        sign = -sign
    return s1, s2, s3


@njit(cache=True, inline="always")
def _radial(h, h2, inv_h, R):
    """``h² J0, h J1, h J2, h J3`` with ``J_n(R) = ∫_0^R ρ^(n+1) / (h² + ρ²)² dρ`` (no ``1/h`` factors left), given
    ``h2 = h²`` and ``inv_h = 1 / h`` (one division here)."""
    R2 = R * R
    inv_den = 1.0 / (h2 + R2)
    x = R * inv_h
    t0 = 0.5 * R2 * inv_den
    if x < _SERIES_X:
        s1, s2, s3 = _series(x)
        return t0, s1, h * s2, h2 * s3
    at = math.atan(x)
    hr = h * R
    t1 = 0.5 * at - 0.5 * hr * inv_den
    t2 = 0.5 * h * (math.log1p(x * x) - R2 * inv_den)
    t3 = hr - 1.5 * h2 * at + 0.5 * h2 * hr * inv_den
    return t0, t1, t2, t3


@njit(cache=True, inline="always")
def _to_frame(W, nw, y0, y1, y2, e1, e2):
    """The clipped polygon ``W[:nw]`` in the target's frame about the foot ``y``, in place (``W[:, 0]``, ``W[:, 1]``);
    its orientation (+1 counter-clockwise, −1 clockwise)."""
    for k in range(nw):
        d0, d1, d2 = W[k, 0] - y0, W[k, 1] - y1, W[k, 2] - y2
        W[k, 0] = d0 * e1[0] + d1 * e1[1] + d2 * e1[2]
        W[k, 1] = d0 * e2[0] + d1 * e2[1] + d2 * e2[2]
    area2 = 0.0
    for k in range(nw):
        kb = k + 1 if k + 1 < nw else 0
        area2 += W[k, 0] * W[kb, 1] - W[k, 1] * W[kb, 0]
    return 1.0 if area2 > 0 else -1.0


@njit(cache=True, inline="always")
def _expand(mom, deg, p0, q0, a0, bp, bq, cpp, cpq, cqq):
    """``mom`` from the rays' sums ``Σ w (c0, p1 c1, q1 c1, p1² c2, p1 q1 c2, q1² c2)``: the monomials of the target
    expanded about the foot ``(p0, q0)``, ``m(p0 + p1 ρ, q0 + q1 ρ)``, once per point rather than at every ray."""
    mom[0] = a0 * _INV_PI
    if deg >= 1:
        mom[1] = (p0 * a0 + bp) * _INV_PI
        mom[2] = (q0 * a0 + bq) * _INV_PI
        if deg >= 2:
            mom[3] = (p0 * p0 * a0 + 2.0 * p0 * bp + cpp) * _INV_PI
            mom[4] = (p0 * q0 * a0 + p0 * bq + q0 * bp + cpq) * _INV_PI
            mom[5] = (q0 * q0 * a0 + 2.0 * q0 * bq + cqq) * _INV_PI


@njit(cache=True)
def inner_exact(x, nx, V, nv, nP, cj, e1, e2, inv_l, deg, gx, gw, panel, W, mom):
    """``mom[d] = ∫_P k(x, y) m_d(y) dA_y`` over the target ``V[:nv]`` (normal ``nP``, frame ``cj, e1, e2``, ``1/L``)
    clipped at the horizon of ``x`` (normal ``nx``); radial integrals exact, angular by the rule ``gx, gw`` on each
    edge's panels at most ``panel`` wide in ``u``. ``W``: scratch ``[KMAX, 3]``."""
    nb = 1 if deg == 0 else (3 if deg == 1 else 6)
    for d in range(nb):
        mom[d] = 0.0
    h = nP[0] * (x[0] - V[0, 0]) + nP[1] * (x[1] - V[0, 1]) + nP[2] * (x[2] - V[0, 2])
    if h <= 0.0:
        return
    nw = clip_polygon(V, nv, x, nx, W)
    if nw == 0:
        return
    h2 = h * h
    inv_h = 1.0 / h
    y0, y1, y2 = x[0] - h * nP[0], x[1] - h * nP[1], x[2] - h * nP[2]
    bs = nx[0] * e1[0] + nx[1] * e1[1] + nx[2] * e1[2]
    bt = nx[0] * e2[0] + nx[1] * e2[1] + nx[2] * e2[2]
    cc = nx[0] * nP[0] + nx[1] * nP[1] + nx[2] * nP[2]
    p0, q0 = frame_coords(y0, y1, y2, cj, e1, e2, inv_l)
    orient = _to_frame(W, nw, y0, y1, y2, e1, e2)
    S = W[:, 0]
    T = W[:, 1]
    a0 = bp = bq = cpp = cpq = cqq = 0.0
    for k in range(nw):
        kb = k + 1 if k + 1 < nw else 0
        as_, at_ = S[k], T[k]
        ds, dt = S[kb] - as_, T[kb] - at_
        ln = math.sqrt(ds * ds + dt * dt)
        if ln <= 0.0:
            continue
        cross = as_ * T[kb] - at_ * S[kb]
        dist = abs(cross) / ln
        if dist <= 1e-13 * ln:
            continue  # the foot lies on this edge's line: the edge subtends no area
        ts, tt = ds / ln, dt / ln
        sa = as_ * ts + at_ * tt
        sb = sa + ln
        fs, ft = as_ - sa * ts, at_ - sa * tt
        ua = math.asinh(sa / dist)
        ub = math.asinh(sb / dist)
        sign = orient if cross > 0 else -orient
        # panels of at most `panel` in u: an edge seen from close by (its length ≫ d) spans many, and the
        # integrand changes where the ray's length passes the height h
        npan = max(1, math.ceil((ub - ua) / panel))
        half = 0.5 * (ub - ua) / npan
        for pan in range(npan):
            mid = ua + (2 * pan + 1) * half
            for g in range(gx.shape[0]):
                u = mid + half * gx[g]
                eu = math.exp(u)  # cosh and sinh from one exponential
                ie = 1.0 / eu
                ch = 0.5 * (eu + ie)
                sig = dist * (0.5 * (eu - ie))
                R = dist * ch
                inv_r = 1.0 / R
                wgt = sign * gw[g] * half * dist * inv_r  # · 1 / cosh(u)
                os_ = (fs + sig * ts) * inv_r
                ot = (ft + sig * tt) * inv_r
                bw = bs * os_ + bt * ot
                t0, t1, t2, t3 = _radial(h, h2, inv_h, R)
                # Σ over the ray of (bw ρ − h cc) m(ρ) ρ / (h² + ρ²)² · h, m = a0 + a1 ρ + a2 ρ²
                c0 = bw * t1 - cc * t0  # a0 term
                c1 = bw * t2 - cc * h * t1  # a1 term
                c2 = bw * t3 - cc * h * t2  # a2 term
                a0 += wgt * c0
                if deg >= 1:
                    p1, q1 = os_ * inv_l, ot * inv_l
                    w1 = wgt * c1
                    bp += w1 * p1
                    bq += w1 * q1
                    if deg >= 2:
                        w2 = wgt * c2
                        cpp += w2 * p1 * p1
                        cpq += w2 * p1 * q1
                        cqq += w2 * q1 * q1
    _expand(mom, deg, p0, q0, a0, bp, bq, cpp, cpq, cqq)
