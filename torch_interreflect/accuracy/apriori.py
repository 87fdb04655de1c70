"""An a-priori estimate of the discretisation error of one solve, from the irradiance at the facets' corners.

The piecewise-constant model lets every source facet ``j`` send its *average* radiosity ``B̄_j``. With ``B(y)`` the
true radiosity and ``F(y → i)`` the form factor from a point ``y`` of ``j`` to facet ``i``, the facet averages
obey exactly ``(I − F R) Ē = E0 + local`` with ``local_i = Σ_j (A_j / A_i) cov_{y ∈ j}(F(y → i), B(y))``, so the
error of the solved averages is ``e = (I − F R)⁻¹ local``: second order, the product of how much the kernel and
the radiosity vary over each source facet. :func:`estimate` evaluates ``E`` at the corners of every facet (nudged
inside; one point per vertex where a single plane meets, one per facet elsewhere) by one exact gather from the
solved facets (Lambert's point-to-polygon formula with occlusion, :func:`torch_interreflect.camera.point_form_factors`,
which also gives ``F(y → i)`` at the corners, and the light at the point), takes each covariance over the four
corners, sums their magnitudes (no cancellation between sources is counted on) and solves once more with the same
form factors.

A source facet whose own rows rest on ray-cast visibility (a partly hidden floor under a sky) can vary inside in
ways its corners miss: it contributes :data:`OSC_SHARE` of the bound ``F_ij r_j osc_j`` (``osc_j`` the largest
deviation at its corners) instead.

Against extrapolated fine solutions (the accuracy benchmark's scenes: V-grooves at 30° and 45°, a box corner, a W
shape under a sun, r = 0.2 and 0.9, 48 to 200 facets) the RMS estimate is 3.4–4.8× the actual RMS error, and at
least the actual error on 95–100 % of the facets (half the bound ``(I − F R)⁻¹ F R osc``, the estimate used before:
5.4–9.8× the RMS error, so the planner refined where one solve already met the request). The Cornell box under a
sky (all its sources occluded) keeps that: 4.0× (r = 0.9) and 1.7× (r = 0.2). The corners' covariance is about
three times the area covariance where both vary linearly, which is the margin. It costs one gather of ``F`` to
``4 F`` points (about a level-0 kernel), against the ``16×`` larger kernel of a forced first split.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from .._unique import unique_rows
from ..camera.point_kernel import point_form_factors
from ..formfactors.operator import FormFactors
from ..geometry._polygon import group_firsts, plane_eps, plane_ids, scene_size
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from ..solver.api import solve

__all__ = ["COV_BLOCK", "NEUMANN_RHO", "OSC_SHARE", "estimate"]

#: Share of the bound ``F_ij r_j osc_j`` taken for a source facet with occluded pairs.
OSC_SHARE = 0.5

#: Entries of the dense block of ``cov_ji`` (source facets × facets × columns) built at a time.
COV_BLOCK = 1 << 22

#: Largest ``ρ = r_max · max row sum`` at which the estimate's solve sums the Neumann series (to 1e-3 in the area-
#: weighted norm: 5 products at 0.2, about 12 at 0.5; its partial sums of these non-negative terms fall short of the
#: factorised answer by about that) instead of the solver's choice (the 200-facet V-groove at r = 0.2: 0.55 ms
#: against 1.4 ms for a Cholesky).
NEUMANN_RHO = 0.5

#: Visibility rays per side of a target facet for the gather at the corners (``samples²`` per blockable pair). On
#: the W shape under a sun (r = 0.2, 150 facets, three seeds each) 2 per side kept every facet's estimate within 1 %
#: of the estimate with 12 per side (3: 0.6 %), in 17 ms against 30 ms; 1 per side: 4.5 %. Under a sky (the Cornell
#: box at r = 0.2, estimated near 30 %, far above any request) the estimate varies by seed at every count.
GATHER_SAMPLES = 2


def _corner_points(sc: Scene, eps: float) -> tuple[Tensor, Tensor, Tensor]:
    """One point per vertex that a single plane touches (a grid's facets share their corners); a vertex where
    facets of several planes meet (a hinge, the foot of a wall on a floor) has one point per facet, since the
    light on either side of a facet standing there differs. Each point is its first facet's corner moved ``1e-6``
    of the way toward that facet's centroid (off the neighbours' edges).

    ``sc``: the scene in float64 on the CPU; ``eps``: :func:`plane_eps` of the scene in its own dtype.

    Shape: ``points [P, 3]`` (float64, CPU), ``facet [P]`` (the facet it was nudged into), ``index [F, 4]``
    (the point of each facet's corner; a triangle's repeated corner is its third).
    """
    F = sc.num_facets
    flat = sc.corners.detach().reshape(-1, 3)
    plane = plane_ids(sc, eps).repeat_interleave(4)  # of each corner slot
    # corners within ~eps of each other are one vertex (a grid's shared vertices may differ in the last bits; a
    # boundary between two rounding cells only keeps two points)
    pos = torch.round(flat / max(eps, 1e-12 * scene_size(sc)))
    vertex = unique_rows(pos)[1]
    planes_at = torch.bincount(unique_rows(torch.stack([vertex, plane], 1))[0][:, 0])  # distinct planes
    owner = torch.where(planes_at[vertex] == 1, plane, -1 - torch.arange(F).repeat_interleave(4))
    _, index, _ = unique_rows(torch.stack([owner, vertex], 1))
    slot = group_firsts(index)  # each point's first corner slot
    facet = slot // 4
    x = flat[slot] + 1e-6 * (sc.centroids.detach()[facet] - flat[slot])
    return x, facet, index.reshape(F, 4)


def _direct_at(light: Any, sc: Scene, x: Tensor, facet: Tensor, index: Tensor, factors: Tensor, covered: Tensor,
               g: Tensor, caster: RayCaster) -> Tensor:
    """The light's geometric factor at every facet's corners ``[F, 4]`` (float64), from the points ``x [P]`` they
    map to by ``index``: the sky from the open part of each point's hemisphere, a sun by one shadow ray per point,
    an area light through the point form factors; a factor given per facet (or anything else) is taken as
    constant over the facet (``sc``: the scene in float64 on the CPU)."""
    g64 = g.detach().to(torch.float64).cpu()
    if isinstance(light, str) and light == "sky":
        return (math.pi * (1.0 - covered).clamp_min(0.0))[index]
    if isinstance(light, str) and light == "uniform":
        return torch.ones(index.shape, dtype=torch.float64)
    t = light if isinstance(light, Tensor) else None
    if t is None and not isinstance(light, str):
        t = torch.as_tensor(light)
    if t is not None and t.numel() == 3 and t.ndim == 1 and t.is_floating_point() and sc.num_facets != 3:
        d = t.detach().to(torch.float64).cpu()
        d = d / d.norm()
        cos = (-(sc.normals @ d)).clamp_min(0.0)[facet]
        lit = cos > 0
        out = torch.zeros(x.shape[0], dtype=torch.float64)
        if bool(lit.any()):  # from a bit further inside: a corner's ray would graze the neighbours
            inside = x[lit] + 1e-3 * (sc.centroids[facet[lit]] - x[lit])
            origin = inside + caster.eps * sc.normals[facet[lit]]
            hit = caster.first_hit(origin.numpy(), (-d).expand(origin.shape[0], 3).numpy())
            out[lit] = cos[lit] * torch.from_numpy(hit < 0).to(torch.float64)
        return out[index]
    if t is not None and t.dtype == torch.bool and t.shape == (sc.num_facets,):
        return (math.pi * torch.sparse.mm(factors, t.to(torch.float64)[:, None]).reshape(-1))[index]
    return g64[:, None].expand(index.shape)


def _corner_covariance(factors: Tensor, index: Tensor, dB: Tensor, areas: Tensor, dense: Tensor | None = None
                       ) -> Tensor:
    """``local_i = Σ_j (A_j / A_i) |cov_j(F(· → i), B)|`` with the covariance over facet ``j``'s four corners:
    ``cov_ji = ¼ Σ_c F(p_jc → i) dB_jc`` (``dB`` sums to zero over the corners, so ``F``'s own mean drops out).

    With ``dense`` (the factors made dense where they fit in :data:`COV_BLOCK` entries) each block of sources takes
    its corners' rows from it (the 200-facet V-groove: 0.5 ms against 2.4 ms for the sparse rows); without, each
    block's rows are gathered from the sparse entries.

    Args:
        factors: Point-to-facet form factors, sparse COO ``[P, n]`` (coalesced).
        index: The point of each facet's corner. Shape ``[n, 4]``.
        dB: Radiosity at each corner minus the mean over the facet's corners. Shape ``[n, 4, B]``.
        areas: Facet areas in m². Shape ``[n]``.
        dense: ``factors`` made dense (:func:`_dense_factors`), where they fit.

    Returns:
        ``local`` (float64). Shape ``[n, B]``.
    """
    n, B = index.shape[0], dB.shape[-1]
    rows = _dense_rows(factors, index) if dense is None else lambda j0, j1: dense[index[j0:j1]]
    acc = torch.zeros(n, B, dtype=torch.float64)
    per = max(1, COV_BLOCK // max(1, 4 * n * B))  # source facets per block: a dense [per, 4, n] and [per, n, B]
    for j0 in range(0, n, per):
        j1 = min(n, j0 + per)
        cov = torch.einsum("jci,jcb->jib", rows(j0, j1), dB[j0:j1])  # 4 cov_ji for the block's sources j
        acc += (areas[j0:j1, None, None] * cov.abs()).sum(0) / 4
    return acc / areas[:, None].clamp_min(1e-300)


def _dense_factors(factors: Tensor) -> Tensor | None:
    """The point-to-facet factors (sparse COO ``[P, n]``) made dense where they fit in :data:`COV_BLOCK` entries."""
    return factors.to_dense() if factors.shape[0] * factors.shape[1] <= COV_BLOCK else None


def _dense_rows(factors: Tensor, index: Tensor) -> Callable[[int, int], Tensor]:
    """``rows(j0, j1)``: the dense rows ``[j1 − j0, 4, n]`` of ``factors`` (sparse COO ``[P, n]``, coalesced) at the
    corner points ``index[j0:j1]``, gathered from its entries."""
    row, col = factors.indices()
    val = factors.values()
    crow = torch.searchsorted(row, torch.arange(factors.shape[0] + 1))  # rows are sorted (coalesced)
    n = factors.shape[1]

    def rows(j0: int, j1: int) -> Tensor:
        p = index[j0:j1].reshape(-1)  # the block's corner slots (4 per facet), each a row of factors
        cnt = crow[p + 1] - crow[p]
        slot = torch.repeat_interleave(torch.arange(p.numel()), cnt)
        ent = crow[p][slot] + torch.arange(slot.numel()) - (torch.cumsum(cnt, 0) - cnt)[slot]
        out = torch.zeros(p.numel() * n, dtype=torch.float64)
        out[slot * n + col[ent]] = val[ent]  # a row's columns are distinct
        return out.reshape(j1 - j0, 4, n)

    return rows


def _method(K: FormFactors, refl: Tensor) -> str:
    """The estimate's solver: the Neumann series where ``ρ = r_max · max row sum`` is at most :data:`NEUMANN_RHO`
    (a dark scene's series converges in a few products, ρ = 0.2: 5 for 1e-3, cheaper than a factorisation), else the
    solver's own choice."""
    rho = float(refl.max()) * float(K.row_sums().max()) if refl.numel() and K.num_facets else 0.0
    return "neumann" if rho <= NEUMANN_RHO else "auto"


@torch.no_grad()
def estimate(scene: Scene, K: FormFactors, refl: Tensor, g: Tensor, h: Tensor, light: Any) -> Tensor:
    """``(I − F R)⁻¹ local``: the error of the piecewise-constant solve, its sources estimated from the corners
    (see the module docstring), relative, per facet.

    Args:
        scene: The solved scene (``n`` facets). K: Its form factors.
        refl: Reflectance per facet and column. Shape ``[..., n, C]``.
        g: The light's geometric factor per facet. Shape ``[n]``.
        h: The solved gain ``(I − F R) h = g``. Shape ``[..., n, C]``.
        light: The light as :func:`~torch_interreflect.accuracy.render` takes it (``"uniform"``, ``"sky"``, a
            direction, a mask ``[n]``, a factor ``[n]``): the light at the corners is evaluated from it.

    Returns:
        Estimated relative error per facet, the largest over the columns (float64, CPU). Shape ``[n]``.
    """
    n = scene.num_facets
    sc = scene.to(torch.float64).to("cpu")
    x, facet, index = _corner_points(sc, plane_eps(scene))
    caster = RayCaster.of(sc)
    factors, covered, _ = point_form_factors(scene, x, facet, samples=GATHER_SAMPLES, caster=caster)
    e0 = _direct_at(light, sc, x, facet, index, factors, covered, g, caster)  # [n, 4]
    h64 = h.detach().to(torch.float64).cpu()
    r64 = refl.detach().to(torch.float64).cpu().expand_as(h64)
    rh = (r64 * h64).movedim(-2, 0)  # [n, ..., C]
    dense = _dense_factors(factors)
    rhs = rh.reshape(n, -1)  # the solved radiosity at the points [P, B]
    gathered = dense @ rhs if dense is not None else torch.sparse.mm(factors, rhs)
    at = e0[..., None] + gathered[index]  # irradiance at every facet's corners [n, 4, B]
    radiosity = r64.movedim(-2, 0).reshape(n, 1, -1) * at
    K64 = K.to(torch.float64) if K.dtype != torch.float64 else K
    K64 = K64.to("cpu") if K64.device.type != "cpu" else K64
    occ = K.info.get("occluded_facets")
    occ = occ.cpu() if occ is not None else torch.zeros(n, dtype=torch.bool)
    dB = radiosity - radiosity.mean(1, keepdim=True)
    dB[occ] = 0.0  # sources whose own light rests on visibility: bounded below instead
    local = _corner_covariance(factors, index, dB, sc.areas.detach(), dense)  # [n, B]
    del dense  # up to COV_BLOCK entries, not needed through the solve
    if bool(occ.any()):
        hh = h64.movedim(-2, 0).reshape(n, -1)
        osc = (at - hh[:, None, :]).abs().amax(1) * occ[:, None]  # [n, B]
        rcol = r64.movedim(-2, 0).reshape(n, -1)
        local = local + OSC_SHARE * K64.matmul(rcol * osc)
    local = local.reshape(rh.shape).movedim(0, -2)  # [..., n, C]
    err = solve(K64, r64, local, tol=1e-3, method=_method(K64, r64)) if bool(local.any()) else local
    rel = err.abs() / h64.abs().clamp_min(1e-300)
    rel = rel.movedim(-2, 0).reshape(n, -1)
    return rel.amax(1) if rel.shape[1] else rel.new_zeros(n)
