"""Visibility between facets: which pairs a third facet could block, and kernel-weighted visible fractions
from quadrature points by Embree rays.

**Gradients.** Visibility is computed on detached geometry: the visible fraction of a pair at a quadrature point
is a constant of the geometry for autograd, so autograd through the quadrature gives ``∂f · vis`` (the unoccluded
point-to-polygon factor ``f`` and the domain's Jacobian move with the corners; ``vis`` does not). What that misses,
the shadow edges moving (the boundary term) and the interior term's spread over the visible part, is added by
:mod:`.visibility_grad` when the corners require grad (``form_factors(visibility_grad_points=)``).
``tests/formfactors/test_geometry_grad.py`` measures both on a moving blocker and a W fold.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .._checks import check_count
from ..errors import ValueRangeError
from ..geometry._polygon import bilinear, clip_polygons, facet_samples, plane_groups
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from .compiled import launch, loops
from .contour import point_polygon_factor
from .sampling import R2_STEP, pair_seeds

__all__ = ["VISIBILITY_ANGLE", "PointVisibility", "blocker_candidates", "check_visibility_options", "grid_offsets"]

#: Default angular size (radians) per visibility sample of a target (:class:`PointVisibility`'s ``angle``).
VISIBILITY_ANGLE = 0.3


def blocker_candidates(sc: Scene, dom: Tensor, tgt: Tensor, eps: float) -> Tensor:
    """Pairs that some third facet could block. Conservative tests per plane group (coplanar facets), so the
    cost is pairs × planes: the group's plane strictly separates corners of the pair, its bounding box overlaps
    the pair's, its bounding sphere comes within reach of the pair's convex hull (which lies inside the capsule
    around the segment between the two centroids, of radius the larger facet radius), and its box and its
    rectangle in the plane's own axes meet those of the hull's part within the group's thickness of the plane,
    where every ray between the two facets meets the group (on the 4,624-facet Cornell box these last tests leave
    1.26 M of 2.40 M pairs and 43 % fewer rays, with the same form factors). A compiled loop over pairs on the CPU
    (:mod:`._numba_pairs`), torch elsewhere (the reference; several times slower than before these tests)."""
    sc = _detached(sc)
    corners, cent = sc.corners, sc.centroids
    need = torch.zeros(dom.numel(), dtype=torch.bool)
    groups = plane_groups(sc, eps, frames=True)
    if groups is None:
        return need
    pn, po, plo, phi, e1, e2, rect, thick = groups
    n_planes = int(pn.shape[0])
    lo = corners.min(1).values
    hi = corners.max(1).values
    g_centre, g_radius = 0.5 * (plo + phi), 0.5 * (phi - plo).norm(dim=-1)
    radius = (corners - cent[:, None, :]).norm(dim=-1).max(dim=1).values
    kern = loops("pairs")
    if kern is not None and corners.device.type == "cpu":
        args = (corners, cent, lo, hi, radius, pn, po, plo, phi, e1, e2, rect, thick, g_centre, g_radius, dom, tgt)
        launch(kern.blockers, *(t.contiguous().numpy() for t in args), float(eps), need.numpy())
        return need
    chunk = max(1, (1 << 22) // (8 * n_planes))
    for s in range(0, dom.numel(), chunk):
        a, b = dom[s : s + chunk], tgt[s : s + chunk]
        pts = torch.cat([corners[a], corners[b]], dim=1)  # [c, 8, 3]
        d = torch.einsum("cpx,nx->cnp", pts, pn) - po[None, :, None]  # [c, planes, 8]
        dmin, dmax = d.amin(-1), d.amax(-1)  # [c, planes]: some member's plane separates corners of the pair
        straddle = (dmax > -thick + eps) & (dmin < thick - eps) & (dmax - dmin > 2 * eps)
        blo = torch.minimum(lo[a], lo[b])
        bhi = torch.maximum(hi[a], hi[b])
        overlap = ((plo[None] < bhi[:, None] - eps) & (phi[None] > blo[:, None] + eps)).all(-1)
        ca, seg = cent[a], cent[b] - cent[a]
        t = ((g_centre[None] - ca[:, None]) * seg[:, None]).sum(-1) / (seg * seg).sum(-1).clamp_min(1e-300)[:, None]
        closest = ca[:, None] + t.clamp(0, 1)[..., None] * seg[:, None]
        reach = (g_centre[None] - closest).norm(dim=-1) <= (
            torch.maximum(radius[a], radius[b])[:, None] + g_radius[None] + eps
        )
        cand = straddle & overlap & reach  # [c, planes]
        ci, gi = torch.nonzero(cand, as_tuple=True)
        if ci.numel():  # ... and where the rays cross the plane
            cand[ci, gi] = _section_meets_box(pts[ci], d[ci, gi], thick[gi] + eps, eps, (plo[gi], phi[gi]),
                                              (e1[gi], e2[gi], rect[gi]))
        need[s : s + chunk] = cand.any(-1)
    return need


def _section_meets_box(pts: Tensor, d: Tensor, half: Tensor, eps: float, box: tuple[Tensor, Tensor],
                       frame: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """Whether the part of a pair's convex hull within ``half [M]`` of a plane can meet the plane's group of facets
    (all within ``half`` of it), per entry: the bounding box of that part (the hull of the corners inside the slab
    and of the crossings of the segments between corners with its two faces; corners ``pts [M, 8, 3]``, signed
    distances ``d [M, 8]``) reaches the group's box ``box = (lo, hi)``, each ``[M, 3]``, and its bounding rectangle
    in the plane's axes reaches the group's (``frame = (e1, e2, rect)``: ``[M, 3]``, ``[M, 3]``, ``[M, 4]``),
    within ``eps``. Every ray between the two facets meets a member inside that part. The crossings' coordinates
    (x, y, z, then along the axes, which are linear) are interpolated from the corners', as in the compiled loop.
    Bool ``[M]``."""
    e1, e2, rect = frame
    pos = torch.cat([pts, (pts * e1[:, None, :]).sum(-1, keepdim=True), (pts * e2[:, None, :]).sum(-1, keepdim=True)],
                    dim=-1)  # [M, 8, 5]
    glo = torch.cat([box[0], rect[:, 0::2]], dim=-1)
    ghi = torch.cat([box[1], rect[:, 1::2]], dim=-1)
    ok = torch.empty(d.shape[0], dtype=torch.bool)
    step = 1 << 13  # entries per step: the [step, 8, 8, 5] temporaries stay in cache
    for s in range(0, d.shape[0], step):
        dd, p, h = d[s : s + step], pos[s : s + step], half[s : s + step, None, None]
        di, dj = dd[:, :, None], dd[:, None, :]
        pi, pj = p[:, :, None, :], p[:, None, :, :]
        inside = (dd.abs() <= h[:, 0])[..., None]
        lo = torch.where(inside, p, math.inf).amin(1)
        hi = torch.where(inside, p, -math.inf).amax(1)
        for c in (h, -h):
            cross = (di > c) & (c > dj)  # [m, 8, 8]
            t = (di - c) / torch.where(cross, di - dj, torch.ones_like(di))
            x = pi + t[..., None] * (pj - pi)  # [m, 8, 8, 5]
            lo = torch.minimum(lo, torch.where(cross[..., None], x, math.inf).amin((1, 2)))
            hi = torch.maximum(hi, torch.where(cross[..., None], x, -math.inf).amax((1, 2)))
        ok[s : s + step] = ((glo[s : s + step] <= hi + eps) & (ghi[s : s + step] >= lo - eps)).all(-1)
    return ok


def check_visibility_options(samples: Any, tol: Any, angle: Any, jitter: Any = True) -> None:
    """Raise for visibility settings out of range: ``samples`` an integer ≥ 1, ``tol`` ``None`` or a finite number
    ≥ 0, ``angle`` ``None`` or a finite number > 0 (radians), ``jitter`` a bool."""
    check_count(samples, "visibility_samples")
    if not isinstance(jitter, bool):
        raise ValueRangeError(f"visibility_jitter must be True or False; got {jitter!r}")
    if tol is not None and not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol >= 0):
        raise ValueRangeError(f"visibility_tol must be None or a finite number >= 0; got {tol!r}")
    if angle is not None and not (isinstance(angle, (int, float)) and math.isfinite(angle) and angle > 0):
        raise ValueRangeError(f"visibility_angle must be None or a finite number > 0 (radians); got {angle!r}")


def _detached(sc: Scene) -> Scene:
    """The scene without autograd history (visibility is a constant of the geometry)."""
    if not sc.corners.requires_grad:
        return sc
    return Scene.from_parts(sc.corners.detach(), sc.is_triangle, sc.material, sc.material_names)


class PointVisibility:
    """Kernel-weighted visible fraction of a target facet from quadrature points, by Embree rays, refined
    adaptively at shadow boundaries.

    From each point ``x`` rays go to one point ``y`` in each of ``n × n`` cells of the target (jittered within the
    cell by default, the cell's midpoint with ``tol`` or ``jitter=False``); each is weighted by
    ``cos θ_x cos θ_y / |x − y|²`` times the cell's area. With ``tol``, a cell whose ray disagrees with a neighbour's (a
    shadow boundary passes near it) is split into 2 × 2 cells with a ray each, and split cells whose four rays
    disagree are split again, while the cell carries more than ``tol`` of the point's kernel weight (at most
    ``max_levels`` times). The error of the fraction is then bounded by the weight of the unsplit boundary cells,
    not by the fixed grid: it falls with ``tol`` (``tests/formfactors/test_visibility.py`` measures it on a
    penumbra against the exact fraction). Computed on detached geometry: the result carries no gradient (module
    docstring).

    Args:
        sc: The scene.
        n: Cells per direction of the first grid on the target facet.
        caster: A :class:`~torch_interreflect.geometry.raycast.RayCaster` of the scene to reuse.
        tol: Kernel-weight share (of a point's row to one target) below which a boundary cell is not split;
            ``0`` splits down to ``max_levels``; ``None`` (default) never splits (the fixed ``n × n`` grid).
        max_levels: Most splits of a first-grid cell.
        angle: With the fixed grid (``tol=None``): a target whose angular size from the domain (diameter over the
            centroids' distance, radians) is ``α`` gets ``ceil(α / angle)`` samples per direction, at most ``n``;
            ``None`` gives every target ``n``.
        jitter: With the fixed grid: each point's rays go to one point per cell at an offset of its own, different
            for every cell and quadrature point (:func:`grid_offsets`: a low-discrepancy sequence, deterministic),
            not to the cell midpoints. The points of a pair then sample the target at ``Q`` times as many places,
            and the estimate has no bias from the grid: with midpoints, a thin blocker that hides (or misses) every
            midpoint hides (or misses) the whole target from every point. In a closed box with a thin plate inside
            (rows sum to 1), the RMS of (row sum − 1) falls from 0.0040 to 0.0017
            (``tests/formfactors/test_visibility.py``); on the Cornell box see ``benchmarks/results/visibility.md``.
            A single pair can come out a little worse (its points' rays no longer share one grid whose errors may
            happen to cancel).
    """

    def __init__(self, sc: Scene, n: int, caster: Any = None, *, tol: float | None = None,
                 max_levels: int = 6, angle: float | None = None, jitter: bool = True) -> None:
        check_visibility_options(n, tol, angle, jitter)
        sc = _detached(sc)
        self.caster = caster if caster is not None else RayCaster.of(sc)
        self.n = int(n)
        self.tol = tol
        self.max_levels = int(max_levels)
        pts, wts = facet_samples(sc.corners, n)  # [F, S, 3], [F, S]
        self.origin = torch.as_tensor(self.caster.origin)
        self.corners = (sc.corners - self.origin).float()
        self.pts = (pts - self.origin).float()
        self.wts = wts.float()
        self.normals = sc.normals.float()
        self.angle = angle
        self.jitter = bool(jitter)
        self._grids: dict[int, tuple[Tensor, Tensor]] = {}
        self._tables: tuple[np.ndarray, np.ndarray] | None = None
        cent = sc.centroids
        self.centroids = cent - self.origin
        self.radius = (sc.corners - cent[:, None, :]).norm(dim=-1).max(dim=1).values
        self.rays = 0
        self.seconds = 0.0

    @torch.no_grad()
    def __call__(self, x: Tensor, dom: Tensor, tgt: Tensor) -> Tensor:
        """Visible fractions ``[P, Q]`` (float64, no gradient) from points ``x [P, Q, 3]`` of facets ``dom [P]``
        to facets ``tgt [P]``."""
        t0 = time.perf_counter()
        x = x.detach()
        out = torch.empty(x.shape[:2], dtype=torch.float64)
        xs = (x - self.origin).float()
        if self.angle is None or self.tol is not None:
            out[:] = self._fractions(xs, dom, tgt, self.n, self.pts, self.wts)
        else:
            for rows, m in self._rows_by_samples(dom, tgt):
                pts, wts = self._grid(m)
                out[rows] = self._fractions(xs[rows], dom[rows], tgt[rows], m, pts, wts)
        self.seconds += time.perf_counter() - t0
        return out

    def _rows_by_samples(self, dom: Tensor, tgt: Tensor) -> list[tuple[Tensor, int]]:
        """``(rows, m)``: the pairs whose target gets ``m × m`` samples, ``m = ceil(angular size / angle)`` (at
        most ``n``): fewer for targets that look small."""
        c = self.centroids
        alpha = 2 * self.radius[tgt] / (c[tgt] - c[dom]).norm(dim=-1).clamp_min(1e-30)
        n_row = (alpha / self.angle).ceil().clamp(1, self.n).long()
        return [(torch.nonzero(n_row == m).reshape(-1), m) for m in n_row.unique().tolist()]

    @torch.no_grad()
    def rule_fractions(self, corners: Tensor, dom: Tensor, tgt: Tensor, shift: Tensor, u: Tensor,
                       v: Tensor) -> Tensor | None:
        """What :meth:`__call__` gives for the points of the rule ``(u, v)`` on whole facets, without the points
        in memory: the compiled loop maps the rule onto ``corners[dom]`` (float64, metres, corners rotated by
        ``shift``) itself. None where the compiled loops do not apply (then call with the points).

        Shape:
            - corners: ``[F, 4, 3]``; dom, tgt, shift: ``[P]``; u, v: ``[Q]``
            - output: ``[P, Q]`` (float64)
        """
        kern = loops("visibility")
        if kern is None or self.tol is not None or corners.device.type != "cpu":
            return None
        t0 = time.perf_counter()
        if self._tables is None:  # the float32 caster-frame tables, widened once
            self._tables = (self.normals.double().numpy(), self.corners.double().numpy())
        out = torch.empty(dom.numel(), u.numel(), dtype=torch.float64)
        groups = [(torch.arange(dom.numel()), self.n)] if self.angle is None else self._rows_by_samples(dom, tgt)
        for rows, m in groups:
            out[rows] = self._rule_chunks(kern, corners, (dom[rows], tgt[rows], shift[rows]), u, v, m)
        self.seconds += time.perf_counter() - t0
        return out

    def _rule_chunks(self, kern: Any, corners: Tensor, sel: tuple[Tensor, Tensor, Tensor], u: Tensor, v: Tensor,
                     n: int) -> Tensor:
        """:meth:`_compiled_fractions` with the rays built from the rule's points by ``rule_rays``."""
        dom, tgt, shift = sel
        eps = float(self.caster.eps)
        c64 = corners.detach().to(torch.float64).contiguous().numpy()
        centre = self.origin.to(torch.float64).numpy()
        normals, rel = self._tables
        uv = [t.to(torch.float64).contiguous().numpy() for t in (u, v)]

        def cast(s: int, e: int, *buffers: np.ndarray) -> None:
            a, b, sh = (t[s:e].contiguous().numpy() for t in (dom, tgt, shift))
            launch(kern.rule_rays, c64, centre, a, b, sh, *uv, normals, rel, n, self.jitter, _MARGIN, eps, _END_GAP,
                   *buffers)

        Q, S = u.numel(), n * n
        return self._cast_chunks(kern, cast, dom.numel(), Q, S, max(1, (1 << 19) // (Q * S)))

    def _grid(self, m: int) -> tuple[Tensor, Tensor]:
        """Midpoint-rule points and weights of an ``m × m`` grid on every facet (cached)."""
        if m == self.n:
            return self.pts, self.wts
        if m not in self._grids:
            pts, wts = facet_samples(self.corners.double(), m)
            self._grids[m] = (pts.float(), wts.float())
        return self._grids[m]

    def _fractions(self, xs: Tensor, dom: Tensor, tgt: Tensor, n: int, grid_pts: Tensor, grid_wts: Tensor) -> Tensor:
        """Visible fractions ``[P, Q]`` from points ``xs`` (relative to the caster's origin) on an ``n × n`` grid:
        its cell midpoints (adaptive refinement), or one jittered point per cell (see :func:`grid_offsets`)."""
        P, Q, _ = xs.shape
        S = grid_pts.shape[1]
        out = torch.empty(P, Q, dtype=torch.float64)
        per = max(1, (1 << 19) // (Q * S))
        jitter = self.jitter and self.tol is None
        kern = loops("visibility") if self.tol is None else None
        if kern is not None:
            return self._compiled_fractions(kern, xs, dom, tgt, n, jitter, per)
        if jitter:
            j = torch.arange(S)
            iu, iv = (j // n).double(), (j % n).double()  # facet_samples: u varies slowest
        for s in range(0, P, per):
            a, b = dom[s : s + per], tgt[s : s + per]
            xa = xs[s : s + per][:, :, None, :]  # [c, Q, 1, 3]
            if jitter:
                xi = grid_offsets(a, b, Q, S)  # [c, Q, S, 2]
                c = a.numel()
                uu = ((iu + xi[..., 0]) / n).reshape(c, Q * S).float()
                vv = ((iv + xi[..., 1]) / n).reshape(c, Q * S).float()
                y, jac = bilinear(self.corners[b], uu, vv)
                y, area = y.reshape(c, Q, S, 3), jac.reshape(c, Q, S) / (n * n)
            else:
                y, area = grid_pts[b][:, None, :, :], grid_wts[b][:, None, :]
            k = self._weights(xa, self.normals[a][:, None, None, :], y, self.normals[b][:, None, None, :], area)
            seen = ~self._blocked(xa, y)  # [c, Q, S]
            num = (k * seen).sum(-1).double()
            den = k.sum(-1).double()
            if self.tol is not None and self.max_levels > 0:
                self._refine(xa, a, b, k, seen, num, den)
            out[s : s + per] = torch.where(den > 0, num / den.clamp_min(1e-300), torch.ones_like(den))
        return out

    def _compiled_fractions(self, kern: Any, xs: Tensor, dom: Tensor, tgt: Tensor, n: int, jitter: bool,
                            per: int) -> Tensor:
        """:meth:`_fractions` of the fixed grid through the compiled loops (:mod:`._numba_visibility`): rays and
        weights in one pass, Embree, then the weighted fractions; no ``[c, Q, S, 3]`` temporaries in torch."""
        eps = float(self.caster.eps)

        def cast(s: int, e: int, *buffers: np.ndarray) -> None:
            a, b = dom[s:e], tgt[s:e]
            args = [t.contiguous().numpy() for t in (xs[s:e].double(), self.normals[a].double(),
                                                      self.corners[b].double(), self.normals[b].double())]
            launch(kern.rays, *args, n, pair_seeds(a, b).numpy(), jitter, _MARGIN, eps, _END_GAP, *buffers)

        return self._cast_chunks(kern, cast, xs.shape[0], xs.shape[1], n * n, per)

    def _cast_chunks(self, kern: Any, cast: Any, P: int, Q: int, S: int, per: int) -> Tensor:
        """Visible fractions ``[P, Q]``, ``per`` pairs at a time: ``cast(start, stop, origin, direction, tfar,
        weight)`` fills the chunk's rays and weights, Embree answers, the compiled loop weighs the answers."""
        out = torch.empty(P, Q, dtype=torch.float64)
        for s in range(0, P, per):
            c = min(per, P - s)
            origin = np.empty((c * Q * S, 3), dtype=np.float32)
            direction = np.empty((c * Q * S, 3), dtype=np.float32)
            tfar = np.empty(c * Q * S, dtype=np.float32)
            weight = np.empty((c, Q, S), dtype=np.float64)
            cast(s, s + c, origin, direction, tfar, weight)
            blocked = self.caster.occluded(origin, direction, tfar)
            self.rays += c * Q * S
            launch(kern.fractions, weight, blocked, out[s : s + c].numpy())
        return out

    @staticmethod
    def _weights(x: Tensor, nx: Tensor, y: Tensor, ny: Tensor, area: Tensor) -> Tensor:
        """Point-to-point kernel ``cos θ_x cos θ_y / |x − y|²`` times the area of ``y``'s cell (no ``π``)."""
        r = y - x
        d2 = (r * r).sum(-1).clamp_min(1e-30)
        cos_a = (r * nx).sum(-1).clamp_min(0)
        cos_b = (-(r * ny).sum(-1)).clamp_min(0)
        return cos_a * cos_b / (d2 * d2) * area

    def _blocked(self, x: Tensor, y: Tensor) -> Tensor:
        """Whether the segments from ``x`` to ``y`` (broadcast) hit a facet (bool, their broadcast shape)."""
        r = y - x
        length = (r * r).sum(-1).clamp_min(1e-30).sqrt()
        direction = r / length[..., None]
        gap = self.caster.eps + _END_GAP * length  # see _END_GAP
        origin = x + gap[..., None] * direction
        blocked = self.caster.occluded(origin.reshape(-1, 3).numpy(), direction.reshape(-1, 3).numpy(),
                                       (length - 2 * gap).reshape(-1).numpy())
        self.rays += int(length.numel())
        return torch.from_numpy(blocked).reshape(length.shape)

    def _refine(self, xa: Tensor, a: Tensor, b: Tensor, k: Tensor, seen: Tensor, num: Tensor, den: Tensor) -> None:
        """Rows (point, target) whose first-grid rays disagree: exact cell weights, and boundary cells split.

        Works in place on ``num`` and ``den`` (float64 ``[c, Q]``) from the first grid (``k``, ``seen``:
        ``[c, Q, n²]``). For a row with a shadow boundary the midpoint weights ``k`` would leave a quadrature error
        of the smooth kernel in the ratio; its cells are weighted instead by their exact point-to-polygon factors
        (Lambert's formula on the cell, clipped to the point's horizon), so ``den`` becomes the exact unoccluded
        factor and only boundary cells carry an error. A split cell's weight is shared among its children in
        proportion to their midpoint kernels (exact sums, second-order split) unless it is wider than a tenth of
        its distance to the point (then its children get exact factors too). A cell is on a boundary when its
        ray disagrees with a neighbour's on the same level's grid (the children of the split cells of a row form
        one grid, so a boundary between the children of two split cells is found like one between siblings).
        """
        n = self.n
        c, Q, S = k.shape
        g = seen.reshape(c, Q, n, n)
        edge = torch.zeros_like(g)
        dv = g[..., 1:, :] != g[..., :-1, :]
        du = g[..., :, 1:] != g[..., :, :-1]
        edge[..., 1:, :] |= dv
        edge[..., :-1, :] |= dv
        edge[..., :, 1:] |= du
        edge[..., :, :-1] |= du
        edge = edge.reshape(c, Q, S)
        cell, row = torch.nonzero(edge.any(-1), as_tuple=True)  # rows with a boundary
        if cell.numel() == 0:
            return
        j = torch.arange(S)
        iu, iv = j // n, j % n  # facet_samples: u varies slowest
        w = self._cell_factors(xa[cell, row, 0], a[cell], b[cell], iu.expand(cell.numel(), S),
                               iv.expand(cell.numel(), S), n)  # [M, S]
        wden = w.sum(-1).clamp_min(1e-300)
        split = edge[cell, row] & (w / wden[:, None] > self.tol)
        den[cell, row] = wden
        num[cell, row] = (w * seen[cell, row] * ~split).sum(-1)
        m, jj = torch.nonzero(split, as_tuple=True)
        cell, row, iu, iv, wp = cell[m], row[m], iu[jj], iv[jj], w[m, jj]
        size = n
        for level in range(self.max_levels):
            if cell.numel() == 0:
                return
            # the 2 × 2 children of every split cell on the grid of the next level
            size *= 2
            iu = (2 * iu[:, None] + torch.tensor([0, 0, 1, 1])).reshape(-1)
            iv = (2 * iv[:, None] + torch.tensor([0, 1, 0, 1])).reshape(-1)
            cell, row = cell.repeat_interleave(4), row.repeat_interleave(4)
            y, jac = bilinear(self.corners[b[cell]], ((iu + 0.5) / size).float()[:, None],
                              ((iv + 0.5) / size).float()[:, None])
            x = xa[cell, row]
            sc = ~self._blocked(x, y)[:, 0]
            # the parent's exact weight shared among its children by their midpoint kernels (second order)
            kc = self._weights(x, self.normals[a[cell]][:, None, :], y, self.normals[b[cell]][:, None, :],
                               jac).reshape(-1, 4).double()
            wc = wp[:, None] * kc / kc.sum(-1, keepdim=True).clamp_min(1e-300)
            # near the point (a cell wider than a tenth of its distance) the kernel varies too much for that:
            # exact factors for those children
            d2 = ((y[:, 0] - x[:, 0]) ** 2).sum(-1).double()
            near = (jac[:, 0].double() / (size * size) > 1e-2 * d2).reshape(-1, 4).any(-1)
            if bool(near.any()):
                g = torch.nonzero(near).reshape(-1) * 4
                idx = (g[:, None] + torch.arange(4)).reshape(-1)
                wc[near] = self._cell_factors(x[idx, 0], a[cell[idx]], b[cell[idx]], iu[idx, None], iv[idx, None],
                                              size).reshape(-1, 4)
            wc = wc.reshape(-1)
            split = _disagrees_with_neighbour(((cell * Q + row) * size + iu) * size + iv, sc, size)
            split &= wc / den[cell, row] > self.tol
            if level == self.max_levels - 1:
                split[:] = False
            keep = ~split
            num.index_put_((cell[keep], row[keep]), (wc * sc)[keep], accumulate=True)
            cell, row, iu, iv, wp = cell[split], row[split], iu[split], iv[split], wc[split]

    def _cell_factors(self, x: Tensor, a: Tensor, b: Tensor, iu: Tensor, iv: Tensor, size: int) -> Tensor:
        """Exact factors ``[R, C]`` (float64, Lambert's formula, no occlusion) from points ``x [R, 3]`` on facets
        ``a [R]`` to the cells ``(iu, iv) [R, C]`` of a ``size × size`` grid of facets ``b [R]``, clipped to the
        points' horizons."""
        R, C = iu.shape
        du = torch.tensor([0, 1, 1, 0])
        dv = torch.tensor([0, 0, 1, 1])
        U = ((iu[..., None] + du) / size).reshape(R, C * 4).double()
        V = ((iv[..., None] + dv) / size).reshape(R, C * 4).double()
        poly, _ = bilinear(self.corners[b].double(), U, V)  # [R, C·4, 3]
        poly = poly.reshape(R * C, 4, 3)
        xx = x.double().repeat_interleave(C, 0)
        nx = self.normals[a].double().repeat_interleave(C, 0)
        poly = clip_polygons(poly, xx, nx, 0.0)
        return point_polygon_factor(xx[:, None, :], nx, poly).reshape(R, C).clamp_min(0)


#: Visibility rays skip this share of their length (plus the caster's ``eps``) at each end. A ray that leaves its
#: facet, or arrives at its target, at a grazing angle ``θ`` runs within ``gap · sin θ`` of that facet's plane, and
#: float32 rays hit the facet (or its coplanar neighbour) when that is below the coordinates' rounding: on the
#: Cornell box, rays arriving at 0.35° were found blocked or not by the last bit of their direction.
_END_GAP = 1e-4
#: Jittered samples keep this share of a cell from each of its sides (see :func:`grid_offsets`).
_MARGIN = 0.1


def grid_offsets(dom: Tensor, tgt: Tensor, Q: int, S: int) -> Tensor:
    """Offsets ``[P, Q, S, 2]`` in ``[0.1, 0.9)²`` of the visibility samples within their ``S`` grid cells, for the
    ``Q`` points of each pair ``(dom, tgt)`` ``[P]``: the R2 low-discrepancy sequence over (point, cell), rotated per
    pair by a hash of its facets (Cranley–Patterson), so every cell of every point, and neighbouring pairs, sample
    different places (stratified, jittered sampling). Offsets stay ``_MARGIN`` (a tenth of a cell) from the cell's
    sides: a sample on the very edge of a target that touches the domain (a contact line) would cast a ray grazing
    the domain's own plane, which float32 rays can hit (measured: a 2e-6 loss on a wall standing on a floor with
    full-cell offsets, none with these). Deterministic: the same pair, point and cell always get the same offset."""
    seed = pair_seeds(dom, tgt)
    k = torch.arange(1, Q * S + 1, dtype=torch.float64).reshape(1, Q, S, 1)
    xi = torch.frac(seed[:, None, None, :] + k * torch.tensor(R2_STEP, dtype=torch.float64))
    return _MARGIN + (1 - 2 * _MARGIN) * xi


def _disagrees_with_neighbour(key: Tensor, value: Tensor, size: int) -> Tensor:
    """Which cells of a sparse grid (int64 keys ``(row · size + iu) · size + iv``) hold a value unlike one of
    their (present) 4-neighbours on the same row."""
    order = torch.argsort(key)
    sk, sv = key[order], value[order]
    iu, iv = (sk // size) % size, sk % size
    out = torch.zeros_like(sv)
    for step, ok in ((1, iv < size - 1), (-1, iv > 0), (size, iu < size - 1), (-size, iu > 0)):
        nb = sk + step
        pos = torch.searchsorted(sk, nb).clamp_max(sk.numel() - 1)
        found = ok & (sk[pos] == nb)
        out |= found & (sv[pos] != sv)
    res = torch.empty_like(out)
    res[order] = out
    return res
