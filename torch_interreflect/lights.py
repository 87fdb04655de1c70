"""Direct irradiance ``E0`` on every facet: directional (sun-like, with cast shadows), uniform sky, uniform.

Irradiance is in W·m⁻²·nm⁻¹; spectra are on the caller's wavelength grid (last dimension ``L``). The results
are differentiable with respect to the spectra (and, for :func:`directional`, the direction through the
cosine factor; the lit fraction from ray casting is a constant of the geometry).
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from .errors import ShapeError, ValueRangeError
from .kernel import FormFactors
from .scene import Scene

__all__ = ["back_coverage", "directional", "lit_fraction", "sky", "uniform"]


def _check_spd(spd: Tensor, name: str) -> Tensor:
    if not isinstance(spd, Tensor):
        spd = torch.as_tensor(spd, dtype=torch.get_default_dtype())
    if spd.ndim < 1:
        raise ShapeError(f"{name} must have shape [..., L] (one value per wavelength); got a scalar")
    if not bool(torch.isfinite(spd).all()):
        raise ValueRangeError(f"{name} must be finite; got NaN or inf")
    if bool((spd < 0).any()):
        raise ValueRangeError(f"{name} must be non-negative; got min {float(spd.min()):.4g}")
    return spd


def lit_fraction(
    scene: Scene, direction: Tensor, *, shadows: Literal["auto"] | bool = "auto", samples: int = 4
) -> Tensor:
    """Fraction of each facet's area that a directional light reaches (1 where nothing can cast a shadow).

    Args:
        scene: The scene.
        direction: Direction the light travels (from the light into the scene), shape ``[3]``.
        shadows: ``"auto"`` casts rays only from lit facets that have another facet in front of them;
            ``True`` from every lit facet; ``False`` casts none.
        samples: Rays per direction on each facet (``samples²`` midpoint-rule points per facet).

    Returns:
        Lit fraction in [0, 1], shape ``[F]``, in the scene's dtype (facets facing away get 0).
    """
    if shadows not in ("auto", True, False):
        raise ValueError(f"shadows must be 'auto', True or False; got {shadows!r}")
    if int(samples) < 1:
        raise ValueError(f"samples must be >= 1; got {samples}")
    d = torch.as_tensor(direction, dtype=torch.float64).detach().cpu().reshape(-1)
    if d.numel() != 3 or not bool(torch.isfinite(d).all()) or float(d.norm()) == 0.0:
        raise ValueRangeError(f"direction must be a finite nonzero 3-vector; got {d.tolist()}")
    d = d / d.norm()
    sc = scene.to(torch.float64).to("cpu")
    cos = -(sc.normals @ d)
    frac = (cos > 0).to(torch.float64)
    if shadows is False:
        return frac.to(scene.dtype).to(scene.device)
    from .formfactors import _bilinear, _facing_others

    lit = cos > 0
    if shadows == "auto":
        lit = lit & _facing_others(scene).any(1)
    idx = torch.nonzero(lit).reshape(-1)
    if idx.numel():
        from .raycast import RayCaster

        n = int(samples)
        g = (torch.arange(n, dtype=torch.float64) + 0.5) / n
        x, jac = _bilinear(sc.corners[idx], g.repeat_interleave(n), g.repeat(n))
        caster = RayCaster(sc)
        hit = caster.first_hit(x.reshape(-1, 3).numpy(), (-d).expand(x.shape[0] * x.shape[1], 3).numpy())
        free = torch.from_numpy(hit < 0).reshape(jac.shape).to(torch.float64)
        frac[idx] = (free * jac).sum(1) / jac.sum(1)
    return frac.to(scene.dtype).to(scene.device)


def directional(
    scene: Scene,
    direction: Tensor,
    spd: Tensor,
    *,
    shadows: Literal["auto"] | bool = "auto",
    samples: int = 4,
) -> Tensor:
    """Direct irradiance from a distant (sun-like) light: ``E0_i = spd · max(0, n_i·(−d)) · lit_i``.

    Args:
        scene: The scene.
        direction: Direction the light travels, shape ``[3]`` (need not be unit length). Differentiable.
        spd: Spectral irradiance on a plane facing the light, W·m⁻²·nm⁻¹, shape ``[..., L]``.
        shadows: See :func:`lit_fraction`.
        samples: Shadow rays per direction on each facet.

    Returns:
        ``E0`` in W·m⁻²·nm⁻¹.

    Shape:
        - spd: ``[..., L]``
        - output: ``[..., F, L]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> scene = ti.scenes.v_groove(90.0, divisions=1)
        >>> E0 = ti.lights.directional(scene, torch.tensor([0., 0., -1.]), torch.ones(31))
        >>> E0[:, 0].tolist()
        [1.0, 0.0]
    """
    spd = _check_spd(spd, "spd")
    d = torch.as_tensor(direction)
    if not d.is_floating_point():
        d = d.to(spd.dtype)
    if d.numel() != 3:
        raise ShapeError(f"direction must have 3 components; got shape {list(d.shape)}")
    lit = lit_fraction(scene, d, shadows=shadows, samples=samples).to(spd.dtype).to(spd.device)
    dn = d.reshape(3).to(spd.dtype).to(spd.device)
    dn = dn / dn.norm()
    cos = (-(scene.normals.to(spd.dtype).to(spd.device) @ dn)).clamp_min(0)
    return (cos * lit)[:, None] * spd[..., None, :]


def sky(
    scene: Scene,
    form_factors: FormFactors,
    spd: Tensor,
    *,
    backfaces: Literal["auto"] | bool = "auto",
    samples: int = 16,
) -> Tensor:
    """Direct irradiance from a uniform diffuse sky of radiance ``spd``: ``E0_i = π L (1 − Σ_j F_ij − b_i)``.

    The part of each facet's hemisphere that sees no facet sees the sky. ``F`` counts only the facets whose
    front side a facet sees; ``b_i`` is the part of its hemisphere covered by the *back* of other facets (a
    floor under a block without a bottom sees the block's inside), estimated by ray casting where it can be
    nonzero. With an occlusion-aware ``F`` the result is exact where no back faces are in view.

    Args:
        scene: The scene.
        form_factors: Its form factors.
        spd: Sky radiance, W·sr⁻¹·m⁻²·nm⁻¹, shape ``[..., L]``.
        backfaces: ``"auto"`` estimates ``b_i`` only for facets that have another facet's back in front of
            them; ``True`` for every facet; ``False`` never (``b = 0``).
        samples: Jittered stratified cosine-weighted directions per axis (``samples²`` per point, 8 × 8 points
            per facet) for the ray-cast parts (``b``, and the open part of facets with occluded pairs).

    Shape:
        - output: ``[..., F, L]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> s = ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1)
        >>> E0 = ti.lights.sky(s, ti.form_factors(s), torch.ones(1))
        >>> round(float(E0[0, 0]) / 3.14159265, 4)  # 1 - 0.2000438
        0.8
    """
    spd = _check_spd(spd, "spd")
    if form_factors.num_facets != scene.num_facets:
        raise ShapeError(
            f"form_factors has {form_factors.num_facets} facets but the scene has {scene.num_facets}"
        )
    if backfaces not in ("auto", True, False):
        raise ValueError(f"backfaces must be 'auto', True or False; got {backfaces!r}")
    open_part = 1.0 - form_factors.row_sums().detach().to(torch.float64).cpu()
    if backfaces is not False:
        open_part = open_part - back_coverage(scene, only_where_possible=backfaces == "auto", samples=samples)
    approx = form_factors.info.get("occluded_facets")
    if backfaces is not False and approx is not None and bool(approx.any()):
        # where rows of F rest on ray-cast visibility, 1 − Σ_j F_ij is a small difference of estimates: count the
        # escaping rays directly instead (both sides of every facet block the sky)
        idx = torch.nonzero(approx.cpu()).reshape(-1)
        escape, _ = _hemisphere_fractions(scene.to(torch.float64).to("cpu"), idx, samples=samples, points=8)
        open_part[idx] = escape
    open_part = open_part.clamp_min(0).to(spd.dtype).to(spd.device)
    return math.pi * open_part[:, None] * spd[..., None, :]


def back_coverage(
    scene: Scene, *, only_where_possible: bool = True, samples: int = 12, points: int = 8
) -> Tensor:
    """Fraction of each facet's cosine-weighted hemisphere that sees the back side of some facet.

    Estimated with stratified cosine-weighted rays (``samples²`` directions from each of ``points²`` midpoint
    points per facet), first hits only, so occlusion is included.

    Args:
        scene: The scene.
        only_where_possible: Cast rays only from facets that have a facet in front of them which they see from
            behind (all others get exactly 0).
        samples: Directions per axis.
        points: Points per axis on each facet.

    Returns:
        ``b [F]`` in [0, 1], float64 on the CPU.
    """
    from .formfactors import _facing_others

    sc = scene.to(torch.float64).to("cpu")
    F = sc.num_facets
    b = torch.zeros(F, dtype=torch.float64)
    if only_where_possible:
        front = _facing_others(scene)
        idx = torch.nonzero((front & ~front.T).any(1)).reshape(-1)
    else:
        idx = torch.arange(F)
    if idx.numel() == 0:
        return b
    b[idx] = _hemisphere_fractions(sc, idx, samples=samples, points=points)[1]
    return b


def _hemisphere_fractions(sc: Scene, idx: Tensor, *, samples: int, points: int) -> tuple[Tensor, Tensor]:
    """Cosine-weighted fractions of the hemispheres of facets ``idx`` that escape the scene / hit a back face.

    Jittered stratified cosine-weighted directions (``samples²``) from ``points²`` jittered points per facet,
    area weighted. ``sc`` is a float64 CPU scene. Returns two float64 tensors ``[len(idx)]``.
    """
    from .formfactors import _bilinear, _tangent_frame
    from .raycast import RayCaster

    n = int(samples)
    # jittered stratification of the unit square (fixed seed: reproducible, and unbiased where the midpoint
    # rule is not for a discontinuous visibility) → cosine-weighted hemisphere
    gen = torch.Generator().manual_seed(0)
    cells = torch.arange(n, dtype=torch.float64)
    r1 = (cells.repeat_interleave(n) + torch.rand(n * n, dtype=torch.float64, generator=gen)) / n
    r2 = (cells.repeat(n) + torch.rand(n * n, dtype=torch.float64, generator=gen)) / n
    rad, ang = r1.sqrt(), 2 * math.pi * r2
    local = torch.stack([rad * ang.cos(), rad * ang.sin(), (1 - r1).clamp_min(0).sqrt()], dim=-1)  # [D, 3]
    normals = sc.normals[idx]
    t1, t2 = _tangent_frame(normals)
    lx, ly, lz = (local[None, :, c, None] for c in range(3))
    dirs = lx * t1[:, None] + ly * t2[:, None] + lz * normals[:, None]  # [k, D, 3]
    q = (torch.arange(points, dtype=torch.float64) + 0.5) / points
    qu = q.repeat_interleave(points) + (torch.rand(points * points, dtype=torch.float64, generator=gen) - 0.5) / points
    qv = q.repeat(points) + (torch.rand(points * points, dtype=torch.float64, generator=gen) - 0.5) / points
    caster = RayCaster(sc)
    escape = torch.empty(idx.numel(), dtype=torch.float64)
    back = torch.empty(idx.numel(), dtype=torch.float64)
    per = max(1, (1 << 20) // (points * points * dirs.shape[1]))  # about a million rays at a time
    for s in range(0, idx.numel(), per):
        sl = slice(s, s + per)
        pts, jac = _bilinear(sc.corners[idx[sl]], qu, qv)  # [k, P, 3]
        o = pts[:, :, None, :].expand(-1, -1, dirs.shape[1], -1)
        d = dirs[sl, None, :, :].expand(-1, pts.shape[1], -1, -1)
        hit = torch.from_numpy(caster.first_hit(o.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()))
        hit = hit.reshape(d.shape[:-1])
        is_back = (hit >= 0) & ((d * sc.normals[hit.clamp_min(0)]).sum(-1) > 0)
        w = jac / jac.sum(1, keepdim=True)
        escape[sl] = ((hit < 0).to(torch.float64).mean(-1) * w).sum(1)
        back[sl] = (is_back.to(torch.float64).mean(-1) * w).sum(1)
    return escape, back


def uniform(scene: Scene, spd: Tensor) -> Tensor:
    """The same direct irradiance ``spd`` on every facet (the paper's homogeneous indoor light).

    Shape:
        - spd: ``[..., L]``
        - output: ``[..., F, L]``
    """
    spd = _check_spd(spd, "spd")
    return spd[..., None, :].expand(*spd.shape[:-1], scene.num_facets, spd.shape[-1])
