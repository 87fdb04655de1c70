"""The fragments of a view: sub-pixel rays grouped by (pixel, front-hit facet), and coarser gather points.

A fragment is evaluated once, at the mean of its rays' hit points, weighted by its share of the pixel's rays
(:func:`primary_fragments`); :func:`coarse_points` gives one point per block of pixels and facet and the bilinear
weights that carry values from them to the fragments (``gather_operator(stride=)``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..geometry._polygon import ray_plane_points
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene
from .view import View

__all__ = ["coarse_points", "primary_fragments"]


def primary_fragments(scene: Scene, view: View, s: int, caster: RayCaster) -> dict[str, Tensor]:
    """Sub-pixel rays → fragments (pixel, front-hit facet): facet, pixel, ray count, mean hit point, per-ray data."""
    sc = scene.to(torch.float64).to("cpu")
    eye, dirs = view.rays(s)
    hit = torch.from_numpy(caster.first_hit(np.broadcast_to(eye.numpy(), dirs.shape), dirs.numpy()))
    ok = hit >= 0
    hc = hit.clamp_min(0)
    nd = (sc.normals[hc] * dirs).sum(-1)
    front = ok & (nd < 0)
    pts = ray_plane_points(eye, dirs, sc.centroids[hc], sc.normals[hc])
    h, w = view.height, view.width
    rows = (torch.arange(h * s)[:, None] // s * w + torch.arange(w * s)[None, :] // s).reshape(-1)
    F = sc.num_facets
    key = rows[front] * F + hit[front]
    uniq, inv = torch.unique(key, return_inverse=True)
    count = torch.bincount(inv, minlength=uniq.numel()).to(torch.float64)
    centre = torch.zeros(uniq.numel(), 3, dtype=torch.float64).index_add_(0, inv, pts[front]) / count[:, None]
    background = torch.bincount(rows[~ok], minlength=h * w).to(torch.float64) / (s * s)
    return {"pixel": uniq // F, "facet": uniq % F, "weight": count / (s * s), "centre": centre,
            "background": background.reshape(h, w), "ray_fragment": inv, "ray_point": pts[front],
            "ray_index": torch.nonzero(front).reshape(-1)}


def coarse_points(frag: dict[str, Tensor], height: int, width: int, num_facets: int,
            stride: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gather points every ``stride`` pixels, and the bilinear weights that carry their values to the fragments.

    A coarse fragment is (block of ``stride × stride`` pixels, facet), at the mean of its rays' hit points. Each
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
    count = torch.bincount(inv, minlength=keys.numel()).to(torch.float64)
    centres = torch.zeros(keys.numel(), 3, dtype=torch.float64).index_add_(0, inv, frag["ray_point"]) / count[:, None]
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
