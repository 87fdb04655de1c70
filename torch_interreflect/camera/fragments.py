"""The fragments of a view: sub-pixel rays grouped by (pixel, front-hit facet), and coarser gather points.

A fragment is evaluated once, at the mean of its rays' hit points, weighted by its share of the pixel's rays
(:func:`primary_fragments`); :func:`coarse_points` gives one point per block of pixels and facet and the bilinear
weights that carry values from them to the fragments (``gather_operator(stride=)``).

Anti-aliasing is adaptive when asked (``edge_supersample``): every pixel gets ``s × s`` rays first; where a ray
and one of its eight neighbours on the sub-pixel grid (across pixel borders too) see something different (another
plane or material, the background, a back face, or the other side of a sun shadow), the pixels around get
``e²`` rays instead, at the points of a scrambled Sobol sequence (:meth:`View.rays`; a net when ``e²`` is a
power of two), which place an edge across the pixel far better than an ``e × e`` grid. Elsewhere a pixel sees
one plane in one light, and the mean of its ``s × s`` hit points is what more rays would give.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .._unique import unique_rows
from ..geometry._polygon import plane_eps, plane_ids, ray_plane_points
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene, area_average
from .view import View

__all__ = ["coarse_points", "edge_pixels_of", "primary_fragments", "relative_weights", "sun_free"]


def sun_free(sc: Scene, points: Tensor, facets: Tensor, direction: Tensor, caster: RayCaster) -> Tensor:
    """1 where a hit point on the front of its facet faces the sun and sees it unblocked, else 0. ``[R]`` float64.

    Args:
        sc: The scene (float64, CPU). points: Hit points ``[R, 3]``. facets: Their facets ``[R]``.
        direction: Unit direction the sunlight travels ``[3]``. caster: The scene's ray caster.
    """
    cos = -(sc.normals[facets] @ direction)
    lit = cos > 0
    free = torch.zeros(points.shape[0], dtype=torch.float64)
    if bool(lit.any()):
        pts = points[lit] + caster.eps * sc.normals[facets[lit]]
        escaped = caster.first_hit(pts.numpy(), (-direction).expand(pts.shape[0], 3).numpy()) < 0
        free[lit] = torch.from_numpy(escaped).to(torch.float64)
    return free


def _cast(sc: Scene, eye: Tensor, dirs: Tensor, caster: RayCaster) -> tuple[Tensor, Tensor, Tensor]:
    """``(hit facet or −1 [R], front [R] bool, hit point on the facet's plane [R, 3])`` of rays from ``eye``."""
    hit = torch.from_numpy(caster.first_hit(np.broadcast_to(eye.numpy(), dirs.shape), dirs.numpy()))
    hc = hit.clamp_min(0)
    front = (hit >= 0) & ((sc.normals[hc] * dirs).sum(-1) < 0)
    return hit, front, ray_plane_points(eye, dirs, sc.centroids[hc], sc.normals[hc])


def edge_pixels_of(label: Tensor, height: int, width: int, s: int) -> Tensor:
    """Pixels (flat indices, ascending) holding a sub-pixel ray whose label differs from one of its eight
    neighbours' on the ``[H·s, W·s]`` grid of ``label`` (row-major, as :meth:`View.rays`)."""
    g = label.reshape(height * s, width * s)
    pad = torch.nn.functional.pad(g[None, None].double(), (1, 1, 1, 1), mode="replicate")[0, 0]
    mark = torch.zeros_like(g, dtype=torch.bool)
    for dy in range(3):
        for dx in range(3):
            mark |= pad[dy : dy + g.shape[0], dx : dx + g.shape[1]] != g
    return torch.nonzero(mark.reshape(height, s, width, s).any(3).any(1).reshape(-1)).reshape(-1)


def primary_fragments(scene: Scene, view: View, s: int, caster: RayCaster, *, edge_supersample: int | None = None,
                      sun: Tensor | None = None) -> dict[str, Tensor]:
    """Sub-pixel rays → fragments (pixel, front-hit facet): facet, pixel, weight, mean hit point, per-ray data.

    Args:
        scene: The scene. view: The view. s: Rays per pixel side. caster: The scene's ray caster.
        edge_supersample: Rays per pixel side where the ``s × s`` rays see an edge (module docstring); ``None``
            (or ``≤ s``): ``s`` everywhere.
        sun: Unit direction the sunlight travels ``[3]`` float64: its shadow flags per ray (``"ray_free"``) are
            computed, and with ``edge_supersample`` shadow edges count as edges.

    Returns:
        ``pixel, facet, weight, centre [K, 3]`` per fragment; ``background [H, W]``; per front-hit ray
        ``ray_fragment, ray_point [R, 3], ray_direction [R, 3], ray_weight [R]`` (its share of its pixel) and, with
        a sun, ``ray_free``; ``edge_pixels``, the (flat indices of the) pixels given ``edge_supersample`` rays
        (``[0]`` without).
    """
    sc = scene.to(torch.float64).to("cpu")
    h, w, F = view.height, view.width, sc.num_facets
    eye, dirs = view.rays(s)
    hit, front, pts = _cast(sc, eye, dirs, caster)
    pixel = (torch.arange(h * s)[:, None] // s * w + torch.arange(w * s)[None, :] // s).reshape(-1)
    rays = torch.full((h * w,), float(s * s), dtype=torch.float64)  # rays per pixel
    free = None
    if sun is not None:
        sun = torch.as_tensor(sun, dtype=torch.float64).cpu()
        free = torch.zeros(hit.numel(), dtype=torch.float64)
        free[front] = sun_free(sc, pts[front], hit[front], sun, caster)
    edges = torch.zeros(0, dtype=torch.int64)
    e = 0 if edge_supersample is None else int(edge_supersample)
    if e > s:
        material = sc.material if sc.material is not None else torch.zeros(F, dtype=torch.int64)
        # planes told apart at the float noise of the scene's own dtype (float64 copy, float32 corners)
        facet_label = unique_rows(torch.stack([plane_ids(sc, plane_eps(scene)), material.long()]), dim=1)[1]
        label = torch.where(front, facet_label[hit.clamp_min(0)], torch.where(hit >= 0, -2, -1))
        if free is not None:
            label = torch.where(front, 2 * label + free.long(), label)
        edges = edge_pixels_of(label, h, w, s)
        if edges.numel():
            keep = torch.ones(h * w, dtype=torch.bool)
            keep[edges] = False
            keep = keep[pixel]
            _, d2 = view.rays(e, edges, pattern="sobol")
            h2, f2, p2 = _cast(sc, eye, d2, caster)
            hit, front, pts = torch.cat([hit[keep], h2]), torch.cat([front[keep], f2]), torch.cat([pts[keep], p2])
            dirs = torch.cat([dirs[keep], d2])
            pixel = torch.cat([pixel[keep], edges.repeat_interleave(e * e)])
            rays[edges] = float(e * e)
            if free is not None:
                free2 = torch.zeros(h2.numel(), dtype=torch.float64)
                free2[f2] = sun_free(sc, p2[f2], h2[f2], sun, caster)
                free = torch.cat([free[keep], free2])
    ok = hit >= 0
    key = pixel[front] * F + hit[front]
    uniq, inv = torch.unique(key, return_inverse=True)
    count = torch.bincount(inv, minlength=uniq.numel()).to(torch.float64)
    centre = torch.zeros(uniq.numel(), 3, dtype=torch.float64).index_add_(0, inv, pts[front]) / count[:, None]
    background = torch.bincount(pixel[~ok], minlength=h * w).to(torch.float64) / rays
    out = {"pixel": uniq // F, "facet": uniq % F, "weight": count / rays[uniq // F], "centre": centre,
           "background": background.reshape(h, w), "ray_fragment": inv, "ray_point": pts[front],
           "ray_direction": dirs[front], "ray_weight": 1.0 / rays[pixel[front]], "edge_pixels": edges}
    if free is not None:
        out["ray_free"] = free[front]
    return out


def relative_weights(ray_weight: Tensor) -> Tensor:
    """Ray weights over the smallest one ``[R]``: exactly 1 everywhere when every pixel has the same rays, so a
    weighted mean of hit points is then the plain mean, to the bit."""
    return ray_weight / ray_weight.min() if ray_weight.numel() else ray_weight


def coarse_points(frag: dict[str, Tensor], height: int, width: int, num_facets: int,
            stride: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gather points every ``stride`` pixels, and the bilinear weights that carry their values to the fragments.

    A coarse fragment is (block of ``stride × stride`` pixels, facet), at the mean of its rays' hit points (each
    ray weighted by its share of its pixel, :func:`relative_weights`). Each
    fragment takes the bilinear weights of the four nearest block centres (pixel units) whose coarse fragment lies
    on the same facet, renormalised; its own block is always among them.

    Returns:
        ``(centres [Kc, 3], facets [Kc], weights, ray_point)``: ``weights`` sparse COO ``[K, Kc]`` float64, rows
        summing to 1; ``ray_point [R]`` the coarse point of each of the fragments' rays.
    """
    F, st = num_facets, int(stride)
    wc, hc = -(-width // st), -(-height // st)
    pix = frag["pixel"]
    py, px = pix // width, pix % width
    ray_frag = frag["ray_fragment"]
    ray_key = ((py[ray_frag] // st) * wc + px[ray_frag] // st) * F + frag["facet"][ray_frag]
    keys, inv = torch.unique(ray_key, return_inverse=True)
    centres = area_average(frag["ray_point"], inv, relative_weights(frag["ray_weight"]), keys.numel())
    cy, cx = (py.double() + 0.5) / st - 0.5, (px.double() + 0.5) / st - 0.5
    y0, x0 = cy.floor().long(), cx.floor().long()
    rows, cols, vals = [], [], []
    for dy in (0, 1):
        for dx in (0, 1):
            yy, xx = y0 + dy, x0 + dx
            w = (cy - y0 if dy else 1 - (cy - y0)) * (cx - x0 if dx else 1 - (cx - x0))
            key = (yy.clamp(0, hc - 1) * wc + xx.clamp(0, wc - 1)) * F + frag["facet"]
            at = torch.searchsorted(keys, key).clamp_max(keys.numel() - 1)
            ok = (yy >= 0) & (yy < hc) & (xx >= 0) & (xx < wc) & (keys[at] == key) & (w > 0)
            rows.append(torch.nonzero(ok).reshape(-1))
            cols.append(at[ok])
            vals.append(w[ok])
    r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    v = v / torch.zeros(pix.numel(), dtype=torch.float64).index_add_(0, r, v)[r]
    weights = torch.sparse_coo_tensor(torch.stack([r, c]), v, (pix.numel(), keys.numel()), check_invariants=False)
    weights = weights.coalesce()
    return centres, keys % F, weights, inv
