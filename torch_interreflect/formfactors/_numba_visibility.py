"""Compiled CPU loops (numba) of the fixed-grid visibility estimate (internal; see
:class:`.visibility.PointVisibility`): the rays from quadrature points to one point per target cell, with their
kernel weights, and the weighted visible fraction once Embree has answered.

The same maths as the torch path of :meth:`.visibility.PointVisibility._fractions` (offsets of
:func:`.visibility.grid_offsets`, the bilinear map, the point-to-point kernel), in float64 where the torch path
rounds to float32 (the rays themselves are float32 for Embree in both), so the two agree to float32 rounding.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._numba_geometry import bilinear_map, jacobian_norm

#: the R2 sequence's step (see :data:`.sampling.R2_STEP`)
_G0 = 0.7548776662466927
_G1 = 0.5698402909980532
#: steps of a second Kronecker sequence (√2 − 1, √3 − 1)
_H0 = 0.41421356237309515
_H1 = 0.7320508075688772


@njit(cache=True, inline="always")
def _point_rays(p, q, Q, x0, x1, x2, na, c, nb, n, seed0, seed1, jitter, margin, eps, end_gap, origin, direction,
                tfar, weight):
    """The ``n × n`` rays of pair ``p``'s point ``q`` at ``x`` to the target quad ``c [4, 3]`` (see :func:`rays`);
    ``na``, ``nb``: the domain's and the target's normals."""
    S = n * n
    for s in range(S):
        iu = s // n
        iv = s - iu * n
        if jitter:
            k = q * S + s + 1
            a = seed0 + k * _G0
            b = seed1 + k * _G1
            xu = margin + (1.0 - 2.0 * margin) * (a - math.floor(a))
            xv = margin + (1.0 - 2.0 * margin) * (b - math.floor(b))
        else:
            xu = 0.5
            xv = 0.5
        y0, y1, y2, du0, du1, du2, dv0, dv1, dv2 = bilinear_map(c, (iu + xu) / n, (iv + xv) / n)
        area = jacobian_norm(du0, du1, du2, dv0, dv1, dv2) / S
        r0 = y0 - x0
        r1 = y1 - x1
        r2 = y2 - x2
        d2 = max(r0 * r0 + r1 * r1 + r2 * r2, 1e-30)
        ca = max(r0 * na[0] + r1 * na[1] + r2 * na[2], 0.0)
        cbk = max(-(r0 * nb[0] + r1 * nb[1] + r2 * nb[2]), 0.0)
        weight[p, q, s] = ca * cbk / (d2 * d2) * area
        length = math.sqrt(d2)
        e0 = r0 / length
        e1 = r1 / length
        e2 = r2 / length
        i = (p * Q + q) * S + s
        gap = eps + end_gap * length
        origin[i, 0] = x0 + gap * e0
        origin[i, 1] = x1 + gap * e1
        origin[i, 2] = x2 + gap * e2
        direction[i, 0] = e0
        direction[i, 1] = e1
        direction[i, 2] = e2
        tfar[i] = length - 2 * gap


@njit(cache=True, parallel=True)
def rays(xs, na, cb, nb, n, seed, jitter, margin, eps, end_gap, origin, direction, tfar, weight):
    """For pair ``p``, point ``q``, cell ``s = iu·n + iv`` of an ``n × n`` grid on the target quad ``cb[p]``:
    the ray from ``xs[p, q]`` to the cell's sample (offset ``margin + (1 − 2 margin)·frac(seed[p] + k·g)``,
    ``k = q·n² + s + 1``, or its midpoint without ``jitter``), less ``eps + end_gap · length`` at each end, and its
    weight ``cos θ_x cos θ_y / d² · area``.

    xs ``[P, Q, 3]``; na, nb ``[P, 3]`` (domain / target normals); cb ``[P, 4, 3]``; seed ``[P, 2]``; outputs
    origin, direction ``[P·Q·S, 3]`` (float32), tfar ``[P·Q·S]`` (float32), weight ``[P, Q, S]`` (float64).
    """
    P, Q = xs.shape[0], xs.shape[1]
    for p in prange(P):
        for q in range(Q):
            _point_rays(p, q, Q, xs[p, q, 0], xs[p, q, 1], xs[p, q, 2], na[p], cb[p], nb[p], n, seed[p, 0],
                        seed[p, 1], jitter, margin, eps, end_gap, origin, direction, tfar, weight)


#: pairs per block of :func:`rule_rays` (its scratch quad is allocated once per block)
_RULE_BLOCK = 64


@njit(cache=True, parallel=True)
def rule_rays(corners, centre, dom, tgt, shift, u, v, normals, rel, n, jitter, margin, eps, end_gap, origin,
              direction, tfar, weight):
    """:func:`rays` from the rule's points on whole facets, without the points in memory: pair ``p``'s point
    ``q`` is the bilinear map of ``corners[dom[p]]`` (float64, rotated by ``shift[p]``) at ``(u_q, v_q)``, moved
    to the caster's frame (``− centre``) and rounded to float32 as the points given to :func:`rays` are; the
    target quad is ``rel[tgt[p]]`` and the normals ``normals[dom[p]]``, ``normals[tgt[p]]`` (the caster-frame
    float32 tables, widened to float64); the pair's seed is :func:`.sampling.pair_seeds`' hash of
    ``(dom[p], tgt[p])``. The same rays, bit for bit."""
    P, Q = dom.shape[0], u.shape[0]
    for blk in prange((P + _RULE_BLOCK - 1) // _RULE_BLOCK):
        quad = np.empty((4, 3))
        for p in range(blk * _RULE_BLOCK, min(P, (blk + 1) * _RULE_BLOCK)):
            a = dom[p]
            b = tgt[p]
            for k in range(4):
                kk = (k + shift[p]) % 4
                quad[k, 0] = corners[a, kk, 0]
                quad[k, 1] = corners[a, kk, 1]
                quad[k, 2] = corners[a, kk, 2]
            seed0 = ((a * 2654435761 + b * 2246822519) % 1048573) / 1048576.0
            seed1 = ((a * 3266489917 + b * 668265263) % 1048571) / 1048576.0
            for q in range(Q):
                x0, x1, x2, _, _, _, _, _, _ = bilinear_map(quad, u[q], v[q])
                x0 = np.float64(np.float32(x0 - centre[0]))
                x1 = np.float64(np.float32(x1 - centre[1]))
                x2 = np.float64(np.float32(x2 - centre[2]))
                _point_rays(p, q, Q, x0, x1, x2, normals[a], rel[b], normals[b], n, seed0, seed1, jitter, margin,
                            eps, end_gap, origin, direction, tfar, weight)


@njit(cache=True, parallel=True)
def fractions(weight, blocked, out):
    """``out[p, q] = Σ_s weight·(not blocked) / Σ_s weight`` (1 where the weights sum to 0); blocked is flat
    ``[P·Q·S]`` in the order of :func:`rays`."""
    P, Q, S = weight.shape
    for p in prange(P):
        for q in range(Q):
            num = 0.0
            den = 0.0
            base = (p * Q + q) * S
            for s in range(S):
                w = weight[p, q, s]
                den += w
                if not blocked[base + s]:
                    num += w
            out[p, q] = num / den if den > 0 else 1.0


@njit(cache=True, parallel=True)
def hemisphere_rays(corners, normals, t1, t2, points, n, seed, eps, origin, direction, area):
    """Rays over the cosine-weighted hemispheres of facets ``[K]``: ``points × points`` points per facet (one per
    cell of the unit square, jittered by the R2 sequence rotated by ``seed[f]``), and from each point ``n × n``
    directions, one per cell of the cosine-weighted square (rotated per point by the R2 sequence), starting
    ``eps`` above the facet. ``area[f, p]``: the point's share of the facet's area (bilinear Jacobian).

    corners ``[K, 4, 3]`` (relative to the caster's origin), normals/t1/t2 ``[K, 3]``, seed ``[K, 2]``; outputs
    origin, direction ``[K·P·D, 3]`` (float32, ``P = points²``, ``D = n²``), area ``[K, P]``.
    """
    K = corners.shape[0]
    P = points * points
    D = n * n
    for f in prange(K):
        c = corners[f]
        total = 0.0
        rad = np.empty(n)  # per point: the grid's radii and heights per row, cosines and sines per column
        lz = np.empty(n)
        cs = np.empty(n)
        sn = np.empty(n)
        for p in range(P):
            a = seed[f, 0] + (p + 1) * _G0
            b = seed[f, 1] + (p + 1) * _G1
            y0, y1, y2, du0, du1, du2, dv0, dv1, dv2 = bilinear_map(
                c, (p // points + (a - math.floor(a))) / points, (p % points + (b - math.floor(b))) / points)
            jac = jacobian_norm(du0, du1, du2, dv0, dv1, dv2)
            area[f, p] = jac
            total += jac
            x0 = y0 + eps * normals[f, 0]
            x1 = y1 + eps * normals[f, 1]
            x2 = y2 + eps * normals[f, 2]
            # the direction grid's rotation for this point: a Kronecker sequence of other steps (√2 − 1, √3 − 1),
            # so that it does not follow the point's offset within its cell
            ra = seed[f, 1] + (p + 1) * _H0
            rb = seed[f, 0] + (p + 1) * _H1
            ou = ra - math.floor(ra)
            ov = rb - math.floor(rb)
            for k in range(n):
                s1 = (k + ou) / n
                rad[k] = math.sqrt(s1)
                lz[k] = math.sqrt(max(1.0 - s1, 0.0))
                ang = 2.0 * math.pi * ((k + ov) / n)
                cs[k] = math.cos(ang)
                sn[k] = math.sin(ang)
            for d in range(D):
                r, c_ = d // n, d % n
                lx = rad[r] * cs[c_]
                ly = rad[r] * sn[c_]
                z = lz[r]
                i = (f * P + p) * D + d
                origin[i, 0] = x0
                origin[i, 1] = x1
                origin[i, 2] = x2
                direction[i, 0] = lx * t1[f, 0] + ly * t2[f, 0] + z * normals[f, 0]
                direction[i, 1] = lx * t1[f, 1] + ly * t2[f, 1] + z * normals[f, 1]
                direction[i, 2] = lx * t1[f, 2] + ly * t2[f, 2] + z * normals[f, 2]
        for p in range(P):
            area[f, p] = area[f, p] / total if total > 0 else 1.0 / P


@njit(cache=True, parallel=True)
def hit_counts(tri, owner, direction, normals, n_dirs, escape, back):
    """Per point of :func:`hemisphere_rays` (its ``n_dirs`` rays in a row): ``escape[q]``, the rays that hit nothing
    (``tri < 0``), and ``back[q]``, the rays whose first hit is a facet's back (its normal along the ray). ``tri``:
    Embree's triangle per ray, ``owner`` the facet of each triangle."""
    for q in prange(escape.shape[0]):
        e = 0
        b = 0
        for d in range(n_dirs):
            r = q * n_dirs + d
            t = tri[r]
            if t < 0:
                e += 1
            else:
                f = owner[t]
                if (direction[r, 0] * normals[f, 0] + direction[r, 1] * normals[f, 1]
                        + direction[r, 2] * normals[f, 2]) > 0:
                    b += 1
        escape[q] = e
        back[q] = b


@njit(cache=True, parallel=True)
def hemisphere_count_sums(area, counts, n_dirs, out):
    """``out[f] = Σ_p area[f, p] · counts[f, p] / n_dirs``: a facet's fraction from its points' ray counts."""
    K, P = area.shape
    for f in prange(K):
        acc = 0.0
        for p in range(P):
            acc += area[f, p] * counts[f, p] / n_dirs
        out[f] = acc
