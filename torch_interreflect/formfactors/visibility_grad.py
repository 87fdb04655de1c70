"""The geometry gradient of occluded form factors: what ray-cast visibility leaves out of autograd.

For a point ``x`` of the domain facet, the visible factor of the target is ``N(x) = ∫_T k(x, y) V(x, y) dA_y`` with
``k = cos θ_x cos θ_y / (π |x − y|²)`` and ``V`` the visibility. Visibility is ray-cast on detached geometry
(:mod:`.visibility`), so autograd through the quadrature carries only the *interior* part of ``dN``. When the
geometry moves, the shadows that blockers cast on the target (seen from ``x``) move too, and ``N`` changes by

    ``dN = − ∮_Γ k(x, y) (u(y) · n(y)) dl``

over the shadow boundary ``Γ`` on the target, with ``n`` its unit normal in the target's plane pointing into the
visible part and ``u`` the boundary's velocity relative to the target's own material points (the target's
parameterisation moves with its corners; that part is interior). This module adds ``−k ℓ (n · Δy)`` at sample
points of ``Γ``: a tensor whose *value is zero* and whose gradient is the boundary term (the reparameterisation
trick of edge sampling, Li et al. 2018, "Differentiable Monte Carlo ray tracing through edge sampling").

``Γ`` is found from the mesh: the candidate edges are the boundary edges (one facet) and the creases (two facets
not coplanar). Each is clipped to lie between ``x`` and the target's plane (in front of ``x``), projected from
``x`` onto that plane, clipped to the target polygon, and sampled by a Gauss rule; a sample counts when exactly one
of two rays from ``x`` to points a little to either side of it is blocked (so an edge seen past another blocker,
or a crease inside a blocker's silhouette, adds nothing). The domain integral uses its own rule: ``points``
low-discrepancy points per facet, rotated per pair (:func:`domain_rule`). The boundary term is discontinuous in
``x`` where a shadow edge leaves the target, so no rule converges fast on one large pair (on the moving-blocker
test 8 × 8 Gauss points were 38 % off, 1,024 R2 points 1.9 %); over many pairs the errors average out.

**The interior term.** Autograd through the quadrature differentiates ``f(x) vis(x)``, the unoccluded factor ``f``
times a visible fraction held fixed: ``∂f · vis``. The interior part of ``dN`` is ``∫ ∂(k J) V``, which equals
``∂f · vis`` only where ``∂(k J)`` is spread over the target like ``k J``. On a ceiling rising above a blocker that
was 10 % off (−0.1696 against −0.1884). :func:`interior_values` adds the difference, ``Σ_c ∂(k_c A_c) (s_c − vis)``
over ``cells × cells`` cells ``c`` of the target with ray-cast visibility ``s_c``: zero where a row is fully
visible (so the exact singular parts of adjacent pairs stay with the quadrature), and zero in value.

What is included: blockers moving, the target moving under a shadow, the domain point moving (the shadow's
projection centre). Not included: shadow edges on the *domain* side (``N(x)`` is continuous in ``x``, so there are
none), visibility changes caused by a facet's own edges (they move with its parameterisation: interior). Cost:
every (pair, point) against every candidate edge, ``[rows, edges]`` work in chunks, then rays for the samples
that land on the target; meant for scenes of up to a few thousand facets.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from ..geometry._polygon import bilinear, clip_interval, clip_segments, quad_coordinates
from ..geometry.edges import candidate_edges
from ..geometry.scene import Scene
from .compiled import launch, loops
from .rules import gauss_legendre01
from .sampling import R2_STEP, pair_seeds

__all__ = [
    "VISIBILITY_GRAD_POINTS", "boundary_values", "candidate_edges", "domain_rule", "interior_values",
    "shadow_spans", "visibility_gradient",
]

#: Default points per occluded pair (``form_factors(visibility_grad_points=)``).
VISIBILITY_GRAD_POINTS = 32
#: Side offset of the two test rays of a boundary sample, as a share of its distance from the point.
_SIDE = 1e-4


def domain_rule(n: int, dom: Tensor, tgt: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """``n`` points ``(u, v)`` ``[P, n]`` on the unit square for each pair ``(dom, tgt)`` ``[P]``, and their weights
    ``1 / n`` ``[n]``: the R2 low-discrepancy sequence rotated per pair by a hash of its facets (Cranley–Patterson),
    so that the pairs' quadrature errors do not line up. Deterministic."""
    k = torch.arange(n, dtype=torch.float64)[None, :, None]
    uv = torch.frac(pair_seeds(dom, tgt)[:, None, :] + k * torch.tensor(R2_STEP, dtype=torch.float64)).to(dtype)
    return uv[..., 0], uv[..., 1], torch.full((n,), 1.0 / n, dtype=dtype)


def visibility_gradient(sc: Scene, dom: Tensor, tgt: Tensor, caster: Any, eps: float, *,
                        points: int = VISIBILITY_GRAD_POINTS, cells: int = 4, edge_order: int = 4) -> Tensor:
    """Zero-valued ``A_dom F_dom,tgt`` (m²) whose gradient is what ray-cast visibility leaves out: the interior
    correction (:func:`interior_values`) plus the boundary term (:func:`boundary_values`). Add it to the values of
    the occluded pairs when the corners require grad.

    Args:
        sc: The scene, float64 on the CPU, its corners requiring grad.
        dom, tgt: Occluded pairs (domain facet, target facet). Shape ``[P]``.
        caster: A :class:`~torch_interreflect.geometry.raycast.RayCaster` of the scene.
        eps: Plane tolerance of the scene (m).
        points: Low-discrepancy points on each domain facet.
        cells: Target cells per direction for the interior correction.
        edge_order: Gauss points per clipped shadow edge.

    Shape:
        - output: ``[P]`` (zeros carrying the gradient)
    """
    rule = domain_rule(points, dom, tgt, sc.corners.dtype)
    out = sc.corners.new_zeros(dom.numel())
    edges = candidate_edges(sc, eps)
    spans = shadow_spans(sc, dom, tgt, rule, edges, eps)
    if spans[0].numel() == 0:
        return out  # no edge casts a shadow on any target: visibility is 0 or 1 at every point
    Q = int(rule[0].shape[1])
    rows = torch.unique(spans[0] * Q + spans[1])  # (pair, point) rows with a shadow edge on the target
    out = out + interior_values(sc, dom, tgt, caster, rule, cells, rows)
    return out + boundary_values(sc, dom, tgt, caster, rule, spans, edges, edge_order=edge_order)


def interior_values(sc: Scene, dom: Tensor, tgt: Tensor, caster: Any, rule: tuple[Tensor, Tensor, Tensor],
                    cells: int, rows: Tensor, chunk: int = 1 << 18, *, points: Tensor | None = None) -> Tensor:
    """Zero-valued ``[P]`` (m²) whose gradient is ``Σ_q w_q J_q Σ_c ∂(k_c A_c) (s_c − vis_q)``: the interior part of
    the occluded pairs' derivative that ``∂f · vis`` misses (module docstring). ``rule``: domain points
    ``(u, v, w)`` (:func:`domain_rule`); ``cells × cells`` midpoint cells on each target; ``rows``: the
    ``pair · Q + point`` rows to evaluate (the others have no shadow edge on their target, so ``s_c = vis``).
    ``points``: with a one-point rule, the domain point of each pair ``[P, 3]`` carrying its own gradient (e.g. a
    pixel's hit point, which moves along its camera ray) in place of the point that follows its facet's corners."""
    corners = sc.corners
    cd = corners.detach()
    uq, vq, wq = rule
    Q = int(uq.shape[1])
    normals, normals_g = sc.normals.detach(), sc.normals
    g = (torch.arange(cells, dtype=cd.dtype) + 0.5) / cells
    uc, vc = g.repeat_interleave(cells), g.repeat(cells)
    C = cells * cells
    out = corners.new_zeros(dom.numel())
    for s in range(0, rows.numel(), max(1, chunk // C)):
        r = rows[s : s + max(1, chunk // C)]
        p, q = r // Q, r % Q
        a, b = dom[p], tgt[p]
        u, v = uq[p, q][:, None], vq[p, q][:, None]
        x, jx = bilinear(cd[a], u, v)  # [R, 1, 3]
        y, jy = bilinear(cd[b], uc, vc)  # [R, C, 3]
        start = x.expand(-1, C, -1).reshape(-1, 3)
        seen = ~torch.from_numpy(caster.segments_blocked(start.numpy(), y.reshape(-1, 3).numpy())).reshape(-1, C)
        seen = seen.to(cd.dtype)
        ka = _kernel(x, normals[a][:, None], y, normals[b][:, None]) * jy  # [R, C]
        den = ka.sum(-1, keepdim=True)
        vis = torch.where(den > 0, (ka * seen).sum(-1, keepdim=True) / den.clamp_min(1e-300), torch.ones_like(den))
        weight = (seen - vis) * (jx[:, 0] * wq[q])[:, None] / C  # [R, C], constants of the geometry
        live = torch.nonzero((weight != 0).any(-1)).reshape(-1)
        if live.numel():
            # recomputed in the backward: the graph keeps the chunk's inputs, not its [R, C] temporaries
            xg = None if points is None else points[p[live]]
            val = checkpoint(_interior_chunk, corners, normals_g, a[live], b[live], u[live], v[live], uc, vc,
                             weight[live], xg, use_reentrant=False)
            out = out.index_add(0, p[live], val)
    return out


def _interior_chunk(corners: Tensor, normals: Tensor, a: Tensor, b: Tensor, uq: Tensor, vq: Tensor, uc: Tensor,
                    vc: Tensor, weight: Tensor, points: Tensor | None = None) -> Tensor:
    """``Σ_c k(x, y_c) J_c · weight`` per row (domain facet ``a``, point ``(uq, vq)`` ``[R, 1]`` or ``points
    [R, 3]``, target ``b``; differentiable in ``corners``, ``normals`` and ``points``)."""
    xg = bilinear(corners[a], uq, vq)[0] if points is None else points[:, None, :]  # [R, 1, 3]
    yg, jyg = bilinear(corners[b], uc, vc)  # [R, C, 3]
    kag = _kernel(xg, normals[a][:, None], yg, normals[b][:, None]) * jyg
    return ((kag - kag.detach()) * weight).sum(-1)  # exactly zero in value


def _project(x: Tensor, b: Tensor, o: Tensor, n: Tensor) -> Tensor:
    """Central projection ``[n, 3]`` from points ``x`` through points ``b`` onto the planes ``(o, n)`` (all
    ``[n, 3]``; ``b`` strictly between ``x`` and its plane)."""
    D = ((x - o) * n).sum(-1)
    return x + (b - x) * (D / (D - ((b - o) * n).sum(-1)))[:, None]


def _kernel(x: Tensor, nx: Tensor, y: Tensor, ny: Tensor) -> Tensor:
    """``cos θ_x cos θ_y / (π |x − y|²)`` (broadcast; 1/m²)."""
    r = y - x
    d2 = (r * r).sum(-1).clamp_min(1e-300)
    return (r * nx).sum(-1).clamp_min(0) * (-(r * ny).sum(-1)).clamp_min(0) / (math.pi * d2 * d2)


def shadow_spans(sc: Scene, dom: Tensor, tgt: Tensor, rule: tuple[Tensor, Tensor, Tensor],
                 edges: tuple[Tensor, Tensor], eps: float, chunk: int = 1 << 21) -> tuple[Tensor, ...]:
    """Shadow-edge candidates on the targets of pairs ``(dom, tgt)``, seen from the domain points ``rule``
    (:func:`domain_rule`): flat ``(pair, point, edge, s_a, s_b, λ_a, λ_b)`` (the edge's clipped part ``[s_a, s_b]``
    between the point and the target's plane, and ``[λ_a, λ_b]``, the part of its projection inside the target),
    with ``edge`` indexing ``edges`` (:func:`candidate_edges`). At most ``chunk`` (point, edge) combinations at once."""
    cd = sc.corners.detach()
    facet, corner = edges
    empty = torch.zeros(0, dtype=torch.int64)
    if facet.numel() == 0 or dom.numel() == 0:
        return empty, empty, empty, *(torch.zeros(0, dtype=cd.dtype) for _ in range(4))
    e0, e1 = cd[facet, corner], cd[facet, (corner + 1) % 4]
    uq, vq, _ = rule
    Q = int(uq.shape[1])
    normals = sc.normals.detach()
    kern = loops("shadows")
    pe, ee = _pair_edges(kern, cd, normals, dom, tgt, e0, e1, eps, chunk)
    per = max(1, chunk // Q)
    if kern is not None:
        found = [_compiled_samples(kern, cd, normals, pe[s : s + per], ee[s : s + per], dom, tgt, uq, vq, e0, e1,
                                   eps) for s in range(0, pe.numel(), per)]
    else:
        found = [_samples(cd, normals, pe[s : s + per], ee[s : s + per], dom[pe[s : s + per]],
                          tgt[pe[s : s + per]], uq, vq, e0, e1, eps) for s in range(0, pe.numel(), per)]
    if not found:
        return empty, empty, empty, *(torch.zeros(0, dtype=cd.dtype) for _ in range(4))
    return tuple(torch.cat(c) for c in zip(*found, strict=True))


def boundary_values(sc: Scene, dom: Tensor, tgt: Tensor, caster: Any, rule: tuple[Tensor, Tensor, Tensor],
                    spans: tuple[Tensor, ...], edges: tuple[Tensor, Tensor], *, edge_order: int = 4,
                    points: Tensor | None = None) -> Tensor:
    """Zero-valued ``A_dom F_dom,tgt`` corrections ``[P]`` (m²) whose gradient is the boundary term (module
    docstring), from the candidates ``spans`` of :func:`shadow_spans` (same ``rule`` and ``edges``), ``edge_order``
    Gauss points per clipped edge. ``points``: as for :func:`interior_values`."""
    corners = sc.corners
    out = corners.new_zeros(dom.numel())
    cd = corners.detach()
    facet, corner = edges
    e0, e1 = cd[facet, corner], cd[facet, (corner + 1) % 4]
    uq, vq, wq = rule
    normals = sc.normals.detach()
    p, q, e, sa, sb, la, lb = spans
    if p.numel() == 0:
        return out
    # per span: the domain point, the projected ends; then Gauss points on each clipped, projected segment
    x, jac = bilinear(cd[dom[p]], uq[p, q][:, None], vq[p, q][:, None])
    x, jac = x[:, 0], jac[:, 0]
    nj, oj = normals[tgt[p]], cd[tgt[p], 0]
    D = ((x - oj) * nj).sum(-1)
    ya, yb = (_project(x, e0[e] + t[:, None] * (e1[e] - e0[e]), oj, nj) for t in (sa, sb))
    ga = D - ((e0[e] + sa[:, None] * (e1[e] - e0[e]) - oj) * nj).sum(-1)
    gb = D - ((e0[e] + sb[:, None] * (e1[e] - e0[e]) - oj) * nj).sum(-1)
    tl, wl = gauss_legendre01(edge_order, cd.dtype)
    lam = (la[:, None] + (lb - la)[:, None] * tl).reshape(-1)
    span = ((lb - la)[:, None] * wl).reshape(-1)
    p, q, e, sa, sb, x, jac, nj, ya, yb, ga, gb = (z.repeat_interleave(edge_order, 0)
                                                   for z in (p, q, e, sa, sb, x, jac, nj, ya, yb, ga, gb))
    a, b = dom[p], tgt[p]
    sigma = lam * ga / (lam * ga + (1 - lam) * gb)
    par = sa + sigma * (sb - sa)  # the edge parameter whose projection is the sample
    y = ya + lam[:, None] * (yb - ya)
    seg = yb - ya
    length = seg.norm(dim=-1)
    ell = length * span
    side = torch.linalg.cross(nj, seg / length.clamp_min(1e-300)[:, None], dim=-1)
    r = y - x
    dist = r.norm(dim=-1)
    off = (_SIDE * dist)[:, None] * side
    xs = x.numpy()
    plus = torch.from_numpy(caster.segments_blocked(xs, (y + off).numpy()))
    minus = torch.from_numpy(caster.segments_blocked(xs, (y - off).numpy()))
    edge = plus != minus
    if not bool(edge.any()):
        return out
    sign = torch.where(minus, 1.0, -1.0).to(cd.dtype)  # n points into the visible side
    k = _kernel(x, normals[a], y, nj)
    coef = (-k * ell * sign * jac * wq[q])[edge]
    n_in = side[edge]
    p, q, e, par, y, a, b = (z[edge] for z in (p, q, e, par, y, a, b))
    # the differentiable positions: the shadow point, and the target's material point under it
    xg = bilinear(corners[a], uq[p, q][:, None], vq[p, q][:, None])[0][:, 0] if points is None else points[p]
    g0 = corners[facet[e], corner[e]]
    g1 = corners[facet[e], (corner[e] + 1) % 4]
    bg = g0 + par[:, None] * (g1 - g0)
    njg, ojg = sc.normals[b], corners[b, 0]
    yg = _project(xg, bg, ojg, njg)
    u, v = quad_coordinates(cd[b], y)
    ym, _ = bilinear(corners[b], u[:, None], v[:, None])
    ym = ym[:, 0]
    move = (yg - yg.detach()) - (ym - ym.detach())
    contrib = coef * (n_in * move).sum(-1)
    return out.index_add(0, p, contrib)


def _pair_edges(kern: Any, cd: Tensor, normals: Tensor, dom: Tensor, tgt: Tensor, e0: Tensor, e1: Tensor, eps: float,
                chunk: int) -> tuple[Tensor, Tensor]:
    """``(pair, edge)`` combinations that can cast a shadow edge: the edge reaches in front of both facets' planes
    and its bounding box meets the pair's (which holds every segment between the two facets). Compiled
    (:mod:`._numba_shadows`) when ``kern`` is given."""
    lo = torch.minimum(cd[dom].amin(1), cd[tgt].amin(1))  # [P, 3]
    hi = torch.maximum(cd[dom].amax(1), cd[tgt].amax(1))
    elo, ehi = torch.minimum(e0, e1), torch.maximum(e0, e1)  # [E, 3]
    out_p, out_e = [], []
    per = max(1, chunk // e0.shape[0])
    for s in range(0, dom.numel(), per):
        a, b = dom[s : s + per], tgt[s : s + per]
        if kern is not None:
            mask = torch.empty(a.numel(), e0.shape[0], dtype=torch.bool)
            args = [t.contiguous().numpy() for t in (cd.double(), normals.double(), a, b, e0.double(), e1.double())]
            launch(kern.pair_edge_mask, *args, float(eps), mask.numpy())
        else:
            mask = ((elo[None] <= hi[s : s + per, None] + eps) & (ehi[None] >= lo[s : s + per, None] - eps)).all(-1)
            for f in (a, b):
                n, o = normals[f][:, None, :], cd[f, 0][:, None, :]
                mask &= torch.maximum(((e0[None] - o) * n).sum(-1), ((e1[None] - o) * n).sum(-1)) > eps
        pc, ec = torch.nonzero(mask, as_tuple=True)
        out_p.append(pc + s)
        out_e.append(ec)
    return torch.cat(out_p), torch.cat(out_e)


def _compiled_samples(kern: Any, cd: Tensor, normals: Tensor, p: Tensor, ed: Tensor, dom: Tensor, tgt: Tensor,
                      uq: Tensor, vq: Tensor, e0: Tensor, e1: Tensor, eps: float) -> tuple[Tensor, ...]:
    """:func:`_samples` through the compiled loop (:mod:`._numba_shadows`)."""
    M, Q = p.numel(), uq.shape[1]
    sa, sb, la, lb = (torch.empty(M, Q, dtype=torch.float64) for _ in range(4))
    ok = torch.empty(M, Q, dtype=torch.bool)
    args = [t.contiguous().numpy() for t in (cd.double(), normals.double(), uq.double(), vq.double(), p, ed, dom, tgt,
                                             e0.double(), e1.double())]
    launch(kern.edge_spans, *args, float(eps), sa.numpy(), sb.numpy(), la.numpy(), lb.numpy(), ok.numpy())
    mc, qc = torch.nonzero(ok, as_tuple=True)
    return p[mc], qc, ed[mc], sa[mc, qc], sb[mc, qc], la[mc, qc], lb[mc, qc]


def _samples(cd: Tensor, normals: Tensor, p: Tensor, ed: Tensor, a: Tensor, b: Tensor, uq: Tensor, vq: Tensor,
             e0: Tensor, e1: Tensor, eps: float) -> tuple[Tensor, ...]:
    """For combinations of pairs ``p`` (domain ``a``, target ``b``) and edges ``ed`` ``[M]``, and every domain
    point: the edge's part between the point and the target's plane, projected and clipped to the target. Returns
    flat ``(pair, point, edge, s_a, s_b, λ_a, λ_b)`` of the non-empty ones (edge parameters of the clipped part,
    and the part of its projection inside the target)."""
    x, _ = bilinear(cd[a], uq[p], vq[p])  # [M, Q, 3]
    E0, E1 = e0[ed][:, None, :], e1[ed][:, None, :]  # [M, 1, 3]
    nx, nj, oj = normals[a][:, None, :], normals[b][:, None, :], cd[b, 0][:, None, :]
    D = ((x - oj) * nj).sum(-1)  # [M, Q]
    d0 = ((E0 - oj) * nj).sum(-1)  # [M, 1]
    d1 = ((E1 - oj) * nj).sum(-1)
    h0 = ((E0 - x) * nx).sum(-1)  # [M, Q]
    h1 = ((E1 - x) * nx).sum(-1)
    lo = torch.zeros_like(h0)
    hi = torch.ones_like(h0)
    lo, hi = clip_interval(lo, hi, d0 - eps, d1 - d0)  # in front of the target's plane
    lo, hi = clip_interval(lo, hi, D - eps - d0, d0 - d1)  # behind the point
    lo, hi = clip_interval(lo, hi, h0 - eps, h1 - h0)  # in front of the point's plane
    mc, qc = torch.nonzero(hi > lo, as_tuple=True)
    sa, sb = lo[mc, qc], hi[mc, qc]
    pc, ec = p[mc], ed[mc]
    xs = x[mc, qc]
    njs, ojs = normals[b[mc]], cd[b[mc], 0]
    ya, yb = (_project(xs, e0[ec] + t[:, None] * (e1[ec] - e0[ec]), ojs, njs) for t in (sa, sb))
    la, lb = clip_segments(ya, yb, cd[b[mc]], njs)
    keep = (lb - la) * (yb - ya).norm(dim=-1) > eps
    return pc[keep], qc[keep], ec[keep], sa[keep], sb[keep], la[keep], lb[keep]
