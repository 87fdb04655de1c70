"""The fused form-factor quadrature: Lambert's contour formula, horizon clipping and the per-pair Gauss sum in
one compiled loop over pairs, on every core.

:func:`grouped_sums` runs every unoccluded rule group in one launch (runs of equal point counts across the
threads); :func:`group_sums` one rule, with visibility. They and :func:`fan_sums` give the same numbers as the
torch quadrature of :func:`~torch_interreflect.formfactors.pair_values` (float64, to rounding), without its ~25
temporaries per point: on CPU through numba (``@njit(parallel=True)``, threads = ``torch.get_num_threads()``),
elsewhere (a CUDA device) through the same maths in torch.

Gradients to the geometry: when an input requires grad (CPU), the domains, clipped targets and normals are gathered
in torch (a graph of O(pairs) size) and the sums run through a compiled loop with a compiled, hand-written adjoint
(derivatives of Lambert's edge terms, the bilinear map and its Jacobian); of the quadrature points only the visible
fractions of occluded pairs are kept. It agrees with autograd through the torch path to rounding
(``tests/formfactors/test_geometry_grad.py``). First derivatives only (``create_graph=True`` raises: use
``backend="torch"`` for higher orders).

``backend`` (of :func:`~torch_interreflect.form_factors` and of the functions here) selects the path:
``"fused"`` / ``"auto"`` (the compiled loop, and its adjoint under autograd, where they apply; torch otherwise;
``"auto"`` is the default), ``"torch"`` (always torch: the reference).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from .._threads import work_threads
from ..geometry._polygon import bilinear, clip_polygons
from .compiled import launch, loops
from .contour import point_polygon_factor

__all__ = ["Backend", "fan_sums", "first_order_only", "fused_available", "group_sums", "grouped_sums",
           "resolve_backend"]

Backend = Literal["auto", "fused", "torch"]
#: Visible fractions ``[R, Q]`` at points ``x [R, Q, 3]`` of pairs ``(dom [R], tgt [R])``.
Visibility = Callable[[Tensor, Tensor, Tensor], Tensor]
#: Quadrature points evaluated per call of the compiled loop (bounds the visibility temporaries).
_CHUNK_POINTS = 1 << 21


def fused_available(*tensors: Tensor) -> bool:
    """Whether the compiled loop can take these inputs: numba present, CPU tensors, none requiring grad."""
    if loops() is None:
        return False
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    return not grad and all(t.device.type == "cpu" for t in tensors)


def resolve_backend(backend: Backend, *tensors: Tensor) -> bool:
    """True for the compiled loop, False for torch, from ``backend`` and the inputs (see the module doc)."""
    if backend not in ("auto", "fused", "torch"):
        raise ValueError(f"backend must be 'auto', 'fused' or 'torch'; got {backend!r}")
    return backend != "torch" and fused_available(*tensors)


def _np(t: Tensor):
    return t.detach().contiguous().numpy()


def _domains(corners: Tensor, dom: Tensor, shift: Tensor) -> Tensor:
    """The domain quads ``[P, 4, 3]``, corners rotated by ``shift`` (the shared edge/vertex first)."""
    idx = (torch.arange(4, device=dom.device)[None, :] + shift[:, None]) % 4
    return torch.gather(corners[dom], 1, idx[..., None].expand(-1, -1, 3))


def _visible_rows(
    need: Tensor | None, vis: Visibility | None, quads: Callable[[Tensor], Tensor], u: Tensor, v: Tensor,
    dom: Tensor, tgt: Tensor, whole: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """Visible fractions ``[R, Q]`` of the pairs that need rays, and each pair's row in it (-1: fully visible).

    ``quads(rows)`` gives the domain quads ``[R, 4, 3]`` of those pairs (their points are ``bilinear(quads, u, v)``).
    ``whole = (corners, shift)``: the domains are whole facets (``corners[dom]`` rotated by ``shift``), so a
    :class:`~.visibility.PointVisibility` builds the rays from the rule itself (no points in memory).
    """
    P = dom.numel()
    vrow = torch.full((P,), -1, dtype=torch.int64)
    if need is None or vis is None or not bool(need.any()):
        return torch.ones(1, u.numel(), dtype=torch.float64), vrow
    rows = torch.nonzero(need).reshape(-1)
    vrow[rows] = torch.arange(rows.numel())
    rule_fractions = getattr(vis, "rule_fractions", None)
    if whole is not None and rule_fractions is not None:  # domains are whole facets: no points in memory
        fr = rule_fractions(whole[0], dom[rows], tgt[rows], whole[1][rows], u, v)
        if fr is not None:
            return fr.contiguous(), vrow
    q = quads(rows).detach()
    if loops() is not None and q.device.type == "cpu":
        x = torch.empty(rows.numel(), u.numel(), 3, dtype=torch.float64)
        launch(loops().quad_points, _np(q.double()), _np(u.double()), _np(v.double()), x.numpy())
    else:
        x, _ = bilinear(q, u, v)
    return vis(x, dom[rows], tgt[rows]).to(torch.float64).contiguous(), vrow


def first_order_only() -> None:
    """The compiled adjoints give first derivatives only: a backward that builds a graph (``create_graph=True``,
    for second derivatives or gradient penalties) would silently treat them as constants."""
    if torch.is_grad_enabled():
        raise RuntimeError("the compiled adjoint of the form factors gives first derivatives only (create_graph=True "
                           "needs a graph of the gradient): use form_factors(..., backend='torch') for higher orders")


class _PolygonSums(torch.autograd.Function):
    """The compiled :func:`polygon_sums` loop with its compiled adjoint (gradients to the domain quads, normals and
    target polygons; visible fractions are constants). Memory O(pairs): of the quadrature points only the visible
    fractions of occluded pairs are kept. First derivatives only."""

    @staticmethod
    def forward(ctx, domain, normal, target, count, u, v, w, vis, vrow):  # type: ignore[override]
        out = torch.empty(domain.shape[0], dtype=torch.float64)
        args = [_np(t.double()) if t.is_floating_point() else _np(t) for t in (domain, normal, target, count, u, v, w,
                                                                              vis, vrow)]
        if domain.shape[0]:
            launch(loops().polygon_sums, *args, out.numpy())
        ctx.save_for_backward(domain, normal, target, count, u, v, w, vis, vrow)
        return out.to(domain.dtype)

    @staticmethod
    def backward(ctx, gout):  # type: ignore[override]
        first_order_only()
        domain, normal, target, count, u, v, w, vis, vrow = ctx.saved_tensors
        P = domain.shape[0]
        gd = torch.zeros(P, 4, 3, dtype=torch.float64)
        gn = torch.zeros(P, 3, dtype=torch.float64)
        gt = torch.zeros(target.shape, dtype=torch.float64)
        if P:
            args = [_np(t.double()) if t.is_floating_point() else _np(t) for t in (domain, normal, target, count, u, v,
                                                                                  w, vis, vrow)]
            launch(loops().polygon_sums_grad, *args, _np(gout.double()), gd.numpy(), gn.numpy(), gt.numpy())
        return gd.to(domain.dtype), gn.to(normal.dtype), gt.to(target.dtype), None, None, None, None, None, None


class _PairSums(torch.autograd.Function):
    """The compiled :func:`pair_sums` loop for pairs whose target is not clipped, with its compiled adjoint to the
    facets' corners and normals. Keeps only the pair indices (and visible fractions) for the backward; domains and
    targets are gathered again there, a chunk at a time."""

    @staticmethod
    def forward(ctx, corners, normals, cent, dom, tgt, shift, u, v, w, vis, vrow):  # type: ignore[override]
        out = torch.empty(dom.numel(), dtype=torch.float64)
        if dom.numel():
            clip = torch.zeros(dom.numel(), dtype=torch.bool)
            launch(loops().pair_sums, _np(corners.double()), _np(normals.double()), _np(cent.double()), _np(dom),
                 _np(tgt), _np(shift), _np(clip), torch.arange(dom.numel()).numpy(), _np(u), _np(v), _np(w), 0.0,
                 _np(vis), _np(vrow), out.numpy())
        ctx.save_for_backward(corners, normals, dom, tgt, shift, u, v, w, vis, vrow)
        return out.to(corners.dtype)

    @staticmethod
    def backward(ctx, gout):  # type: ignore[override]
        first_order_only()
        corners, normals, dom, tgt, shift, u, v, w, vis, vrow = ctx.saved_tensors
        c = corners.detach().double()
        n = normals.detach().double()
        gc = torch.zeros(c.shape[0] * 4, 3, dtype=torch.float64)
        gn = torch.zeros(n.shape, dtype=torch.float64)
        step = 1 << 16
        for s in range(0, dom.numel(), step):
            d, t, sh = dom[s : s + step], tgt[s : s + step], shift[s : s + step]
            quads, target = _domains(c, d, sh).contiguous(), c[t].contiguous()
            P = d.numel()
            gd = torch.empty(P, 4, 3, dtype=torch.float64)
            gnp = torch.empty(P, 3, dtype=torch.float64)
            gt = torch.empty(P, 4, 3, dtype=torch.float64)
            count = torch.full((P,), 4, dtype=torch.int64)
            launch(loops().polygon_sums_grad, quads.numpy(), _np(n[d]), target.numpy(), count.numpy(), _np(u),
                 _np(v), _np(w), _np(vis), _np(vrow[s : s + step]), _np(gout[s : s + step].double()), gd.numpy(),
                 gnp.numpy(), gt.numpy())
            k = torch.arange(4)
            gc.index_add_(0, (d[:, None] * 4 + (k[None, :] + sh[:, None]) % 4).reshape(-1), gd.reshape(-1, 3))
            gc.index_add_(0, (t[:, None] * 4 + k[None, :]).reshape(-1), gt.reshape(-1, 3))
            gn.index_add_(0, d, gnp)
        return (gc.reshape(corners.shape).to(corners.dtype), gn.to(normals.dtype), None, None, None, None, None, None,
                None, None, None)


def _adjoint_wanted(backend: Backend, *tensors: Tensor) -> bool:
    """Whether to run the compiled loop with its adjoint: autograd needs the inputs, numba is there, CPU."""
    if backend not in ("auto", "fused", "torch"):
        raise ValueError(f"backend must be 'auto', 'fused' or 'torch'; got {backend!r}")
    if backend == "torch" or loops() is None:
        return False
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors) and all(
        t.device.type == "cpu" for t in tensors)


def group_sums(
    corners: Tensor,
    normals: Tensor,
    cent: Tensor,
    dom: Tensor,
    tgt: Tensor,
    shift: Tensor,
    clip: Tensor,
    rule: tuple[Tensor, Tensor, Tensor],
    eps: float,
    need: Tensor | None = None,
    vis: Visibility | None = None,
    backend: Backend = "auto",
    *,
    chunk_points: int = 1 << 18,
    select: Tensor | None = None,
    out: Tensor | None = None,
) -> Tensor:
    """``A_dom F_dom,tgt`` (not clamped) of pairs whose domain is a whole facet, by one rule.

    Args:
        corners: Facet corners in metres, float64. Shape ``[F, 4, 3]``.
        normals: Unit facet normals. Shape ``[F, 3]``.
        cent: Facet centroids in metres. Shape ``[F, 3]``.
        dom: Integration facet of each pair. Shape ``[P]``.
        tgt: Contour facet of each pair. Shape ``[P]``.
        shift: Rotation of the domain's corners (the shared edge or vertex first, for graded rules). ``[P]``.
        clip: Whether the target crosses the domain's plane (it is clipped at the horizon). Bool ``[P]``.
        rule: ``(u, v, w)``, each ``[Q]``, on the unit square (:func:`.rules.quadrature_rule`).
        eps: Plane tolerance in metres (:func:`..geometry._polygon.plane_eps`).
        need: Pairs whose points get visible fractions from ``vis``. Bool ``[P]`` (None: all visible).
        vis: Visible fractions of points (a :class:`.visibility.PointVisibility`).
        backend: See the module doc.
        chunk_points: Quadrature points × polygon corners per chunk of the torch path.
        select: Integrate only the pairs at these indices (int64 ``[N]``) of ``dom, tgt, shift, clip, need``; the
            compiled loop reads them in place, with no gathered copies (default: all pairs).
        out: Write the sums into ``out`` (float64 ``[P]``) at ``select`` and return it, rather than a new tensor.

    Returns:
        ``Σ_q F(x_q → target) |J_q| w_q vis_q`` in m². Shape ``[P]`` (``[N]`` with ``select`` and no ``out``).
    """
    u, v, w = rule
    fused = not _adjoint_wanted(backend, corners, normals, cent) and resolve_backend(backend, corners, normals, cent)
    if not fused:
        if select is not None:
            dom, tgt, shift, clip = dom[select], tgt[select], shift[select], clip[select]
            need = need[select] if need is not None else None
        if _adjoint_wanted(backend, corners, normals, cent):
            sums = _adjoint_group_sums(corners, normals, cent, dom, tgt, shift, clip, rule, eps, need, vis)
        else:
            sums = _torch_group_sums(corners, normals, cent, dom, tgt, shift, clip, rule, eps, need, vis,
                                     chunk_points)
        if out is None:
            return sums
        if select is None:
            out.copy_(sums)
        else:
            out[select] = sums
        return out
    sel = torch.arange(dom.numel()) if select is None else select
    into = torch.empty(dom.numel(), dtype=torch.float64) if out is None else out
    per = max(64, _CHUNK_POINTS // u.numel())
    args = [_np(t) for t in (corners, normals, cent, dom, tgt, shift, clip)]
    rule_np = [_np(t) for t in (u, v, w)]
    no_rays = need is None or vis is None or not bool(need.any())
    for s in range(0, sel.numel(), per):
        p = sel[s : s + per]
        if no_rays:  # an empty vrow: every pair fully visible (no [N] fill between the compiled launches)
            fr, vrow = torch.ones(1, u.numel(), dtype=torch.float64), torch.empty(0, dtype=torch.int64)
        else:
            d, t, sh = dom[p], tgt[p], shift[p]
            fr, vrow = _visible_rows(need[p], vis, lambda r: _domains(corners, d[r], sh[r]), u, v, d, t,  # noqa: B023
                                     whole=(corners, sh))
        launch(loops().pair_sums, *args, _np(p), *rule_np, float(eps), _np(fr), _np(vrow), into.numpy())
    return into if out is not None or select is None else into[select]


def grouped_sums(
    corners: Tensor,
    normals: Tensor,
    cent: Tensor,
    pairs: tuple[Tensor, Tensor, Tensor, Tensor],
    parts: list[tuple[tuple[Tensor, Tensor, Tensor], Tensor]],
    eps: float,
    out: Tensor,
    backend: Backend = "auto",
    chunk_points: int = 1 << 18,
) -> None:
    """:func:`group_sums` of several rule groups, every point visible, written into ``out``: on the CPU one
    launch of the compiled loop for all groups, cut into runs of equal point counts (one launch per group costs
    a thread wake-up each, and a small group cannot keep two threads busy); the other paths one group at a time.

    Args:
        corners, normals, cent, eps, backend, chunk_points: As in :func:`group_sums`.
        pairs: ``(dom, tgt, shift, clip)``, each ``[P]``, as in :func:`group_sums`.
        parts: ``(rule, select)`` per group: the rule ``(u, v, w)`` and the pair indices (int64) it integrates.
        out: float64 ``[P]``, written at every ``select``.
    """
    dom, tgt, shift, clip = pairs
    parts = [(rule, sel) for rule, sel in parts if sel.numel()]
    if not parts:
        return
    fused = not _adjoint_wanted(backend, corners, normals, cent) and resolve_backend(backend, corners, normals, cent)
    if not fused:
        for rule, sel in parts:
            group_sums(corners, normals, cent, dom, tgt, shift, clip, rule, eps, backend=backend,
                       chunk_points=chunk_points, select=sel, out=out)
        return
    size = torch.tensor([rule[0].numel() for rule, _ in parts], dtype=torch.int64)
    table = torch.zeros(3, len(parts), int(size.max()), dtype=torch.float64)
    for g, (rule, _) in enumerate(parts):
        for k in range(3):
            table[k, g, : rule[k].numel()] = rule[k]
    bounds = torch.zeros(len(parts) + 1, dtype=torch.int64)
    bounds[1:] = torch.cumsum(torch.tensor([sel.numel() for _, sel in parts]), 0)
    # numpy, not torch.cat: a torch parallel region right before the launch leaves OpenMP workers spinning on a core
    sel = parts[0][1] if len(parts) == 1 else torch.from_numpy(np.concatenate([_np(sel) for _, sel in parts]))
    blocks = max(1, min(int(bounds[-1]), 64 * work_threads()))
    launch(loops().rule_sums, *(_np(t) for t in (corners, normals, cent, dom, tgt, shift, clip, sel, bounds,
                                                 table[0], table[1], table[2], size)), float(eps), blocks, out.numpy())


def _adjoint_group_sums(corners, normals, cent, dom, tgt, shift, clip, rule, eps, need, vis) -> Tensor:
    """:func:`group_sums` for inputs that require grad, with compiled sums and adjoints: whole targets through
    :class:`_PairSums` (only the pair indices are kept), clipped targets (pairs straddling the domain's plane)
    through :class:`_PolygonSums` with the clipping differentiated in torch."""
    u, v, w = rule
    out = []
    per = max(64, _CHUNK_POINTS // u.numel())
    for s in range(0, dom.numel(), per):
        d, t, sh = dom[s : s + per], tgt[s : s + per], shift[s : s + per]
        nd = need[s : s + per] if need is not None else None
        cut = clip[s : s + per]
        fr, vrow = _visible_rows(nd, vis, lambda r: _domains(corners.detach(), d[r], sh[r]), u, v, d, t)  # noqa: B023
        keep = torch.nonzero(~cut).reshape(-1)  # whole targets: indices only are kept for the backward
        part = _PairSums.apply(corners, normals, cent, d[keep], t[keep], sh[keep], u, v, w, fr, vrow[keep])
        chunk = torch.zeros(d.numel(), dtype=corners.dtype).index_put((keep,), part)
        rows = torch.nonzero(cut).reshape(-1)  # clipped targets (straddling pairs): clipping differentiated in torch
        if rows.numel():
            dc, tc = d[rows], t[rows]
            target = clip_polygons(corners[tc], cent[dc], normals[dc], eps)[:, :5]
            count = torch.full((rows.numel(),), target.shape[1], dtype=torch.int64)
            part = _PolygonSums.apply(_domains(corners, dc, sh[rows]), normals[dc], target, count, u, v, w, fr,
                                      vrow[rows])
            chunk = chunk.index_put((rows,), part)
        out.append(chunk)
    return torch.cat(out) if out else torch.zeros(0, dtype=corners.dtype, device=corners.device)


def _torch_group_sums(corners, normals, cent, dom, tgt, shift, clip, rule, eps, need, vis, chunk_points) -> Tensor:
    """:func:`group_sums` in torch (any device, autograd), chunked: the reference the compiled loop follows."""
    u, v, w = rule
    out = []
    per = max(1, chunk_points // (u.numel() * 5))
    for s in range(0, dom.numel(), per):
        d, t, sh = dom[s : s + per], tgt[s : s + per], shift[s : s + per]
        target = corners[t]
        if bool(clip[s : s + per].any()):
            target = clip_polygons(target, cent[d], normals[d], eps)[:, :5]
        x, jac = bilinear(_domains(corners, d, sh), u, v)
        f = point_polygon_factor(x, normals[d], target)
        if need is not None and vis is not None:
            nd = need[s : s + per]
            if bool(nd.any()):
                frac = torch.ones_like(f)
                rows = torch.nonzero(nd).reshape(-1)
                frac[rows] = vis(x[rows].detach(), d[rows], t[rows]).to(f)
                f = f * frac
        out.append((f * jac * w).sum(1))
    return torch.cat(out) if out else torch.zeros(0, dtype=corners.dtype, device=corners.device)


def fan_sums(
    poly: Tensor,
    target: Tensor,
    normal: Tensor,
    rules: tuple[tuple[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]],
    dom: Tensor,
    tgt: Tensor,
    need: Tensor | None = None,
    vis: Visibility | None = None,
    backend: Backend = "auto",
) -> Tensor:
    """Quadrature over clipped domains split into the fan triangles ``(0, k, k+1)``, ``k = 1..3``.

    Args:
        poly: The clipped domain, its edge on the target's plane first. Shape ``[P, 5, 3]``.
        target: The (clipped) target polygon, padded by repeating a corner. Shape ``[P, K, 3]``.
        normal: The domain's unit normal. Shape ``[P, 3]``.
        rules: ``(edge rule, vertex rule)``: the first fan triangle gets the edge-graded rule, the others the
            vertex-graded one.
        dom, tgt: Facet indices of each pair (for ``vis``). Shape ``[P]``.
        need, vis, backend: As in :func:`group_sums`.

    Returns:
        ``Σ_k Σ_q F(x_q → target) |J_q| w_q vis_q`` in m². Shape ``[P]``.
    """
    adjoint = _adjoint_wanted(backend, poly, target, normal)
    fused = adjoint or resolve_backend(backend, poly, target, normal)
    total = torch.zeros(poly.shape[0], dtype=poly.dtype, device=poly.device)
    for k in range(1, 4):
        u, v, w = rules[0] if k == 1 else rules[1]
        tri = torch.stack([poly[:, 0], poly[:, k], poly[:, k + 1], poly[:, k + 1]], dim=1)
        if adjoint:
            fr, vrow = _visible_rows(need, vis, lambda r: tri[r].detach(), u, v, dom, tgt)  # noqa: B023
            count = torch.full((poly.shape[0],), target.shape[1], dtype=torch.int64)
            total = total + _PolygonSums.apply(tri, normal, target, count, u, v, w, fr, vrow)
            continue
        if fused:
            kern = loops()
            fr, vrow = _visible_rows(need, vis, lambda r: tri[r], u, v, dom, tgt)  # noqa: B023
            out = torch.empty(poly.shape[0], dtype=torch.float64)
            count = torch.full((poly.shape[0],), target.shape[1], dtype=torch.int64)
            launch(kern.polygon_sums, _np(tri), _np(normal), _np(target), _np(count), _np(u), _np(v), _np(w), _np(fr),
                 _np(vrow), out.numpy())
            total += out
            continue
        x, jac = bilinear(tri, u, v)
        f = point_polygon_factor(x, normal, target)
        if need is not None and vis is not None and bool(need.any()):
            frac = torch.ones_like(f)
            rows = torch.nonzero(need).reshape(-1)
            frac[rows] = vis(x[rows].detach(), dom[rows], tgt[rows]).to(f)
            f = f * frac
        total = total + (f * jac * w).sum(1)
    return total
