"""Contacts between the facets of a pair for the moments' outer rules (internal; see :mod:`.moments`): which edge or
corner of the domain touches the target where the shared corners do not show it (leaves of unequal refinement,
T-junctions, plates cut at other places than their neighbours), and the table of quadrature rules the compiled loops
take, with the edge rule cut at the ends of a partly shared edge."""

from __future__ import annotations

import itertools

import numpy as np
import torch
from torch import Tensor

from ..geometry.scene import Scene
from .compiled import loops
from .rules import quadrature_rule

__all__ = ["CUT_MIN", "RuleTable", "contacts", "on_boundary", "shared_segments"]

#: A shared segment's end closer than this (a fraction of the edge) to the edge's own end is taken at that end
#: (the edge rule is graded toward both ends of the edge).
CUT_MIN = 1e-6


class RuleTable:
    """Concatenated quadrature rules on the unit square, one id per (kind, order, cut)."""

    def __init__(self) -> None:
        self.ids: dict[tuple[str, int, tuple[float, ...]], int] = {}
        self.u: list[Tensor] = []
        self.v: list[Tensor] = []
        self.w: list[Tensor] = []
        self.off = [0]

    def id(self, kind: str, n: int, cut: tuple[float, ...] = ()) -> int:
        """The rule's id; ``cut``: points along ``u`` where the rule is cut, each part taking the whole rule (the
        edge rule graded toward the ends of a shared segment, :func:`contacts`)."""
        key = (kind, int(n), cut)
        if key not in self.ids:
            if cut:
                ends = (0.0, *cut, 1.0)
                # every part the whole rule (measured on the box cut to 0.4 m at tol 1e-4: parts with points along
                # the edge in proportion to their length left 5-11× the rows' error)
                parts = [(a, b, quadrature_rule(kind, int(n), torch.float64, torch.device("cpu")))
                         for a, b in itertools.pairwise(ends)]
                u = torch.cat([a + (b - a) * r[0] for a, b, r in parts])
                v = torch.cat([r[1] for _, _, r in parts])
                w = torch.cat([(b - a) * r[2] for a, b, r in parts])
            else:
                u, v, w = quadrature_rule(kind, int(n), torch.float64, torch.device("cpu"))
            self.ids[key] = len(self.off) - 1
            self.u.append(u)
            self.v.append(v)
            self.w.append(w)
            self.off.append(self.off[-1] + u.numel())
        return self.ids[key]

    def arrays(self) -> tuple[np.ndarray, ...]:
        return (np.asarray(self.off, dtype=np.int64), torch.cat(self.u).numpy(), torch.cat(self.v).numpy(),
                torch.cat(self.w).numpy())


def on_boundary(points: Tensor, poly: Tensor, tol: Tensor) -> Tensor:
    """Whether each of ``points [P, 4, 3]`` lies on an edge of ``poly [P, 4, 3]`` (within ``tol [P]``): ``[P, 4]``."""
    a = poly[:, None, :, :]  # [P, 1, 4, 3] edge starts
    b = torch.roll(poly, -1, 1)[:, None, :, :]
    x = points[:, :, None, :]  # [P, 4, 1, 3]
    d = b - a
    t = ((x - a) * d).sum(-1) / (d * d).sum(-1).clamp_min(1e-300)
    foot = a + t.clamp(0, 1)[..., None] * d
    return ((x - foot).norm(dim=-1) <= tol[:, None, None]).any(-1)


def shared_segments(cd: Tensor, ct: Tensor, tol: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Where edges of ``cd [P, 4, 3]`` share a segment longer than ``tol [P]`` (m) with an edge of ``ct [P, 4, 3]``
    (collinear within ``tol``): ``(over [P, 4], s0 [P, 4], s1 [P, 4])``, edge ``k`` from corner ``k`` to ``k + 1``,
    the shared segment from ``s0`` to ``s1`` along it (0 to 1: the whole edge)."""
    a, b = cd[:, :, None, :], torch.roll(cd, -1, 1)[:, :, None, :]  # [P, 4, 1, 3]
    c, e = ct[:, None, :, :], torch.roll(ct, -1, 1)[:, None, :, :]  # [P, 1, 4, 3]
    d = b - a
    L2 = (d * d).sum(-1)
    tc = ((c - a) * d).sum(-1) / L2.clamp_min(1e-300)  # the other edge's ends along this one (0 to 1 on it)
    te = ((e - a) * d).sum(-1) / L2.clamp_min(1e-300)
    t = tol[:, None, None]
    on_line = ((c - a - tc[..., None] * d).norm(dim=-1) <= t) & ((e - a - te[..., None] * d).norm(dim=-1) <= t)
    s0, s1 = torch.minimum(tc, te).clamp_min(0.0), torch.maximum(tc, te).clamp_max(1.0)
    ok = on_line & (t * t < L2) & ((s1 - s0) * L2.sqrt() > t)
    m = torch.argmax(ok.to(torch.int8), 2, keepdim=True)  # the (one) edge of ct along each edge of cd
    return ok.any(2), s0.gather(2, m)[..., 0], s1.gather(2, m)[..., 0]


def contacts(sc: Scene, dom: Tensor, tgt: Tensor, touch_edge: Tensor, touch_vertex: Tensor, shift: Tensor,
              near: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Contacts that the shared corners do not show (leaves of unequal refinement, a T-junction): an edge of the
    domain sharing a segment with an edge of the target (graded toward it; of the two, the shorter edge is the
    domain's, turning the pair around if need be), or else only a corner lying on the other's boundary (graded
    toward it; a pair touched only from the target's side is turned around). Pairs that share a corner are left as
    they are (:func:`~.pairs.corner_edge_contacts`). Returns ``(dom, tgt, touch_edge, touch_vertex, shift, swapped,
    cut)``.

    Measured on the Cornell box split at its contacts and cut to 0.4 m (65 pieces; 26 pairs share part of an edge,
    12 of them without a shared corner, which this grades, and 14 from a shared corner; before, all were graded
    toward a corner or not at all): the rows of the moments' form factors moved by up to 0.17 % between quadrature
    tol 1e-10 and 1e-12 before (one form factor by 0.3 %), by 4e-9 now."""
    idx = torch.nonzero(near & ~touch_edge & ~touch_vertex).reshape(-1)
    swapped = torch.zeros(dom.numel(), dtype=torch.bool)
    cut = torch.tensor([0.0, 1.0], dtype=torch.float64).expand(dom.numel(), 2).clone()
    if idx.numel() == 0:
        return dom, tgt, touch_edge, touch_vertex, shift, swapped, cut
    kern = loops("contacts") if sc.corners.dtype == torch.float64 and sc.corners.device.type == "cpu" else None
    if kern is not None:  # the same per pair in a compiled loop (on the 50-piece Cornell box 0.05 ms, not 1.7 ms)
        out = [t.clone().contiguous() for t in (dom, tgt, touch_edge, touch_vertex, shift)]
        kern.contacts(sc.corners.detach().contiguous().numpy(), sc.diameters.detach().contiguous().numpy(),
                      idx.numpy(), *(t.numpy() for t in out), swapped.numpy(), cut.numpy())
        return (*out, swapped, cut)
    cd, ct = sc.corners[dom[idx]], sc.corners[tgt[idx]]
    tol = 1e-7 * torch.maximum(sc.diameters[dom[idx]], sc.diameters[tgt[idx]])
    on_d = on_boundary(cd, ct, tol)  # domain corners on the target's boundary
    on_t = on_boundary(ct, cd, tol)
    some = on_d.any(1) | on_t.any(1)  # a shared segment ends at a corner of one of the two
    if not bool(some.any()):
        return dom, tgt, touch_edge, touch_vertex, shift, swapped, cut
    idx, cd, ct, tol, on_d, on_t = idx[some], cd[some], ct[some], tol[some], on_d[some], on_t[some]
    dom, tgt, touch_edge, touch_vertex, shift = dom.clone(), tgt.clone(), touch_edge.clone(), touch_vertex.clone(), \
        shift.clone()
    (over_d, s0_d, s1_d), (over_t, s0_t, s1_t) = shared_segments(cd, ct, tol), shared_segments(ct, cd, tol)
    e = over_d.any(1)
    len_d = (torch.roll(cd, -1, 1) - cd).norm(dim=-1)
    len_t = (torch.roll(ct, -1, 1) - ct).norm(dim=-1)
    short_d = torch.where(over_d, len_d, torch.inf).min(1)
    short_t = torch.where(over_t, len_t, torch.inf).min(1)
    swap_e = e & (short_t.values < short_d.values * (1 - 1e-9))
    k_e = torch.where(swap_e, short_t.indices, short_d.indices)
    hit = idx[swap_e]
    dom[hit], tgt[hit] = tgt[hit], dom[hit].clone()
    swapped[hit] = True
    touch_edge[idx[e]] = True
    shift[idx[e]] = k_e[e]
    pick = lambda x: x.gather(1, k_e[:, None])[:, 0]  # noqa: E731
    cut[idx[e]] = torch.stack([torch.where(swap_e, pick(s0_t), pick(s0_d)),
                               torch.where(swap_e, pick(s1_t), pick(s1_d))], 1)[e]
    for on, swap in ((on_d, False), (on_t, True)):
        v = on.any(1) & ~e & ~touch_vertex[idx]  # (after the first pass: the pairs it made corner contacts)
        hit = idx[v]
        if swap:
            dom[hit], tgt[hit] = tgt[hit], dom[hit].clone()
            swapped[hit] = True
        touch_vertex[hit] = True
        shift[hit] = torch.argmax(on.to(torch.int8), 1)[v]
    return dom, tgt, touch_edge, touch_vertex, shift, swapped, cut
