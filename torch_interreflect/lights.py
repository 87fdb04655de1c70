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

__all__ = ["directional", "lit_fraction", "sky", "uniform"]


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
    from .formfactors import _bilinear, _facing, _plane_eps

    lit = cos > 0
    if shadows == "auto":
        F = sc.num_facets
        front = _facing(sc.corners, sc.normals, sc.centroids, _plane_eps(scene), chunk=max(1, (1 << 22) // (4 * F)))
        front.fill_diagonal_(False)
        lit = lit & front.any(1)
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


def sky(scene: Scene, form_factors: FormFactors, spd: Tensor) -> Tensor:
    """Direct irradiance from a uniform diffuse sky of radiance ``spd``: ``E0_i = π L (1 − Σ_j F_ij)``.

    The part of each facet's hemisphere that sees no facet sees the sky, so with an occlusion-aware ``F``
    this is exact.

    Args:
        scene: The scene (for validation).
        form_factors: Its form factors.
        spd: Sky radiance, W·sr⁻¹·m⁻²·nm⁻¹, shape ``[..., L]``.

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
    open_part = (1.0 - form_factors.row_sums().to(spd.dtype).to(spd.device)).clamp_min(0)
    return math.pi * open_part[:, None] * spd[..., None, :]


def uniform(scene: Scene, spd: Tensor) -> Tensor:
    """The same direct irradiance ``spd`` on every facet (the paper's homogeneous indoor light).

    Shape:
        - spd: ``[..., L]``
        - output: ``[..., F, L]``
    """
    spd = _check_spd(spd, "spd")
    return spd[..., None, :].expand(*spd.shape[:-1], scene.num_facets, spd.shape[-1])
