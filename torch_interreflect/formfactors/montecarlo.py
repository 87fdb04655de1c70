"""The paper's Monte Carlo form-factor estimator (Deeb et al. 2017, §5.2), kept for comparison."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import check_count
from ..geometry._polygon import tangent_frame
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene

__all__ = ["monte_carlo"]



def monte_carlo(
    scene: Scene, samples: int, generator: torch.Generator | None
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """The paper's estimator (§5.2): random points on each facet, cosine-distributed directions, first hit."""
    check_count(samples, "samples")
    sc = scene.to(torch.float64).to("cpu")
    caster = RayCaster.of(sc)
    F = sc.num_facets
    normals = sc.normals
    # orthonormal frame per facet
    t1, t2 = tangent_frame(normals)
    rows, cols, vals = [], [], []
    per = max(1, (1 << 21) // samples)
    for s in range(0, F, per):
        idx = torch.arange(s, min(F, s + per))
        b = idx.numel()
        u = torch.rand(b, samples, dtype=torch.float64, generator=generator)
        v = torch.rand(b, samples, dtype=torch.float64, generator=generator)
        # uniform points on the (possibly collapsed) quad: split at the diagonal into two triangles by area
        c = sc.corners[idx]
        a1 = 0.5 * torch.linalg.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0], dim=-1).norm(dim=-1)
        a2 = 0.5 * torch.linalg.cross(c[:, 2] - c[:, 0], c[:, 3] - c[:, 0], dim=-1).norm(dim=-1)
        pick2 = torch.rand(b, samples, dtype=torch.float64, generator=generator) < (a2 / (a1 + a2))[:, None]
        su = u.sqrt()
        bary_b, bary_c = su * (1 - v), su * v
        p1, p2 = torch.where(pick2[..., None], c[:, None, 2], c[:, None, 1]), torch.where(
            pick2[..., None], c[:, None, 3], c[:, None, 2]
        )
        x = c[:, None, 0] + bary_b[..., None] * (p1 - c[:, None, 0]) + bary_c[..., None] * (p2 - c[:, None, 0])
        # cosine-weighted directions
        r1 = torch.rand(b, samples, dtype=torch.float64, generator=generator)
        r2 = torch.rand(b, samples, dtype=torch.float64, generator=generator)
        rad, ang = r1.sqrt(), 2 * math.pi * r2
        lx, ly, lz = rad * ang.cos(), rad * ang.sin(), (1 - r1).clamp_min(0).sqrt()
        d = lx[..., None] * t1[idx, None] + ly[..., None] * t2[idx, None] + lz[..., None] * normals[idx, None]
        hit = torch.from_numpy(caster.first_hit(x.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()))
        hit = hit.reshape(b, samples)
        src = idx[:, None].expand(-1, samples)
        ok = hit >= 0
        key = src[ok] * F + hit[ok]
        uniq, counts = torch.unique(key, return_counts=True)
        rows.append(uniq // F)
        cols.append(uniq % F)
        vals.append(counts.to(torch.float64) / samples)
    rows_t, cols_t, vals_t = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    keep = rows_t != cols_t
    info = {"rays": F * samples, "samples": samples}
    return rows_t[keep], cols_t[keep], vals_t[keep], info
