"""Direct irradiance ``E0`` on every facet: directional (sun-like, with cast shadows), uniform sky, uniform.

Irradiance is in W·m⁻²·nm⁻¹; spectra are on the caller's wavelength grid (last dimension ``L``).

**Gradients.** Every light is differentiable with respect to its spectrum, and with respect to the geometry
where the geometry enters smoothly:

- :func:`directional`: the cosine factor ``max(0, n_i·(−d))`` passes gradients to the light direction ``d`` and
  to the scene's corners (through the normals). The lit fraction is ray cast (a constant for autograd); a shadow
  edge sweeping over a facet as the light, a blocker or the facet moves is added by edge sampling
  (:func:`sun_shadow_gradient`, zero in value).
- :func:`sky`: ``π L (1 − Σ_j F_ij)`` is differentiable through ``F`` (so to the corners, exactly for unoccluded
  rows, and with the shadow terms of :func:`torch_interreflect.form_factors` for occluded ones). Where the open
  part is counted by rays (facets with occluded pairs), its value is the count and its gradient that of
  ``1 − Σ_j F_ij``. The back-face coverage ``b_i`` is a constant of the geometry.
- area lights: ``π Σ_{j ∈ light} F_ij`` is differentiable through ``F``.
- :func:`light_geometry` keeps these gradients (a given factor ``g [F]`` is taken as a constant).

How :func:`light_geometry` turns a light into ``E0`` (the ``light=`` argument of the layer and of ``render``):
``E0[..., i, λ] = g_i · S[..., λ]`` with a
geometric factor ``g [F]`` computed once at construction (DESIGN.md §3):

- ``"uniform"`` (default): ``g_i = 1``, the paper's homogeneous light; ``S`` is the irradiance every facet gets.
- a direction ``[3]`` (the direction the light travels): ``g_i = max(0, n_i·(−d)) · lit_i`` with cast shadows
  (:func:`torch_interreflect.lights.directional`); ``S`` is the irradiance on a plane facing the light.
- ``"sky"``: ``g_i = π (1 − Σ_j F_ij)`` (:func:`torch_interreflect.lights.sky`); ``S`` is the sky radiance.
- a material name (e.g. ``"light"`` of the Cornell box) or a boolean mask ``[F]``: an area light, the listed
  facets emit exitance ``M = π S`` (radiance ``S``) toward the others: ``g_i = π Σ_{j ∈ light} F_ij`` (the
  irradiance a diffuse emitter produces, by reciprocity). The emitters' own emission is not part of the rendered
  radiance ``R E / π`` (add it for display if wanted).
- a tensor ``[F]``: ``g`` itself.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor

from ._checks import check_count, check_indices
from ._deprecation import renamed_keywords
from .errors import ShapeError, ValueRangeError
from .formfactors.hemisphere import hemisphere_fractions
from .formfactors.operator import FormFactorOperator
from .formfactors.rules import gauss_legendre01
from .geometry._polygon import bilinear, facing_any, plane_eps, quad_coordinates
from .geometry.raycast import RayCaster
from .geometry.scene import Scene
from .geometry.shadows import shadow_segments

__all__ = ["back_coverage", "directional", "light_geometry", "lit_fraction", "shadow_candidates", "sky",
           "sun_direction", "uniform"]


def _detached_cpu(scene: Scene) -> Scene:
    """The scene in float64 on the CPU without autograd history (for ray casting: constants of the geometry)."""
    return scene.detach().to(torch.float64).to("cpu")


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


def shadow_candidates(scene: Scene, direction: Tensor, shadows: Literal["auto"] | bool) -> Tensor:
    """Lit facets (int64 ``[K]``) that cast shadow rays: with ``shadows="auto"`` only those with another facet in
    front of them."""
    d = torch.as_tensor(direction, dtype=torch.float64).detach().cpu().reshape(-1)
    lit = -(_detached_cpu(scene).normals @ (d / d.norm())) > 0
    if shadows == "auto":
        lit = lit & facing_any(scene)
    return torch.nonzero(lit).reshape(-1)


@renamed_keywords(samples="shadow_samples")
def lit_fraction(
    scene: Scene, direction: Tensor, *, shadows: Literal["auto"] | bool = "auto", shadow_samples: int = 4
) -> Tensor:
    """Fraction of each facet's area that a directional light reaches (1 where nothing can cast a shadow).

    A constant of the geometry: computed on detached corners and direction, it carries no gradient.

    Args:
        scene: The scene.
        direction: Direction the light travels (from the light into the scene), shape ``[3]``.
        shadows: ``"auto"`` casts rays only from lit facets that have another facet in front of them (found in
            row blocks, memory ``O(F)`` per block); ``True`` from every lit facet; ``False`` casts none.
        shadow_samples: Rays per direction on each facet (``shadow_samples²`` midpoint-rule points per facet;
            formerly ``samples``).

    Returns:
        Lit fraction in [0, 1], shape ``[F]``, in the scene's dtype (facets facing away get 0).
    """
    if shadows not in ("auto", True, False):
        raise ValueError(f"shadows must be 'auto', True or False; got {shadows!r}")
    check_count(shadow_samples, "shadow_samples")
    d = torch.as_tensor(direction, dtype=torch.float64).detach().cpu().reshape(-1)
    if d.numel() != 3 or not bool(torch.isfinite(d).all()) or float(d.norm()) == 0.0:
        raise ValueRangeError(f"direction must be a finite nonzero 3-vector; got {d.tolist()}")
    d = d / d.norm()
    sc = _detached_cpu(scene)
    cos = -(sc.normals @ d)
    frac = (cos > 0).to(torch.float64)
    if shadows is False:
        return frac.to(scene.dtype).to(scene.device)
    idx = shadow_candidates(scene, d, shadows)
    if idx.numel():
        n = int(shadow_samples)
        g = (torch.arange(n, dtype=torch.float64) + 0.5) / n
        x, jac = bilinear(sc.corners[idx], g.repeat_interleave(n), g.repeat(n))
        caster = RayCaster.of(sc)
        hit = caster.first_hit(x.reshape(-1, 3).numpy(), (-d).expand(x.shape[0] * x.shape[1], 3).numpy())
        free = torch.from_numpy(hit < 0).reshape(jac.shape).to(torch.float64)
        frac[idx] = (free * jac).sum(1) / jac.sum(1)
    return frac.to(scene.dtype).to(scene.device)


#: Cells per side for the lit facet's own stretching in :func:`sun_shadow_gradient`.
_STRETCH_CELLS = 32


def sun_shadow_gradient(scene: Scene, direction: Tensor, facets: Tensor, *, edge_order: int = 4) -> Tensor:
    """Zero-valued lit fractions ``[F]`` whose gradient is the motion of the shadow edges on ``facets``.

    :func:`lit_fraction` is ray cast on detached geometry. When a blocker, a facet or the light direction moves,
    the shadow a blocker casts on a facet moves, and the facet's lit area changes by ``− ∮_Γ (u · n) dl`` over the
    shadow's edge ``Γ`` on the facet (``n``: its unit normal in the facet's plane pointing into the lit part,
    ``u``: its velocity relative to the facet's own points). ``Γ`` is found by
    :func:`~torch_interreflect.geometry.shadows.shadow_segments` (boundary and crease edges of the mesh, the part
    in front of the facet, projected along the light onto its plane and clipped to it), ``edge_order`` Gauss points
    per part, kept where a ray toward the light is blocked on exactly one side. The facet's own uneven stretching
    (a corner moving) changes its lit share too: ``Σ_c dJ_c (V_c − lit) / A`` over 32 × 32 cells (zero for affine
    motion). Both are added with value zero (edge sampling).

    Args:
        scene: The scene (its corners may require grad).
        direction: Direction the light travels, ``[3]`` (may require grad).
        facets: The lit facets that something could shadow (int64 ``[K]``).
        edge_order: Gauss points per projected edge.

    Raises:
        ValueRangeError: ``direction`` is not a finite nonzero 3-vector, or a facet index is out of range.
        ShapeError: ``facets`` is not a 1-D int64 tensor.

    Shape:
        - output: ``[F]`` (zeros), float64 on the CPU
    """
    d_g = torch.as_tensor(direction).to(torch.float64).cpu()
    if d_g.numel() != 3 or not bool(torch.isfinite(d_g).all()) or float(d_g.detach().norm()) == 0.0:
        raise ValueRangeError(f"direction must be a finite nonzero 3-vector; got {d_g.detach().tolist()}")
    facets = torch.as_tensor(facets)
    if facets.ndim != 1 or facets.dtype != torch.int64:
        raise ShapeError(f"facets must be int64 facet indices [K]; got shape {list(facets.shape)} ({facets.dtype})")
    facets = check_indices(facets, scene.num_facets, "facets")
    sc = scene.to(torch.float64).to("cpu")
    corners, normals_g = sc.corners, sc.normals
    cd, normals = corners.detach(), normals_g.detach()
    d_g = d_g.reshape(3)
    d_g = d_g / d_g.norm()
    d = d_g.detach()
    caster = RayCaster(Scene.from_parts(cd, sc.is_triangle, sc.material, sc.material_names))
    out = corners.new_zeros(sc.num_facets) + 0 * d_g.sum()
    if facets.numel():
        # the facet's own stretching: d lit = Σ_c dJ_c (V_c − lit) / A over m × m cells (0 for affine motion)
        g = (torch.arange(_STRETCH_CELLS, dtype=torch.float64) + 0.5) / _STRETCH_CELLS
        u, v = g.repeat_interleave(_STRETCH_CELLS), g.repeat(_STRETCH_CELLS)
        x, jac = bilinear(cd[facets], u, v)
        hit = caster.first_hit(x.reshape(-1, 3).numpy(), (-d).expand(x.shape[0] * x.shape[1], 3).numpy())
        free = torch.from_numpy(hit < 0).reshape(jac.shape).to(torch.float64)
        lit = (free * jac).sum(1, keepdim=True) / jac.sum(1, keepdim=True)
        jac_g = bilinear(corners[facets], u, v)[1]
        out = out.index_add(0, facets, ((jac_g - jac_g.detach()) * (free - lit)).sum(1) / jac.sum(1))
    eps = plane_eps(sc)
    parts = shadow_segments(sc.detach(), d, facets, eps)
    if parts.facet.numel() == 0:
        return out
    t, w = gauss_legendre01(edge_order)
    seg = parts.end - parts.start
    length = seg.norm(dim=-1)
    f, n = parts.facet.repeat_interleave(edge_order), normals[parts.facet].repeat_interleave(edge_order, 0)
    y = (parts.start[:, None, :] + t[None, :, None] * seg[:, None, :]).reshape(-1, 3)
    s = (parts.s_a[:, None] + t * (parts.s_b - parts.s_a)[:, None]).reshape(-1)
    ell = (w * length[:, None]).reshape(-1)
    seg, length = seg.repeat_interleave(edge_order, 0), length.repeat_interleave(edge_order)
    ef, ec = parts.edge_facet.repeat_interleave(edge_order), parts.edge_corner.repeat_interleave(edge_order)
    side = torch.linalg.cross(n, seg / length[:, None], dim=-1)
    off = 1e-4 * sc.areas.detach()[f].sqrt()[:, None] * side
    towards = (-d).expand(y.shape[0], 3).numpy()
    plus = torch.from_numpy(caster.first_hit((y + off).numpy(), towards) >= 0)
    minus = torch.from_numpy(caster.first_hit((y - off).numpy(), towards) >= 0)
    edge = plus != minus
    if not bool(edge.any()):
        return out
    sign = torch.where(minus, 1.0, -1.0).to(torch.float64)[edge]  # n_in = sign · side points into the lit part
    f, ef, ec, s, y, side, ell = (z[edge] for z in (f, ef, ec, s, y, side, ell))
    # the differentiable positions: the shadow point, and the facet's own point under it
    g0, g1 = corners[ef, ec], corners[ef, (ec + 1) % 4]
    b = g0 + s[:, None] * (g1 - g0)
    ng, og = normals_g[f], corners[f, 0]
    yg = b - (((b - og) * ng).sum(-1) / (ng * d_g).sum(-1))[:, None] * d_g
    u, v = quad_coordinates(cd[f], y)
    ym, _ = bilinear(corners[f], u[:, None], v[:, None])
    move = (yg - yg.detach()) - (ym[:, 0] - ym[:, 0].detach())
    lit_area = -ell * sign * (side * move).sum(-1)
    return out.index_add(0, f, lit_area / sc.areas.detach()[f])


@renamed_keywords(samples="shadow_samples")
def directional(
    scene: Scene,
    direction: Tensor,
    spd: Tensor,
    *,
    shadows: Literal["auto"] | bool = "auto",
    shadow_samples: int = 4,
) -> Tensor:
    """Direct irradiance from a distant (sun-like) light: ``E0_i = spd · max(0, n_i·(−d)) · lit_i``.

    Args:
        scene: The scene.
        direction: Direction the light travels, shape ``[3]`` (need not be unit length). Differentiable (with the
            scene's corners) through the cosine factor and the shadows' edges (:func:`sun_shadow_gradient`).
        spd: Spectral irradiance on a plane facing the light, W·m⁻²·nm⁻¹, shape ``[..., L]``.
        shadows: See :func:`lit_fraction`.
        shadow_samples: Shadow rays per direction on each facet (formerly ``samples``).

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
    lit = lit_fraction(scene, d, shadows=shadows, shadow_samples=shadow_samples).to(spd.dtype).to(spd.device)
    if shadows is not False and torch.is_grad_enabled() and (scene.corners.requires_grad or d.requires_grad):
        # the shadows' edges moving with the geometry and the direction: zero in value (sun_shadow_gradient)
        facets = shadow_candidates(scene, d, shadows)
        lit = lit + sun_shadow_gradient(scene, d, facets).to(spd.dtype).to(spd.device)
    dn = d.reshape(3).to(spd.dtype).to(spd.device)
    dn = dn / dn.norm()
    cos = (-(scene.normals.to(spd.dtype).to(spd.device) @ dn)).clamp_min(0)
    return (cos * lit)[:, None] * spd[..., None, :]


@renamed_keywords(samples="sky_samples")
def sky(
    scene: Scene,
    form_factors: FormFactorOperator,
    spd: Tensor,
    *,
    backfaces: Literal["auto"] | bool = "auto",
    sky_samples: int = 16,
    facets: Tensor | None = None,
) -> Tensor:
    """Direct irradiance from a uniform diffuse sky of radiance ``spd``: ``E0_i = π L (1 − Σ_j F_ij − b_i)``.

    The part of each facet's hemisphere that sees no facet sees the sky. ``F`` counts only the facets whose
    front side a facet sees; ``b_i`` is the part of its hemisphere covered by the *back* of other facets (a
    floor under a block without a bottom sees the block's inside), estimated by ray casting where it can be
    nonzero. With an occlusion-aware ``F`` the result is exact where no back faces are in view. Where rows are ray
    cast the escaping rays are counted instead; under bright surroundings :func:`~torch_interreflect.solver.solve_sky`
    (with :func:`~torch_interreflect.sky_parts.sky_open_parts`) weighs that count against ``1 − Σ_j F_ij − b_i``.

    Args:
        scene: The scene.
        form_factors: Its form factors.
        spd: Sky radiance, W·sr⁻¹·m⁻²·nm⁻¹, shape ``[..., L]``.
        backfaces: ``"auto"`` estimates ``b_i`` only for facets that have another facet's back in front of
            them (found in row blocks, no ``[F, F]`` matrix); ``True`` for every facet; ``False`` never (``b = 0``).
        sky_samples: Stratified cosine-weighted directions per axis (``sky_samples²`` per point, 8 × 8 points per
            facet, both with low-discrepancy offsets:
            :func:`~torch_interreflect.formfactors.hemisphere.hemisphere_fractions`) for the ray-cast parts (``b``,
            and the open part of facets with occluded pairs; formerly ``samples``).
        facets: Only these facets' rows (integer ``[k]``, e.g. the new facets of a refined mesh whose other values
            are known): rays are cast from them alone, with the same values as in the full call.

    Shape:
        - output: ``[..., F, L]`` (``[..., k, L]`` with ``facets``)

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
    check_count(sky_samples, "sky_samples")
    F = scene.num_facets
    rows = None if facets is None else check_indices(facets, F, "facets")
    open_part = 1.0 - form_factors.row_sums().to(torch.float64).cpu()  # keeps the gradient of F (module docstring)
    open_part = open_part if rows is None else open_part[rows]
    if backfaces is not False:
        # where rows of F rest on ray-cast visibility, 1 − Σ_j F_ij is a small difference of estimates: count the
        # escaping rays directly instead (both sides of every facet block the sky); elsewhere subtract the part of
        # the hemisphere that sees some facet's back. One pass of rays serves both.
        approx = form_factors.info.get("occluded_facets")
        approx = approx.cpu() if approx is not None else torch.zeros(F, dtype=torch.bool)
        maybe_back = facing_any(scene, one_way=True) if backfaces == "auto" else torch.ones(F, dtype=torch.bool)
        ids = torch.arange(F) if rows is None else rows
        approx, maybe_back = approx[ids], maybe_back[ids]
        open_part = open_part.clone()
        sc = _detached_cpu(scene)
        escape_pos = torch.nonzero(approx).reshape(-1)  # positions in the output; the facets are ids[pos]
        back_pos = torch.nonzero(maybe_back & ~approx).reshape(-1)
        caster = RayCaster.of(sc) if escape_pos.numel() or back_pos.numel() else None  # one BVH for both passes
        if escape_pos.numel():
            # the escaping rays' count as the value, the gradient of 1 − Σ_j F_ij (which carries the moving shadow
            # edges of its occluded pairs, see form_factors) as its derivative
            from_f = open_part[escape_pos]
            open_part[escape_pos] = hemisphere_fractions(sc, ids[escape_pos], samples=sky_samples, points=8,
                                                         back=False, caster=caster)[0] + (from_f - from_f.detach())
        if back_pos.numel():
            open_part[back_pos] = open_part[back_pos] - hemisphere_fractions(
                sc, ids[back_pos], samples=sky_samples, points=8, escape=False, caster=caster)[1]
    open_part = open_part.clamp_min(0).to(spd.dtype).to(spd.device)
    return math.pi * open_part[:, None] * spd[..., None, :]


@renamed_keywords(samples="sky_samples")
def back_coverage(
    scene: Scene, *, only_where_possible: bool = True, sky_samples: int = 12, points: int = 8
) -> Tensor:
    """Fraction of each facet's cosine-weighted hemisphere that sees the back side of some facet.

    Estimated with stratified cosine-weighted rays (``sky_samples²`` directions from each of ``points²`` jittered
    points per facet), first hits only, so occlusion is included.

    Args:
        scene: The scene.
        only_where_possible: Cast rays only from facets that have a facet in front of them which they see from
            behind (all others get exactly 0; found in row blocks, no ``[F, F]`` matrix).
        sky_samples: Directions per axis (formerly ``samples``).
        points: Points per axis on each facet.

    Returns:
        ``b [F]`` in [0, 1], float64 on the CPU.
    """
    check_count(sky_samples, "sky_samples")
    check_count(points, "points")
    sc = _detached_cpu(scene)
    F = sc.num_facets
    b = torch.zeros(F, dtype=torch.float64)
    idx = torch.nonzero(facing_any(scene, one_way=True)).reshape(-1) if only_where_possible else torch.arange(F)
    if idx.numel() == 0:
        return b
    b[idx] = hemisphere_fractions(sc, idx, samples=sky_samples, points=points, escape=False)[1]
    return b


def uniform(scene: Scene, spd: Tensor) -> Tensor:
    """The same direct irradiance ``spd`` on every facet (the paper's homogeneous indoor light).

    Shape:
        - spd: ``[..., L]``
        - output: ``[..., F, L]``
    """
    spd = _check_spd(spd, "spd")
    return spd[..., None, :].expand(*spd.shape[:-1], scene.num_facets, spd.shape[-1])


def sun_direction(light: object, num_facets: int) -> Tensor | None:
    """``light`` as a direction ``[3]`` (the direction the light travels, as given: not normalised, gradients
    kept), or ``None`` when it is another kind of light (see :func:`light_geometry`).

    Three numbers are a direction, except in a scene of 3 facets, where they are the factor ``g [F]``; a boolean
    tensor is an area-light mask. Integers come back as an integer tensor (callers convert); anything
    ``torch.as_tensor`` cannot read raises its error.

    Example:
        >>> from torch_interreflect.lights import sun_direction
        >>> sun_direction([0, 0, -1], 8).tolist(), sun_direction("sky", 8), sun_direction([0.2, 0.1, 0.3], 3)
        ([0, 0, -1], None, None)
    """
    if light is None or isinstance(light, str):
        return None
    t = light if isinstance(light, Tensor) else torch.as_tensor(light)
    if t.dtype == torch.bool or t.ndim != 1 or t.numel() != 3 or num_facets == 3:
        return None
    return t


def light_geometry(
    scene: Scene | None,
    form_factors: FormFactorOperator,
    light: str | Tensor | Sequence[float] | None = None,
    *,
    shadows: str | bool = "auto",
) -> Tensor:
    """The geometric factor ``g [F]`` of a light: ``E0[..., i, :] = g_i · spectrum`` (see the module docstring).

    Arguments come in the order of every light function, ``(scene, form_factors, light)``. The old order
    ``light_geometry(light, form_factors, scene=None)`` still works for one release, with a
    ``DeprecationWarning``.

    Args:
        scene: The scene (directional lights and material names need it; ``None`` for the others).
        form_factors: The scene's form factors (``"sky"`` and area lights use them).
        light: ``"uniform"``, ``"sky"``, a direction ``[3]``, a material name, a boolean mask ``[F]`` (area light),
            or ``g`` itself as a floating tensor ``[F]``.
        shadows: Shadow handling of directional lights (see :func:`torch_interreflect.lights.lit_fraction`).

    Returns:
        ``g`` in the form factors' dtype and device. Shape ``[F]``.

    Raises:
        ValueError: an unknown light name, or a light that needs the scene when none is given.
        ShapeError: a tensor of the wrong size.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.lights import light_geometry
        >>> scene = ti.scenes.v_groove(90.0, divisions=1)
        >>> light_geometry(scene, ti.form_factors(scene), [0.0, 0.0, -1.0]).tolist()
        [1.0, 0.0]
    """
    if scene is not None and not isinstance(scene, Scene):  # the old order (light, form_factors, scene)
        warnings.warn(
            "light_geometry(light, form_factors, scene) is now light_geometry(scene, form_factors, light) (the "
            "order of every light function); the old order will be removed in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        scene, light = light, scene
        if scene is not None and not isinstance(scene, Scene):
            raise TypeError(f"scene must be a Scene or None; got {type(scene).__name__}")
    if light is None:
        raise TypeError("light_geometry() needs a light: light_geometry(scene, form_factors, light)")
    n = form_factors.num_facets
    dtype, device = form_factors.dtype, form_factors.device
    if isinstance(light, str):
        if light == "uniform":
            return torch.ones(n, dtype=dtype, device=device)
        if light == "sky":
            return math.pi * (1.0 - form_factors.row_sums()).clamp_min(0.0)
        if scene is None or scene.material_names is None or light not in scene.material_names:
            names = list(scene.material_names) if scene is not None and scene.material_names else []
            raise ValueError(
                f"light must be 'uniform', 'sky', a direction [3], a facet mask [F], a tensor [F] or a material name "
                f"of the scene {names}; got {light!r}"
            )
        mask = scene.material == scene.material_names.index(light)
        return light_geometry(scene, form_factors, mask.to(device))
    t = torch.as_tensor(light)
    if t.dtype == torch.bool:
        if t.shape != (n,):
            raise ShapeError(f"an area-light mask must have shape [{n}] (one flag per facet); got {list(t.shape)}")
        cols = t.to(device=device, dtype=dtype)[:, None]
        return math.pi * form_factors.matmul(cols).reshape(n)
    if sun_direction(t, n) is not None:
        if scene is None:
            raise ValueError("a directional light needs the scene (for normals and shadows); pass a Scene")
        e0 = directional(scene, t.to(torch.float64), torch.ones(1, dtype=torch.float64), shadows=shadows)
        return e0[:, 0].to(device=device, dtype=dtype)
    if not t.is_floating_point() or t.shape != (n,):
        raise ShapeError(
            f"light as a tensor must be a direction [3] or a geometric factor / mask [F = {n}]; got "
            f"{list(t.shape)} ({t.dtype})"
        )
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueRangeError("a geometric light factor [F] must be finite and non-negative")
    return t.detach().to(device=device, dtype=dtype)
