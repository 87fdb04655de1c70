"""Gradients of gathered images with respect to the scene's corners and a sun's direction.

A gathered image (:mod:`.gather`) is built from ray-cast quantities that are constants for autograd: which facet
each sub-pixel ray hits, the hit points, the per-pixel kernel ``F(x → j) V(x, j)`` and the direct light ``g0(x)``.
:func:`image_gradient` gives, for an operator and the same scene with corners that require grad (and/or a sun
direction that does), the terms that carry their gradient. Every term is zero in value (``t − t.detach()``), so an
image keeps its values bit for bit; only its graph changes.

- **Interior.** The hit point of each sub-pixel ray moves with the plane of the facet it hits
  (``x = eye + t d``, ``t = (c − eye)·n / (d·n)``); each gather point's kernel ``F(x → j)`` (Lambert's contour
  formula, ``j`` clipped to the tangent plane of ``x``) follows ``x``, the normal and ``j``'s corners, times the
  ray-cast visible fraction ``V(x, j)`` (its own change: below); the direct light follows the same quantities (a
  sun's per-ray cosine, the sky's open part ``1 − Σ_j F V`` over the front-facing targets, an area light's
  ``π Σ F V``).
- **Silhouettes and facet borders** (edge sampling, as in Li et al. 2018, *Differentiable Monte Carlo ray tracing
  through edge sampling*). An image is the box-filtered integral of the radiance over each pixel; where a facet's
  edge is visible the radiance jumps, and moving the edge in the image by ``v`` (pixels, along its normal ``n``)
  changes the pixel by ``∫ (f_a − f_b) v dl`` with ``f_a``, ``f_b`` the radiance on the two sides (``n`` points
  from ``a`` to ``b``). Every mesh edge (:func:`~torch_interreflect.geometry.edges.mesh_edges`) is projected,
  clipped to the image and sampled at midpoints every ``spacing`` pixels; two primary rays just either side of
  each sample tell whether the edge is seen there (one side hits one of its facets) and what lies on each side (the
  fragment of that pixel and facet, or the facet's flat radiance where the pixel has no such fragment, or 0 for
  the background and the back of a facet).
- **A sun's shadow edges on the surfaces.** The parts of mesh edges that the sun projects onto the seen, lit
  facets (:func:`~torch_interreflect.geometry.shadows.shadow_segments`) are projected into the image and sampled the
  same way; a sample counts where both side rays land on the receiving facet and exactly one of their hit points
  sees the sun. The jump across it is the sun's direct light ``r S cos / π``.
- **Per-pixel visibility.** For the pairs a third facet could block, the shadow edges on ``j`` seen from each gather
  point and the interior correction (:mod:`~torch_interreflect.formfactors.visibility_grad`, the gather point as a
  one-point rule that moves along its camera ray).

Edges that reach behind the camera are clipped to the part in front of it first. Not included (held fixed): the part
of the sky hidden by the backs of facets (a :class:`~torch_interreflect.errors.GradientWarning` says so when there
is some).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from ..errors import GradientWarning, ShapeError
from ..formfactors.fused_points import point_polygon_factors
from ..formfactors.visibility import blocker_candidates
from ..formfactors.visibility_grad import boundary_values, interior_values, shadow_spans
from ..geometry._polygon import bilinear, clip_polygons, plane_eps, quad_coordinates, ray_plane_points
from ..geometry.edges import candidate_edges
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene, area_average
from ..lights import sun_direction
from .edge_samples import edge_samples, shadow_samples
from .fragments import relative_weights
from .gather import Gather
from .image_terms import ImageGradient

__all__ = ["EDGE_SPACING", "PAIR_CHUNK", "image_gradient"]

#: Default distance between edge samples along a projected edge, in pixels.
EDGE_SPACING = 0.5
#: (gather point, facet) pairs whose kernel is evaluated at once (checkpointed: memory ~ 16 bytes per pair kept).
PAIR_CHUNK = 1 << 18


def _hit_points(op: Gather, scene: Scene) -> tuple[Tensor, Tensor]:
    """Differentiable hit points of the front rays ``[R, 3]`` and their facets ``[R]``."""
    d = op.ray_direction.to(device=scene.device, dtype=scene.dtype)
    e = torch.tensor(op.view.eye, device=scene.device, dtype=scene.dtype)
    h = op.fragment_facet.cpu()[op.ray_fragment.cpu()].to(scene.device)
    return ray_plane_points(e, d, scene.centroids[h], scene.normals[h]), h


def _kernel_delta(op: Gather, scene: Scene, x_ray: Tensor,
                  caster: RayCaster) -> tuple[Tensor, Tensor | None, Tensor, Tensor, Tensor]:
    """``(delta [Kp, F] sparse COO, weights | None, rows [P], cols [P], delta values [P])`` of the gather
    points."""
    ray_weight = torch.ones(op.ray_fragment.numel(), dtype=torch.float64)  # a fragment's rays share one weight
    if op.kernel is None:
        group, facet, weights = op.ray_fragment.cpu(), op.fragment_facet.cpu(), None
        g = op.gather.cpu()  # CSR: rows in order, columns ascending within a row
        counts = g.crow_indices().diff()
        rows = torch.repeat_interleave(torch.arange(counts.numel()), counts)
        cols, vals = g.col_indices(), g.values()
    else:
        group, facet, weights, g = op.kernel
        ray_weight = relative_weights(op.ray_weight.cpu())  # a coarse point's, as coarse_points weights them
        g = g.coalesce()
        (rows, cols), vals = g.indices(), g.values()
    shape = tuple(g.shape)
    group, facet = group.to(scene.device), facet.to(scene.device)
    x = area_average(x_ray, group, ray_weight, int(facet.numel()))
    rows, cols = rows.to(scene.device), cols.to(scene.device)
    vals = vals.to(device=scene.device, dtype=scene.dtype)
    eps = plane_eps(scene)
    parts = []
    for s in range(0, rows.numel(), PAIR_CHUNK):
        # recomputed in the backward: the graph keeps the chunk's indices, not its per-pair temporaries
        parts.append(checkpoint(_pair_factors, x, scene.normals, scene.centroids, scene.corners, facet,
                                rows[s : s + PAIR_CHUNK], cols[s : s + PAIR_CHUNK], eps, use_reentrant=False))
    f = torch.cat(parts) if parts else torch.zeros(0, dtype=scene.dtype, device=scene.device)
    fd = f.detach()
    vis = torch.where(fd > 0, vals / torch.where(fd > 0, fd, torch.ones_like(fd)), torch.zeros_like(fd)).clamp(0, 1)
    delta_vals = vis * (f - fd) + _visibility_delta(scene, x, rows, cols, facet, caster)
    # (row, column) pairs are sorted and unique: already coalesced
    delta = torch.sparse_coo_tensor(torch.stack([rows, cols]), delta_vals, shape, check_invariants=False,
                                    is_coalesced=True)
    return delta, weights, rows, cols, delta_vals


def _pair_factors(x: Tensor, normals: Tensor, centroids: Tensor, corners: Tensor, facet: Tensor, rows: Tensor,
                  cols: Tensor, eps: float) -> Tensor:
    """``F(x_row → col)`` ``[P]`` without occlusion (Lambert's contour formula; targets the point's plane cuts are
    clipped first, the others evaluated on their four corners). Differentiable in every tensor argument."""
    h = facet[rows]
    n, c = normals[h], centroids[h]
    target = corners[cols]
    cut = (((target.detach() - c.detach()[:, None, :]) * n.detach()[:, None, :]).sum(-1) < -eps).any(1)
    f = torch.zeros(rows.numel(), dtype=corners.dtype, device=corners.device)
    whole, part = torch.nonzero(~cut).reshape(-1), torch.nonzero(cut).reshape(-1)
    if whole.numel():  # targets wholly in front of the point's plane: their four corners
        f = f.index_copy(0, whole, point_polygon_factors(x[rows[whole]], n[whole], target[whole]))
    if part.numel():  # targets the plane cuts: clipped first
        poly = clip_polygons(target[part], c[part], n[part], eps)
        f = f.index_copy(0, part, point_polygon_factors(x[rows[part]], n[part], poly))
    return f


def _visibility_delta(scene: Scene, x: Tensor, rows: Tensor, cols: Tensor, facet: Tensor,
                      caster: RayCaster) -> Tensor:
    """Zero-valued ``[P]`` whose gradient is what the ray-cast ``V(x, j)`` leaves out of ``F(x → j) V(x, j)`` for
    the pairs a third facet could block: the interior correction and the moving shadow edges on ``j`` seen from
    ``x`` (:func:`~torch_interreflect.formfactors.visibility_grad.interior_values`,
    :func:`~torch_interreflect.formfactors.visibility_grad.boundary_values`, with the gather point as a one-point
    domain rule that moves along its camera ray)."""
    out = torch.zeros(rows.numel(), dtype=scene.dtype, device=scene.device)
    if rows.numel() == 0:
        return out
    sc = scene.to(torch.float64).to("cpu")
    cd = sc.corners.detach()
    eps = plane_eps(sc)
    F = sc.num_facets
    h, j = facet.cpu()[rows.cpu()], cols.cpu()
    used = torch.zeros(F * F, dtype=torch.bool)
    used[h * F + j] = True  # the facet pairs in use (a flag per pair: no sort over the point pairs)
    keys = torch.nonzero(used).reshape(-1)
    table = torch.zeros(F * F, dtype=torch.bool)
    table[keys] = blocker_candidates(sc.detach(), keys // F, keys % F, eps)
    sel = torch.nonzero(table[h * F + j]).reshape(-1)
    if sel.numel() == 0:
        return out
    dom, tgt = h[sel], j[sel]
    xp = x.to(torch.float64).to("cpu")[rows.cpu()[sel]]  # [P', 3], differentiable
    u, v = quad_coordinates(cd[dom], xp.detach())  # exact on triangles too (Gauss–Newton converges there)
    rule = (u[:, None], v[:, None], torch.ones(1, dtype=torch.float64))
    edges = candidate_edges(sc, eps)
    spans = shadow_spans(sc, dom, tgt, rule, edges, eps)
    if spans[0].numel() == 0:
        return out
    val = interior_values(sc, dom, tgt, caster, rule, 4, torch.unique(spans[0]), points=xp)
    val = val + boundary_values(sc, dom, tgt, caster, rule, spans, edges, points=xp)
    jac = bilinear(cd[dom], u[:, None], v[:, None])[1][:, 0]  # the rule's area element: per point, divide it out
    val = torch.where(jac > 0, val / jac.clamp_min(1e-300), torch.zeros_like(val))
    return out.index_add(0, sel.to(scene.device), val.to(device=scene.device, dtype=scene.dtype))


def _direct_delta(op: Gather, scene: Scene, light: Any, h_ray: Tensor, rows: Tensor | None,
                  cols: Tensor | None, dvals: Tensor | None, weights: Tensor | None) -> Tensor | None:
    """Zero-valued ``g0`` per fragment ``[K]`` that carries the gradient of the light (see the module docstring)."""
    K = op.num_fragments
    if isinstance(light, str) and light == "uniform":
        return None
    if isinstance(light, str) and scene.material_names is not None and light in scene.material_names:
        light = scene.material == scene.material_names.index(light)
    t = light if isinstance(light, Tensor) else None
    per_point = None
    if isinstance(light, str) and light == "sky" and dvals is not None:
        per_point = -torch.pi * torch.zeros(op.kernel[1].numel() if op.kernel is not None else K, dtype=dvals.dtype,
                                            device=dvals.device).index_add(0, rows, dvals)
    elif t is not None and t.dtype == torch.bool and dvals is not None:
        keep = t.to(scene.device)[cols]
        per_point = torch.pi * torch.zeros(op.kernel[1].numel() if op.kernel is not None else K, dtype=dvals.dtype,
                                           device=dvals.device).index_add(0, rows[keep], dvals[keep])
    if per_point is not None:
        if weights is None:
            return per_point
        return torch.sparse.mm(weights.to(device=per_point.device, dtype=per_point.dtype), per_point[:, None])[:, 0]
    sun = _sun_direction(light, scene)
    if sun is None or op.ray_free is None:
        return None  # a factor per facet: held
    sun = sun.to(device=scene.device, dtype=scene.dtype)
    sun = sun / sun.norm()
    cos = (-(scene.normals[h_ray] * sun).sum(-1)).clamp_min(0) * op.ray_free.to(device=scene.device,
                                                                                 dtype=scene.dtype)
    g0 = area_average(cos[:, None], op.ray_fragment.to(scene.device), torch.ones_like(cos), K)[:, 0]
    return g0 - g0.detach()


def image_gradient(op: Gather, scene: Scene, light: Any = "uniform", *, spacing: float = EDGE_SPACING,
                   shading: str = "gather") -> ImageGradient:
    """The zero-valued terms that carry a gathered image's gradient to ``scene``'s corners and a sun's direction.

    Args:
        op: The view's :class:`~torch_interreflect.camera.Gather`, built from a scene with the same facets.
        scene: That scene, its corners requiring grad (or not, when only the light's direction does).
        light: The light the operator was built with; a direction ``[3]`` that requires grad gets the gradient of
            the per-ray cosines.
        spacing: Distance between edge samples along a projected edge, in pixels (> 0).
        shading: ``"gather"`` (the kernel and direct terms and the edges) or ``"flat"`` (the edges only).

    Returns:
        The :class:`ImageGradient`, for :func:`~torch_interreflect.camera.gathered_radiance`'s ``gradient=``.

    Raises:
        ShapeError: the scene has not the operator's number of facets.
        ValueError: a bad ``spacing`` or ``shading``, or a gather operator built for flat shading only.

    Shape:
        - edge samples ``S`` ≈ the visible edges' length in pixels / ``spacing``; memory O(kernel pairs + S).
    """
    if not isinstance(scene, Scene) or scene.num_facets != op.num_facets:
        got = scene.num_facets if isinstance(scene, Scene) else type(scene).__name__
        raise ShapeError(f"scene must be a Scene with the operator's {op.num_facets} facets; got {got}")
    if isinstance(spacing, bool) or not float(spacing) > 0:
        raise ValueError(f"spacing must be a positive number of pixels; got {spacing!r}")
    if shading not in ("gather", "flat"):
        raise ValueError(f"shading must be 'gather' or 'flat'; got {shading!r}")
    if shading == "gather" and op.gather is None:
        raise ValueError("this operator was built with shading='flat'; build it with shading='gather'")
    if shading == "gather" and isinstance(light, str) and light == "sky" and scene.corners.requires_grad:
        front = (op.gather @ torch.ones(op.num_facets, 1, dtype=op.gather.dtype, device=op.gather.device))[:, 0]
        slack = 100 * torch.finfo(op.open_sky.dtype).eps  # rounding of the sums (~5e-7 in float32), not a hidden sky
        if bool(((1.0 - op.open_sky) - front > slack).any()):
            warnings.warn("image_gradient: the part of the sky hidden by the backs of facets is held fixed (its "
                          "change carries no gradient)", GradientWarning, stacklevel=3)
    caster = RayCaster.of(scene.detach().to(torch.float64).to("cpu"))
    pixel, weight, side_fragment, side_facet = edge_samples(op, scene, caster, float(spacing))
    delta = weights = direct = None
    dev = scene.device
    shadow = (torch.zeros(0, dtype=torch.int64, device=dev), weight.new_zeros(0),
              torch.zeros(0, dtype=torch.int64, device=dev))
    sun = _sun_direction(light, scene)
    if shading == "gather" and sun is not None and op.ray_free is not None:
        shadow = shadow_samples(op, scene, sun, caster, float(spacing))
    if shading == "gather":
        x_ray, h_ray = _hit_points(op, scene)
        rows = cols = dvals = None
        if scene.corners.requires_grad:
            delta, weights, rows, cols, dvals = _kernel_delta(op, scene, x_ray, caster)
        direct = _direct_delta(op, scene, light, h_ray, rows, cols, dvals, weights)
    return ImageGradient(delta, weights, direct, pixel.to(dev), weight, side_fragment.to(dev), side_facet.to(dev),
                         shadow[0].to(dev), shadow[1], shadow[2].to(dev))


def _sun_direction(light: Any, scene: Scene) -> Tensor | None:
    """The light as a sun direction ``[3]`` (floating, possibly requiring grad), or ``None``."""
    t = sun_direction(light, scene.num_facets)
    return t if t is None or t.is_floating_point() else t.to(torch.float64)
