"""Visibility between facets: which pairs a third facet could block, and kernel-weighted visible fractions
from quadrature points by Embree rays.

**Gradients.** Visibility is computed on detached geometry: the visible fraction of a pair at a quadrature point
is a constant of the geometry for autograd. Form factors of occluded pairs, ``∫ f(x) vis(x) dA_x``, then carry the
*interior* part of the derivative (the unoccluded point-to-polygon factor ``f`` and the domain's Jacobian move with
the corners; ``vis`` does not), and miss the *boundary* term: how the visible fraction changes as silhouette
edges (of blockers, or of the pair itself seen past a blocker) move. A blocker's corners get no gradient at all
through ``F``. ``tests/formfactors/test_geometry_grad.py`` measures the bias on a moving blocker and on a W fold.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from torch import Tensor

from ..geometry._polygon import facet_samples, plane_groups
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene

__all__ = ["PointVisibility", "blocker_candidates"]


def blocker_candidates(sc: Scene, dom: Tensor, tgt: Tensor, eps: float) -> Tensor:
    """Pairs that some third facet could block. Conservative tests per plane group (coplanar facets), so the
    cost is pairs × planes: the group's plane strictly separates corners of the pair, its bounding box overlaps
    the pair's, and its bounding sphere comes within reach of the pair's convex hull (which lies inside the
    capsule around the segment between the two centroids, of radius the larger facet radius)."""
    sc = _detached(sc)
    corners, cent = sc.corners, sc.centroids
    need = torch.zeros(dom.numel(), dtype=torch.bool)
    groups = plane_groups(sc, eps)
    if groups is None:
        return need
    pn, po, plo, phi = groups
    n_planes = int(pn.shape[0])
    lo = corners.min(1).values
    hi = corners.max(1).values
    g_centre, g_radius = 0.5 * (plo + phi), 0.5 * (phi - plo).norm(dim=-1)
    radius = (corners - cent[:, None, :]).norm(dim=-1).max(dim=1).values
    chunk = max(1, (1 << 22) // (8 * n_planes))
    for s in range(0, dom.numel(), chunk):
        a, b = dom[s : s + chunk], tgt[s : s + chunk]
        pts = torch.cat([corners[a], corners[b]], dim=1)  # [c, 8, 3]
        d = torch.einsum("cpx,nx->cnp", pts, pn) - po[None, :, None]  # [c, planes, 8]
        straddle = (d > eps).any(-1) & (d < -eps).any(-1)
        blo = torch.minimum(lo[a], lo[b])
        bhi = torch.maximum(hi[a], hi[b])
        overlap = ((plo[None] < bhi[:, None] - eps) & (phi[None] > blo[:, None] + eps)).all(-1)
        ca, seg = cent[a], cent[b] - cent[a]
        t = ((g_centre[None] - ca[:, None]) * seg[:, None]).sum(-1) / (seg * seg).sum(-1).clamp_min(1e-300)[:, None]
        closest = ca[:, None] + t.clamp(0, 1)[..., None] * seg[:, None]
        reach = (g_centre[None] - closest).norm(dim=-1) <= (
            torch.maximum(radius[a], radius[b])[:, None] + g_radius[None] + eps
        )
        need[s : s + chunk] = (straddle & overlap & reach).any(-1)
    return need


def _detached(sc: Scene) -> Scene:
    """The scene without autograd history (visibility is a constant of the geometry)."""
    if not sc.corners.requires_grad:
        return sc
    return Scene.from_parts(sc.corners.detach(), sc.is_triangle, sc.material, sc.material_names)


class PointVisibility:
    """Kernel-weighted visible fraction of a target facet from quadrature points, by Embree rays.

    From each point ``x`` rays go to ``n × n`` midpoint-rule points ``y`` of the target; each is weighted by
    ``cos θ_x cos θ_y / |x − y|²`` times ``y``'s area, so the fraction converges to the visibility-weighted
    point-to-polygon factor over the plain one as ``n`` grows. Computed on detached geometry: the result carries
    no gradient (module docstring).
    """

    def __init__(self, sc: Scene, n: int, caster: Any = None) -> None:
        sc = _detached(sc)
        self.caster = caster if caster is not None else RayCaster(sc)
        pts, wts = facet_samples(sc.corners, n)  # [F, S, 3], [F, S]
        self.origin = torch.as_tensor(self.caster.origin)
        self.pts = (pts - self.origin).float()
        self.wts = wts.float()
        self.normals = sc.normals.float()
        self.rays = 0
        self.seconds = 0.0

    @torch.no_grad()
    def __call__(self, x: Tensor, dom: Tensor, tgt: Tensor) -> Tensor:
        """Visible fractions ``[P, Q]`` (float64, no gradient) from points ``x [P, Q, 3]`` of facets ``dom [P]``
        to facets ``tgt [P]``."""
        t0 = time.perf_counter()
        x = x.detach()
        P, Q, _ = x.shape
        S = self.pts.shape[1]
        out = torch.empty(P, Q, dtype=torch.float64)
        xs = (x - self.origin).float()
        per = max(1, (1 << 19) // (Q * S))
        for s in range(0, P, per):
            a, b = dom[s : s + per], tgt[s : s + per]
            xa = xs[s : s + per][:, :, None, :]  # [c, Q, 1, 3]
            r = self.pts[b][:, None, :, :] - xa  # [c, Q, S, 3]
            d2 = (r * r).sum(-1).clamp_min(1e-30)
            length = d2.sqrt()
            cos_a = (r * self.normals[a][:, None, None, :]).sum(-1).clamp_min(0)
            cos_b = (-(r * self.normals[b][:, None, None, :]).sum(-1)).clamp_min(0)
            k = cos_a * cos_b / (d2 * d2) * self.wts[b][:, None, :]
            direction = r / length[..., None]
            origin = xa + self.caster.eps * direction
            blocked = torch.from_numpy(
                self.caster.occluded(origin.reshape(-1, 3).numpy(), direction.reshape(-1, 3).numpy(),
                                     (length - 2 * self.caster.eps).reshape(-1).numpy())
            ).reshape(k.shape)
            num = (k * (~blocked)).sum(-1)
            den = k.sum(-1)
            out[s : s + per] = torch.where(den > 0, num / den.clamp_min(1e-30), torch.ones_like(den)).double()
            self.rays += int(blocked.numel())
        self.seconds += time.perf_counter() - t0
        return out
