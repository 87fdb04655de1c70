"""Direct light projected on the polynomial basis of every facet: the right-hand side ``e0`` of the Galerkin system
of :func:`~torch_interreflect.formfactors.moment_form_factors` (``E0[(i, a)]`` = the mean over facet ``i`` of
``ψ_a E0``), as a geometric factor per basis function, ``e0[..., i, a, :] = g[i, a] · spectrum``.

- ``"uniform"``: ``g = (1, 0, …)``.
- a direction (a sun): ``g_a = cos θ_i · mean_i(ψ_a · lit)``; ``lit`` from one shadow ray at each point of an
  ``n × n`` Gauss rule on the facets that something could shadow (:func:`~torch_interreflect.lights.shadow_candidates`),
  1 elsewhere.
- ``"sky"``: ``g_a = π mean_i(ψ_a · open)`` with ``open(x) = 1 − Σ_j F(x → j) − b(x)``; the first part is exact from
  the moments (``Σ_j G[(i, a), (j, 0)]``, also where rows rest on the moments' unbiased ray-cast visibility); where
  other facets' backs may be in view, ``b`` comes from back-hitting cosine-weighted rays
  (:func:`~torch_interreflect.formfactors.hemisphere.hemisphere_point_fractions`), or, on facets whose rows are
  ray cast, the whole open part from escaping rays (both sides of every facet block the sky).
  :func:`sky_estimates` gives that and, from the same rays, ``1 − Σ_j F − b`` on those facets too;
  :func:`~torch_interreflect.solver.solve_moments_sky` weighs the two per facet (their errors differ in kind).
- an area light (a mask ``[F]`` or a material name, radiance ``L``): ``g_a = π Σ_{j ∈ light} G[(i, a), (j, 0)]``.
- a factor ``[F]`` per facet: constant over each facet, ``g = (g_i, 0, …)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from ._checks import check_count
from ._threads import compiled_work
from .errors import ShapeError, ValueRangeError
from .formfactors.basis import facet_rule
from .formfactors.hemisphere import hemisphere_point_fractions
from .formfactors.moments import MomentFormFactors
from .formfactors.pairs import facing_pairs
from .formfactors.visibility import blocker_candidates
from .geometry._polygon import facing_any, plane_eps
from .geometry.raycast import RayCaster
from .geometry.scene import Scene
from .lights import lit_fraction, shadow_candidates, sun_direction
from .sky_openings import sky_through_openings

__all__ = ["SkyRays", "light_is_rough", "light_moments", "sky_estimates", "sky_rays"]


def _project(K: MomentFormFactors, facets: Tensor, points: Tensor, weights: Tensor, values: Tensor) -> Tensor:
    """``Σ_q w_q ψ_a(x_q) v_q`` per facet ``[k, nb]`` from points ``[k, Q, 3]``, weights ``[k, Q]`` (summing to 1
    per facet) and values ``[k, Q]``."""
    psi = K.basis.evaluate_on(facets, points)  # [k, Q, nb]
    return torch.bmm((weights * values)[:, None, :].to(psi.dtype), psi)[:, 0]


def _sun(sc: Scene, K: MomentFormFactors, d: Tensor, shadows: Literal["auto"] | bool,
         n: int) -> tuple[Tensor, Tensor]:
    d = d / d.norm()
    cos = (-(sc.normals @ d)).clamp_min(0.0)
    g = torch.zeros(sc.num_facets, K.size, dtype=torch.float64)
    g[:, 0] = cos
    rough = torch.zeros(sc.num_facets, dtype=torch.bool)
    if shadows is False:
        return g, rough
    idx = shadow_candidates(sc, d, shadows)
    if idx.numel():
        x, wq = facet_rule(sc.corners[idx], n)
        caster = RayCaster.of(sc)
        inside = x + 1e-9 * (sc.centroids[idx][:, None] - x) + caster.eps * sc.normals[idx][:, None]  # off the facet
        hit = caster.first_hit(inside.reshape(-1, 3).numpy(), (-d).expand(inside.shape[0] * inside.shape[1], 3).numpy())
        lit = torch.from_numpy(hit < 0).reshape(wq.shape).to(torch.float64)
        g[idx] = cos[idx, None] * _project(K, idx, x, wq, lit)
        rough[idx] = (lit.amax(1) > 0) & (lit.amin(1) < 1)  # a shadow edge crosses the facet
    return g, rough


@dataclass
class SkyRays:
    """The ray-cast part of the sky's moments: on ``escape_ids`` the open part's moments ``[k, nb]`` counted from
    escaping rays, on ``back_ids`` the back coverage's moments ``[k', nb]`` from back-hitting rays (float64, CPU;
    :func:`sky_rays`). Estimates made with different ``seed`` are independent replicas: :meth:`mean` averages two
    (the sky's moments are affine in them, so the light of the mean is the mean of the lights). ``escape_back``
    (cast with ``rows=True``): the back coverage's moments on ``escape_ids`` from the same rays, for the open part
    as ``1 − Σ_j F − b`` there too (:func:`sky_estimates`). ``opening_rays``: where the open part came from the
    scene's openings instead (:func:`sky_rays` with ``openings=True``; ``escape_ids`` then every facet), the rays
    that cast per sample count squared (for a cost model), else None."""

    escape_ids: Tensor
    escape: Tensor
    back_ids: Tensor
    back: Tensor
    escape_back: Tensor | None = None
    opening_rays: float | None = None

    def mean(self, other: SkyRays) -> SkyRays:
        """The average of two replicas on the same facets.

        Raises:
            ValueError: the replicas cover other facets.
        """
        if not (torch.equal(self.escape_ids, other.escape_ids) and torch.equal(self.back_ids, other.back_ids)):
            raise ValueError("SkyRays.mean needs two replicas on the same facets (the same moments' leaves); got "
                             f"{self.escape_ids.numel()}/{self.back_ids.numel()} and "
                             f"{other.escape_ids.numel()}/{other.back_ids.numel()} escape/back facets that differ")
        both = self.escape_back is not None and other.escape_back is not None
        if not both and (self.escape_back is not None or other.escape_back is not None):
            raise ValueError("SkyRays.mean needs two replicas cast alike: one was cast with rows=True (escape_back) "
                             "and the other without")
        return SkyRays(self.escape_ids, 0.5 * (self.escape + other.escape), self.back_ids,
                       0.5 * (self.back + other.back),
                       0.5 * (self.escape_back + other.escape_back) if both else None,  # type: ignore[operator]
                       self.opening_rays)


def sky_rays(scene: Scene, form_factors: MomentFormFactors, *, backfaces: Literal["auto"] | bool = "auto",
             samples: int = 16, points: int = 8, seed: int = 0, rows: bool = False, openings: bool = False) -> SkyRays:
    """The sky's ray-cast part on the facets where the moments' row sums do not give the open part: where some
    facet's back may be in view (``backfaces``), the whole open part from escaping rays on facets whose rows are ray
    cast, and elsewhere the back coverage from back-hitting rays (both sides of every facet block the sky).

    Args:
        scene: The scene of the moments.
        form_factors: Its :class:`~torch_interreflect.formfactors.moments.MomentFormFactors`.
        backfaces: As for :func:`light_moments`.
        samples, points: Directions and points per axis (``samples² · points²`` rays per facet).
        seed: The samples' rotation (:func:`~torch_interreflect.formfactors.hemisphere.hemisphere_point_fractions`).
        rows: Also count the back-hitting rays on ``escape_ids`` (``escape_back``; one first-hit cast gives both, at
            about twice the cost of the escape count alone), for :func:`sky_estimates`.
        openings: Where the scene's openings can be told (:func:`~torch_interreflect.geometry.openings.openings`),
            the open part of every facet from them instead (:func:`~.sky_openings.sky_through_openings` with
            :data:`OPENING_SAMPLES` times ``samples`` rays per side of an opening and the moments' quadrature
            tolerance; ``escape_ids`` all facets), and with ``rows`` the back coverage from
            :data:`OPENING_BACK_SAMPLES` of the directions; not where the rows are exact (no pair ray cast in
            moments with occlusion, no back in view).

    Returns:
        :class:`SkyRays`.

    Shape:
        - ``escape``: ``[k, nb]``, ``back``: ``[k', nb]``
    """
    check_count(samples, "sky_samples")
    check_count(points, "sky_points")
    sc = scene.detach().to(torch.float64).to("cpu")
    K, F = form_factors, sc.num_facets
    occ = K.info.get("occluded_facets")
    occ = occ.cpu() if isinstance(occ, Tensor) else torch.zeros(F, dtype=torch.bool)
    # where rows rest on ray-cast visibility (occluded pairs), the moments' unbiased estimate makes 1 − Σ_j F as good
    # as the visibility itself (its ray-cast part is measured with it); only where some facet's back may be in view
    # are the escaping rays counted (both sides of every facet block the sky), and elsewhere the part of the
    # hemisphere seeing a back is subtracted. On the Cornell box (200 leaves, 3 rays per side) the ray-cast part
    # fell from 0.31 % to 0.12 %, where counting escaping rays had also needed more sky directions.
    maybe_back = torch.zeros(F, dtype=torch.bool) if backfaces is False else (
        facing_any(sc, one_way=True) if backfaces == "auto" else torch.ones(F, dtype=torch.bool))
    if openings:
        got = _through_openings(sc, K, maybe_back, samples, points, seed, rows)
        if got is not None:
            return got
    escape_ids = torch.nonzero(occ & maybe_back).reshape(-1)
    back_ids = torch.nonzero(maybe_back & ~occ).reshape(-1)
    caster = RayCaster.of(sc) if escape_ids.numel() or back_ids.numel() else None
    escape = torch.zeros(0, K.size, dtype=torch.float64)
    back = torch.zeros(0, K.size, dtype=torch.float64)
    escape_back = torch.zeros(0, K.size, dtype=torch.float64) if rows else None
    if escape_ids.numel():
        h = hemisphere_point_fractions(sc, escape_ids, samples=samples, points=points, back=rows, caster=caster,
                                       seed=seed)
        escape = _project(K, escape_ids, h["points"], h["weights"], h["escape"])
        if rows:
            escape_back = _project(K, escape_ids, h["points"], h["weights"], h["back"])
    if back_ids.numel():
        h = hemisphere_point_fractions(sc, back_ids, samples=samples, points=points, escape=False, caster=caster,
                                       seed=seed)
        back = _project(K, back_ids, h["points"], h["weights"], h["back"])
    return SkyRays(escape_ids, escape, back_ids, back, escape_back)


#: Rays per side of an opening per sky direction per axis (``sky_rays(..., openings=True)``): the open part from
#: the openings is far less noisy than from the escaping rays at the same count (the Cornell box, 122 pieces, r = 0.2:
#: 0.29 % / 0.11 % from Mitsuba with 8² / 16² rays per outer point, against 0.27 % / 0.19 % from 8² / 16² escaping
#: directions at 8² points, 0.15 m). ``render`` on the Cornell box at 1e-2 … 1e-3 (r = 0.9 and 0.2; ``Q_HALVING`` then
#: 0.5) took 0.65–7.9 s with 0.5 and 0.70–7.0 s with 0.75, against 1.2–3.3 s at 1e-2 … 2e-3 with 1.
OPENING_SAMPLES = 0.5

#: Share of the sky's directions per axis that count the back coverage where the open part comes from the openings
#: (the rows' estimate, ``sky_rays(..., openings=True, rows=True)``): 4² directions from 8² points per leaf at the
#: first 16 (the Cornell box at r = 0.9, 122 pieces, 16² rays per side of the opening, three draws: 0.048 % from
#: Mitsuba).
OPENING_BACK_SAMPLES = 0.25


def _through_openings(sc: Scene, K: MomentFormFactors, maybe_back: Tensor, samples: int, points: int, seed: int,
                      rows: bool) -> SkyRays | None:
    """:func:`sky_rays` from the scene's openings (None where they cannot be told, or where the moments' rows are
    exact: moments with occlusion in which no pair of facets is ray cast, and no facet's back in view, so
    ``1 − Σ_j F`` is the open part with no rays, and the openings' moments are not computed)."""
    occ = K.info.get("occluded_facets")
    visibility = K.info.get("settings", {}).get("occlusion", "auto") is not False  # occ marks every blockable pair
    if isinstance(occ, Tensor) and visibility and not bool(occ.any()) and not bool(maybe_back.any()):
        return None
    n_open = max(2, round(samples * OPENING_SAMPLES))
    got = sky_through_openings(sc, K.degree, quadrature_tol=float(K.info.get("quadrature_tol", 1e-6)),
                               visibility_samples=n_open, seed=seed, with_rays=True)
    if got is None:
        return None
    g, rays = got  # type: ignore[misc]
    F = sc.num_facets
    escape_back = None
    if rows:
        escape_back = torch.zeros(F, K.size, dtype=torch.float64)
        ids = torch.nonzero(maybe_back).reshape(-1)
        if ids.numel():
            n = max(2, round(samples * OPENING_BACK_SAMPLES))
            h = hemisphere_point_fractions(sc, ids, samples=n, points=points, escape=False, seed=seed)
            escape_back[ids] = _project(K, ids, h["points"], h["weights"], h["back"])
            rays += ids.numel() * n * n * points * points  # for the cost model, as the openings' rays
    empty = torch.zeros(0, dtype=torch.int64)
    return SkyRays(torch.arange(F), g / math.pi, empty, torch.zeros(0, K.size, dtype=torch.float64), escape_back,
                   rays / samples**2)


def _open_rows(K: MomentFormFactors) -> Tensor:
    """``mean_i(ψ_a (1 − Σ_j F(x → j)))`` per facet ``[F, nb]``: the open part that the moments' rows leave."""
    nb, F = K.size, K.num_facets
    G = K.matrix.detach().to(torch.float64).cpu()
    g = -G.reshape(F, nb, F, nb)[:, :, :, 0].sum(2)
    g[:, 0] += 1.0
    return g


def _sky(K: MomentFormFactors, rays: SkyRays, open_rows: Tensor | None = None) -> Tensor:
    """The sky's geometric factor from the escape count (``open_rows``: :func:`_open_rows` of ``K``, if made)."""
    g = _open_rows(K) if open_rows is None else open_rows.clone()
    g[rays.escape_ids] = rays.escape
    g[rays.back_ids] -= rays.back
    return math.pi * g


def _sky_rows(K: MomentFormFactors, rays: SkyRays, open_rows: Tensor | None = None) -> Tensor:
    """:func:`_sky` with the open part ``1 − Σ_j F − b`` on every facet (``rays.escape_back`` on ``escape_ids``)."""
    g = _open_rows(K) if open_rows is None else open_rows.clone()
    g[rays.back_ids] -= rays.back
    g[rays.escape_ids] -= rays.escape_back  # type: ignore[operator]
    return math.pi * g


def sky_estimates(scene: Scene, form_factors: MomentFormFactors, *, backfaces: Literal["auto"] | bool = "auto",
                  sky_samples: int = 16, sky_points: int = 8, sky_seed: int = 0,
                  sky: SkyRays | None = None) -> tuple[Tensor, Tensor]:
    """The sky's geometric factor (as :func:`light_moments` gives it for ``"sky"``) by two estimators of its open
    part, from the same rays: ``escape``, which counts the escaping rays on the facets whose rows are ray cast and
    some other facet's back may be in view (the estimate of :func:`light_moments`), and ``rows``, ``1 − Σ_j F − b``
    on every facet (the moments' own rows, less the back coverage counted from the rays). Both estimate the same
    light; they differ only on those facets, and only by their sampling errors.

    Their errors differ in kind. The escaping rays' count is an independent estimate of the open part; ``rows``
    takes the moments' visibility errors into the direct light with the opposite sign to the interreflected light's,
    so the two cancel where the facets in view are about as bright as the sky. For an answer the escape estimate
    holds where the surroundings are dark and ``rows`` where they are bright:
    :func:`~torch_interreflect.solver.solve_moments_sky` weighs them per facet.

    Args:
        scene, form_factors, backfaces: As for :func:`light_moments`.
        sky_samples, sky_points, sky_seed: The rays, as for :func:`light_moments` (points and directions per axis,
            the rotation).
        sky: The rays already cast (:func:`sky_rays` with ``rows=True``); cast here when None.

    Returns:
        ``(escape, rows)``, each ``[F, nb]`` (float64, CPU); the direct light is ``g[..., None] * radiance``.

    Raises:
        ShapeError: the moments are of another scene. ValueError: ``sky`` was cast without ``rows=True``, or
        ``backfaces`` is not ``"auto"``, True or False.

    Shape:
        - ``escape``, ``rows``: ``[F, nb]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.formfactors import moment_form_factors
        >>> from torch_interreflect.light_moments import sky_estimates
        >>> box = ti.scenes.v_groove(60.0, divisions=2, dtype=torch.float64)
        >>> G = moment_form_factors(box, 2)
        >>> escape, rows = sky_estimates(box, G)   # no occluded rows: the two are the same
        >>> bool(torch.equal(escape, rows))
        True
    """
    if form_factors.num_facets != scene.num_facets:
        raise ShapeError(f"form_factors has {form_factors.num_facets} facets but the scene has {scene.num_facets}")
    if backfaces not in ("auto", True, False):
        raise ValueError(f"backfaces must be 'auto', True or False; got {backfaces!r}")
    sc = scene.detach().to(torch.float64).to("cpu")
    if sky is None:
        with compiled_work():
            sky = sky_rays(sc, form_factors, backfaces=backfaces, samples=sky_samples, points=sky_points,
                           seed=sky_seed, rows=True)
    elif sky.escape_back is None:
        raise ValueError("sky_estimates needs the back coverage on the escape facets: cast the rays with "
                         "sky_rays(..., rows=True); got SkyRays without escape_back")
    base = _open_rows(form_factors)  # one pass over the moments for both
    return _sky(form_factors, sky, base), _sky_rows(form_factors, sky, base)


def light_moments(
    scene: Scene,
    form_factors: MomentFormFactors,
    light: str | Tensor | Sequence[float] = "uniform",
    *,
    shadows: Literal["auto"] | bool = "auto",
    shadow_order: int = 8,
    backfaces: Literal["auto"] | bool = "auto",
    sky_samples: int = 16,
    sky_points: int = 8,
    rough: bool = False,
    direction: bool | None = None,
    sky_seed: int = 0,
    sky: SkyRays | None = None,
) -> Tensor | tuple[Tensor, Tensor]:
    """The geometric factor of a light on the polynomial basis: ``e0[..., i, a, :] = g[i, a] · spectrum``.

    Args:
        scene: The scene of the moments.
        form_factors: Its :class:`~torch_interreflect.formfactors.moments.MomentFormFactors`.
        light: ``"uniform"``, ``"sky"``, a direction ``[3]`` (a sun; the direction the light travels), a material
            name or a boolean mask ``[F]`` (an area light), or a factor ``[F]`` per facet (taken as constant over
            each facet), as :func:`torch_interreflect.lights.light_geometry` takes them.
        shadows: ``"auto"`` (shadow rays only where another facet is in front), ``True`` or ``False``.
        shadow_order: Gauss points per side of a facet for the sun's shadow rays (``shadow_order²`` rays).
        backfaces: The sky's back-face coverage, as in :func:`torch_interreflect.lights.sky`.
        sky_samples, sky_points: Directions and points per axis of the sky's ray-cast back coverage (and open
            part, on facets with occluded pairs and a back in view).
        direction: ``True``: ``light`` is a direction whatever the scene's facet count (three numbers are a factor
            per facet in a scene of 3 facets otherwise, as :func:`~torch_interreflect.lights.sun_direction` says);
            ``None``: decided by that rule.
        rough: Also return, per facet, whether the light is not smooth over it (a sun's shadow edge crosses it,
            or a sky or area light reaches it through pairs that a third facet can block): where a polynomial
            converges slowly.
        sky_seed: The rotation of the sky's ray samples (:func:`sky_rays`).
        sky: The sky's ray-cast part already cast (:func:`sky_rays` on these moments' leaves, or the
            :meth:`SkyRays.mean` of replicas): ``sky_samples``, ``sky_points``, ``sky_seed`` and ``backfaces`` are
            then unused (they were :func:`sky_rays`' to choose).

    Returns:
        ``g`` (float64 on the CPU; the first column is the facet average, as :func:`light_geometry` gives it),
        and with ``rough=True`` the flags ``[F]`` (bool) as well.

    Raises:
        ValueError: an unknown light name. ShapeError: a tensor of the wrong size. ValueRangeError: a bad factor.

    Shape:
        - output: ``[F, nb]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.light_moments import light_moments
        >>> s = ti.scenes.v_groove(90.0, size=(1.0, 1.0), divisions=1, dtype=torch.float64)
        >>> g = light_moments(s, ti.formfactors.moment_form_factors(s, 1), "sky")
        >>> round(float(g[0, 0]) / 3.14159265, 4)  # 1 - 0.2000438
        0.8
    """
    if form_factors.num_facets != scene.num_facets:
        raise ShapeError(f"form_factors has {form_factors.num_facets} facets but the scene has {scene.num_facets}")
    if shadows not in ("auto", True, False) or backfaces not in ("auto", True, False):
        raise ValueError(f"shadows and backfaces must be 'auto', True or False; got {shadows!r}, {backfaces!r}")
    check_count(shadow_order, "shadow_order")
    check_count(sky_samples, "sky_samples")
    check_count(sky_points, "sky_points")
    sc = scene.detach().to(torch.float64).to("cpu")
    with compiled_work():  # torch's glue on one thread, the compiled loops and rays on the caller's
        g, flags = _moments(sc, form_factors, light, shadows, int(shadow_order), backfaces, int(sky_samples),
                            int(sky_points), bool(direction), int(sky_seed), sky)
    return (g, flags) if rough else g


def _moments(sc: Scene, form_factors: MomentFormFactors, light: str | Tensor | Sequence[float],
             shadows: Literal["auto"] | bool, shadow_order: int, backfaces: Literal["auto"] | bool,
             sky_samples: int, sky_points: int, direction: bool, sky_seed: int = 0,
             sky: SkyRays | None = None) -> tuple[Tensor, Tensor]:
    """:func:`light_moments` and its roughness flags."""
    F, nb = sc.num_facets, form_factors.size
    smooth = torch.zeros(F, dtype=torch.bool)
    occ = form_factors.info.get("occluded_facets")
    occluded = occ.cpu() if isinstance(occ, Tensor) else smooth
    if isinstance(light, str):
        if light == "uniform":
            g = torch.zeros(F, nb, dtype=torch.float64)
            g[:, 0] = 1.0
            return g, smooth
        if light == "sky":
            if sky is None:
                sky = sky_rays(sc, form_factors, backfaces=backfaces, samples=sky_samples, points=sky_points,
                               seed=sky_seed)
            return _sky(form_factors, sky), occluded
        if sc.material_names is None or light not in sc.material_names:
            names = list(sc.material_names) if sc.material_names else []
            raise ValueError(f"light must be 'uniform', 'sky', a direction [3], a facet mask [F], a tensor [F] or a "
                             f"material name of the scene {names}; got {light!r}")
        light = sc.material == sc.material_names.index(light)
    t = light if isinstance(light, Tensor) else torch.as_tensor(light)
    if t.dtype == torch.bool:
        if t.shape != (F,):
            raise ShapeError(f"an area-light mask must have shape [{F}] (one flag per facet); got {list(t.shape)}")
        G = form_factors.matrix.detach().to(torch.float64).cpu().reshape(F, nb, F, nb)[:, :, :, 0]
        return math.pi * (G * t.cpu().to(torch.float64)[None, None, :]).sum(2), occluded
    d = t if direction else sun_direction(t, F)
    if d is not None:
        d64 = d.detach().to(torch.float64).cpu()
        if not bool(torch.isfinite(d64).all()) or float(d64.norm()) == 0.0:
            raise ValueRangeError(f"a light direction must be a finite nonzero 3-vector; got {d64.tolist()}")
        return _sun(sc, form_factors, d64, shadows, shadow_order)
    if not t.is_floating_point() or t.shape != (F,):
        raise ShapeError(f"light as a tensor must be a direction [3] or a geometric factor / mask [F = {F}]; got "
                         f"{list(t.shape)} ({t.dtype})")
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueRangeError("a geometric light factor [F] must be finite and non-negative")
    g = torch.zeros(F, nb, dtype=torch.float64)
    g[:, 0] = t.detach().to(torch.float64).cpu()
    return g, smooth


def light_is_rough(scene: Scene, light: str | Tensor | Sequence[float], *, direction: bool | None = None) -> bool:
    """Whether a light is not smooth over some facet: a sun whose shadow edge crosses a facet (its lit fraction, from
    4 × 4 shadow rays, strictly between 0 and 1), or a sky or an area light on a scene where a third facet can block
    a pair (penumbrae). There a polynomial per facet converges slowly (:mod:`torch_interreflect.accuracy.moments_plan`).
    ``direction`` as for :func:`light_moments`.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.light_moments import light_is_rough
        >>> light_is_rough(ti.scenes.v_groove(45.0), "sky"), light_is_rough(ti.scenes.cornell_box(light=False), "sky")
        (False, True)
    """
    sc = scene.detach().to(torch.float64).to("cpu")
    if isinstance(light, str) and light == "uniform":
        return False
    t = None if isinstance(light, str) else (light if isinstance(light, Tensor) else torch.as_tensor(light))
    if t is not None and (direction or sun_direction(t, sc.num_facets) is not None):
        frac = lit_fraction(sc, t.detach().to(torch.float64).cpu())
        return bool(((frac > 0) & (frac < 1)).any())
    if t is not None and t.dtype != torch.bool:
        return False  # a factor per facet: constant over each
    eps = plane_eps(sc)
    iu, ju = facing_pairs(sc, eps, ("dense", 8))
    return bool(blocker_candidates(sc, iu, ju, eps).any()) if iu.numel() else False
