"""Edge sampling in the image: where facets' edges and a sun's shadow edges are seen, and what lies either side.

The boundary terms of :mod:`.image_grad`. A segment in 3-D (a mesh edge, or a shadow edge on a facet) is clipped to
the camera's front, projected, clipped to the image, split where it crosses pixel borders (so that every piece lies
in one pixel) and sampled at midpoints; two primary rays just either side of each sample (``_SIDE`` pixels away)
tell whether it is seen and what each side shows. Each sample carries ``Δl (v − v.detach())``: its length in pixels
times its speed along the image normal, zero in value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..geometry._polygon import clip_interval, pieces_between, plane_eps, ray_plane_points
from ..geometry.edges import edge_pieces
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from ..geometry.shadows import shadow_segments
from .gather import Gather

__all__ = ["edge_samples", "shadow_samples"]

#: Offset of the two side rays of an edge sample from the edge, in pixels.
_SIDE = 1e-2


def _project(view: Any, points: Tensor) -> Tensor:
    """Pixel coordinates ``[N, 2]`` (column, row) of points ``[N, 3]`` in front of the camera (differentiable)."""
    pin = view.pinhole(points.dtype)
    P = (pin.intrinsics[0] @ pin.extrinsics[0]).to(points.device)
    hom = points @ P[:3, :3].T + P[:3, 3]
    return hom[:, :2] / hom[:, 2:3]


def _depth(view: Any, points: Tensor) -> Tensor:
    """Depths ``[N]`` (metres along the optical axis) of points ``[N, 3]`` (differentiable)."""
    P = view.pinhole(points.dtype).extrinsics[0].to(points.device)
    return points @ P[2, :3] + P[2, 3]


def _screen_clip(ua: Tensor, ub: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """The part ``[s0, s1]`` of each segment ``ua + s (ub − ua)`` inside the image ``[−½, W − ½] × [−½, H − ½]``."""
    lo, hi = torch.zeros_like(ua[:, 0]), torch.ones_like(ua[:, 0])
    d = ub - ua
    for axis, size in ((0, width), (1, height)):
        lo, hi = clip_interval(lo, hi, ua[:, axis] + 0.5, d[:, axis])
        lo, hi = clip_interval(lo, hi, size - 0.5 - ua[:, axis], -d[:, axis])
    return lo, hi


def _pixel_pieces(ua: Tensor, ub: Tensor, s0: Tensor, s1: Tensor, ok: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Split each kept segment's part ``[s0, s1]`` where it crosses a pixel border (``u`` or ``v`` = ``k + ½``):
    ``(edge [N], s_a [N], s_b [N])``, pieces of positive length, each inside one pixel."""
    idx = torch.nonzero(ok).reshape(-1)
    pa, pb = ua[idx] + s0[idx, None] * (ub - ua)[idx], ua[idx] + s1[idx, None] * (ub - ua)[idx]
    lo = torch.ceil(torch.minimum(pa, pb) - 0.5)
    count = (torch.floor(torch.maximum(pa, pb) - 0.5) - lo + 1).clamp_min(0).long()  # [E, 2] border lines
    edges, params = [idx, idx], [s0[idx], s1[idx]]
    for axis in (0, 1):
        c = count[:, axis]
        e = torch.repeat_interleave(torch.arange(idx.numel()), c)
        k = torch.arange(e.numel()) - torch.repeat_interleave(torch.cumsum(c, 0) - c, c)
        line = lo[e, axis] + k.double() + 0.5
        d = (ub - ua)[idx[e], axis]
        edges.append(idx[e])
        params.append((line - ua[idx[e], axis]) / torch.where(d != 0, d, torch.ones_like(d)))
    return pieces_between(torch.cat(edges), torch.cat(params))


def _side_hits(op: Gather, caster: RayCaster, q: Tensor, sc: Scene) -> tuple[Tensor, Tensor, Tensor]:
    """Through image points ``q [N, 2]`` (pixels): the facet hit (``-1`` for none), whether its front was hit, and
    the hit points ``[N, 3]`` (metres; meaningless where there is no hit)."""
    pin = op.view.pinhole()
    pts = pin.unproject(q[None], torch.ones(1, q.shape[0], 1, dtype=torch.float64))[0]
    eye = torch.tensor(op.view.eye, dtype=torch.float64)
    d = pts - eye
    hit = torch.from_numpy(caster.first_hit(np.broadcast_to(eye.numpy(), d.shape), d.numpy())).long()
    h = hit.clamp_min(0)
    n = sc.normals[h]
    return hit, (hit >= 0) & ((n * d).sum(-1) < 0), ray_plane_points(eye, d, sc.centroids[h], n)


def _fragment_at(op: Gather, pixel: Tensor, facet: Tensor) -> Tensor:
    """The fragment of (pixel, facet), ``-1`` where there is none (fragments are sorted by pixel, then facet)."""
    F = op.num_facets
    keys = op.fragment_pixel.cpu() * F + op.fragment_facet.cpu()
    key = pixel * F + facet
    at = torch.searchsorted(keys, key).clamp_max(max(keys.numel() - 1, 0))
    found = (facet >= 0) & (keys.numel() > 0) & (keys[at] == key)
    return torch.where(found, at, torch.full_like(at, -1))


def _pixel_of(q: Tensor, height: int, width: int) -> Tensor:
    col = torch.round(q[:, 0]).long().clamp(0, width - 1)
    row = torch.round(q[:, 1]).long().clamp(0, height - 1)
    return row * width + col


@dataclass
class _Samples:
    """Samples of projected 3-D segments: the segment, its screen points, their pixel, unit screen normals, and the
    zero-valued ``Δl (v − v.detach())`` (length times normal speed in the image, pixels²)."""

    segment: Tensor
    q: Tensor
    pixel: Tensor
    normal: Tensor
    weight: Tensor

    def select(self, keep: Tensor) -> _Samples:
        return _Samples(self.segment[keep], self.q[keep], self.pixel[keep], self.normal[keep],
                        self.weight[keep.to(self.weight.device)])


def _screen_samples(op: Gather, a: Tensor, b: Tensor, spacing: float) -> _Samples:
    """Clip segments ``a → b`` (``[N, 3]``, differentiable) to the part in front of the camera (depth above 10⁻³ of
    the view's eye–target distance), project them, clip them to the image, split them at pixel borders and sample
    every piece at ``ceil(length / spacing)`` midpoints."""
    near = 1e-3 * math.dist(op.view.eye, op.view.target)
    za, zb = _depth(op.view, a), _depth(op.view, b)
    front = ((za >= near) | (zb >= near)).detach().cpu()
    # an end behind the near plane moves to where the segment crosses it (on the same line: same image line)
    cut_a, cut_b = (za < near) & (zb >= near), (zb < near) & (za >= near)
    ta = torch.where(cut_a, (near - za) / torch.where(cut_a, zb - za, torch.ones_like(za)), torch.zeros_like(za))
    tb = torch.where(cut_b, (near - zb) / torch.where(cut_b, za - zb, torch.ones_like(zb)), torch.zeros_like(zb))
    a, b = a + ta[:, None] * (b - a), b + tb[:, None] * (a - b)
    # segments wholly behind are dropped: project a point in front instead (no 0/0 in the backward)
    keep = front.to(a.device)[:, None]
    target = torch.tensor(op.view.target, dtype=a.dtype, device=a.device)
    a, b = torch.where(keep, a, target), torch.where(keep, b, target + 1.0)
    ua, ub = _project(op.view, a), _project(op.view, b)
    H, W = op.height, op.width
    uad, ubd = ua.detach().double().cpu(), ub.detach().double().cpu()
    s0, s1 = _screen_clip(uad, ubd, H, W)
    length = (ubd - uad).norm(dim=-1)
    ok = front & (s1 > s0) & (length > 0) & torch.isfinite(length)
    piece_edge, pa, pb = _pixel_pieces(uad, ubd, s0, s1, ok)
    n = torch.ceil(length[piece_edge] * (pb - pa) / spacing).clamp_min(1).long()
    piece = torch.repeat_interleave(torch.arange(n.numel()), n)
    k = torch.arange(piece.numel()) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
    edge = piece_edge[piece]
    s = pa[piece] + (k.double() + 0.5) * (pb - pa)[piece] / n[piece]
    dl = length[edge] * (pb - pa)[piece] / n[piece]
    mid = (pa + pb)[piece] / 2  # the piece's pixel: its middle's (a piece never crosses a pixel border)
    tang = (ubd - uad)[edge] / length[edge, None]
    normal = torch.stack([-tang[:, 1], tang[:, 0]], -1)
    q = uad[edge] + s[:, None] * (ubd - uad)[edge]
    dev, dt = a.device, a.dtype
    sd, nd, ed = s.to(device=dev, dtype=dt), normal.to(device=dev, dtype=dt), edge.to(dev)
    v = (((1 - sd)[:, None] * ua[ed] + sd[:, None] * ub[ed]) * nd).sum(-1)
    pixel = _pixel_of(uad[edge] + mid[:, None] * (ubd - uad)[edge], H, W)
    return _Samples(edge, q, pixel, normal, dl.to(device=dev, dtype=dt) * (v - v.detach()))


def edge_samples(op: Gather, scene: Scene, caster: RayCaster, spacing: float) -> tuple[Tensor, ...]:
    """Samples of the mesh edges seen in the image: the pieces of
    :func:`~torch_interreflect.geometry.edges.edge_pieces` (edges cut where another facet's corner lies on them, so
    a T-junction's border is listed once), where a side ray hits one of the piece's facets.

    Args:
        op: The view's :class:`~torch_interreflect.camera.Gather`. scene: Its scene (corners may require grad).
        caster: A :class:`~torch_interreflect.geometry.raycast.RayCaster` of the scene. spacing: Pixels between
            samples along a piece.

    Returns:
        ``(pixel [S], weight [S], side_fragment [2, S], side_facet [2, S])``: the pixel of each sample, its
        zero-valued ``Δl (v − v.detach())`` (pixels²), and per side (row 0: ``a``, against the image normal; row
        1: ``b``) the fragment of that pixel and facet (``-1``: none) and the facet seen from its front (``-1``:
        background or a back).
    """
    sc = scene.detach().to(torch.float64).to("cpu")
    e = edge_pieces(sc, plane_eps(scene))
    dev, dt = scene.device, scene.dtype
    c0 = scene.corners[e.facet.to(dev), e.corner.to(dev)]
    c1 = scene.corners[e.facet.to(dev), ((e.corner + 1) % 4).to(dev)]
    t0, t1 = e.t0.to(device=dev, dtype=dt)[:, None], e.t1.to(device=dev, dtype=dt)[:, None]
    smp = _screen_samples(op, c0 + t0 * (c1 - c0), c0 + t1 * (c1 - c0), spacing)
    sides = [_side_hits(op, caster, smp.q + sign * _SIDE * smp.normal, sc) for sign in (-1.0, 1.0)]
    own = e.facets[smp.segment]  # [S, M]: every facet that has the piece
    seen = ((sides[0][0][:, None] == own) | (sides[1][0][:, None] == own)).any(1)
    keep = torch.nonzero(seen).reshape(-1)
    smp = smp.select(keep)
    # the value on a side: a facet's front, or 0 (the background, a facet's back)
    side_facet = torch.stack([torch.where(front, hit, torch.full_like(hit, -1))[keep] for hit, front, _ in sides])
    side_fragment = []
    for sign, facet in ((-1.0, side_facet[0]), (1.0, side_facet[1])):
        frag = _fragment_at(op, _pixel_of(smp.q + sign * _SIDE * smp.normal, op.height, op.width), facet)
        deeper = _fragment_at(op, _pixel_of(smp.q + sign * 0.5 * smp.normal, op.height, op.width), facet)
        side_fragment.append(torch.where(frag >= 0, frag, deeper))
    return smp.pixel, smp.weight, torch.stack(side_fragment), side_facet


def shadow_samples(op: Gather, scene: Scene, direction: Tensor, caster: RayCaster,
                   spacing: float) -> tuple[Tensor, Tensor, Tensor]:
    """Samples of a sun's shadow edges seen in the image: the parts of mesh edges that the sun projects onto the
    seen, lit facets (:func:`~torch_interreflect.geometry.shadows.shadow_segments`), kept where both side rays land
    on the receiving facet and exactly one of their hit points sees the sun.

    Args:
        op, scene, caster, spacing: As for :func:`edge_samples`. direction: The way the light travels ``[3]`` (may
            require grad).

    Returns:
        ``(pixel [S], weight [S], facet [S])``: the weight is ``Δl (v − v.detach())`` times the receiving facet's
        cosine and the lit change ``lit_a − lit_b`` across the edge; ``facet`` the receiving facet.
    """
    sc = scene.detach().to(torch.float64).to("cpu")
    dev, dt = scene.device, scene.dtype
    d_g = direction.to(device=dev, dtype=dt).reshape(3)
    d_g = d_g / d_g.norm()
    d = d_g.detach().double().cpu()
    seen = torch.unique(op.fragment_facet.cpu())
    facets = seen[(sc.normals[seen] @ d) < 0]
    parts = shadow_segments(sc, d, facets, plane_eps(sc))
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    if parts.facet.numel() == 0:
        return empty, torch.zeros(0, dtype=dt, device=dev), empty
    ef, ec, f = parts.edge_facet.to(dev), parts.edge_corner.to(dev), parts.facet.to(dev)
    g0, g1 = scene.corners[ef, ec], scene.corners[ef, (ec + 1) % 4]
    n, o = scene.normals[f], scene.corners[f, 0]

    def on_facet(s: Tensor) -> Tensor:  # the edge point's shadow on the facet's plane, along the light
        p = g0 + s.to(device=dev, dtype=dt)[:, None] * (g1 - g0)
        return p - (((p - o) * n).sum(-1) / (n * d_g).sum(-1))[:, None] * d_g

    smp = _screen_samples(op, on_facet(parts.s_a), on_facet(parts.s_b), spacing)
    rec = parts.facet[smp.segment]
    lit = []
    for sign in (-1.0, 1.0):
        hit, front, x = _side_hits(op, caster, smp.q + sign * _SIDE * smp.normal, sc)
        on = front & (hit == rec)
        origin = x + caster.eps * sc.normals[rec]
        free = torch.from_numpy(caster.first_hit(origin.numpy(), (-d).expand(origin.shape[0], 3).numpy()) < 0)
        lit.append(torch.where(on, free.double(), torch.full_like(free, float("nan"), dtype=torch.float64)))
    change = lit[0] - lit[1]  # NaN where a side is not on the receiving facet
    keep = torch.nonzero(torch.isfinite(change) & (change != 0)).reshape(-1)
    smp, rec, change = smp.select(keep), rec[keep], change[keep]
    cos = -(sc.normals[rec] @ d)
    return smp.pixel, smp.weight * (cos * change).to(device=dev, dtype=dt), rec.to(dev)
