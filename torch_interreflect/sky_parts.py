"""The sky's open part per facet on the constant basis, two ways from the same rays (:func:`sky_open_parts`): what
:func:`~torch_interreflect.lights.sky` uses (the escaping rays' count on facets whose rows are ray cast) and one
minus the form factors' row sums less the back coverage. :func:`~torch_interreflect.solver.solve_sky` weighs the two
per facet; :func:`~torch_interreflect.light_moments.sky_estimates` is the same on the polynomial basis.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from ._checks import check_count
from .errors import ShapeError
from .formfactors.hemisphere import hemisphere_fractions
from .formfactors.operator import FormFactorOperator
from .geometry._polygon import facing_any
from .geometry.raycast import RayCaster
from .geometry.scene import Scene

__all__ = ["sky_open_parts"]


def sky_open_parts(scene: Scene, form_factors: FormFactorOperator, *, backfaces: Literal["auto"] | bool = "auto",
                   sky_samples: int = 16) -> tuple[Tensor, Tensor]:
    """The part of each facet's cosine-weighted hemisphere open to the sky, by two estimates from the same rays.

    ``escape`` is the open part of :func:`~torch_interreflect.lights.sky` (``E0 = π L · escape``): the escaping
    rays' count where the facet's row rests on ray-cast visibility, ``1 − Σ_j F_ij − b_i`` elsewhere. ``rows`` is
    ``1 − Σ_j F_ij − b_i`` everywhere, ``b_i`` (the back coverage) counted from the same rays where the facet's row is
    ray cast. Their errors differ in kind (:mod:`~torch_interreflect.solver.sky`). Neither carries a gradient
    (constants of the geometry here; :func:`~torch_interreflect.lights.sky` keeps the gradient of ``F``).

    Args:
        scene: The scene.
        form_factors: Its form factors (:func:`~torch_interreflect.form_factors`).
        backfaces: As for :func:`~torch_interreflect.lights.sky`.
        sky_samples: Directions per axis from each of 8 × 8 points per facet, as for
            :func:`~torch_interreflect.lights.sky`.

    Returns:
        ``(escape, rows)``, each ``[F]`` (float64, CPU); ``rows`` may be slightly negative where the row sums'
        sampling error exceeds a small open part.

    Raises:
        ShapeError: the form factors are of another scene. ValueError: ``backfaces`` is not ``"auto"``, True or False.

    Shape:
        - ``escape``, ``rows``: ``[F]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.sky_parts import sky_open_parts
        >>> box = ti.scenes.cornell_box(light=False, dtype=torch.float64)
        >>> escape, rows = sky_open_parts(box, ti.form_factors(box), sky_samples=4)
        >>> escape.shape, bool((escape - rows).abs().max() < 0.1)
        (torch.Size([16]), True)
    """
    if form_factors.num_facets != scene.num_facets:
        raise ShapeError(f"form_factors has {form_factors.num_facets} facets but the scene has {scene.num_facets}")
    if backfaces not in ("auto", True, False):
        raise ValueError(f"backfaces must be 'auto', True or False; got {backfaces!r}")
    check_count(sky_samples, "sky_samples")
    F = scene.num_facets
    sc = scene.detach().to(torch.float64).to("cpu")
    rows = 1.0 - form_factors.row_sums().detach().to(torch.float64).cpu()
    escape = rows.clone()
    if backfaces is False:
        return escape.clamp_min(0.0), rows
    occ = form_factors.info.get("occluded_facets")
    occ = occ.cpu() if isinstance(occ, Tensor) else torch.zeros(F, dtype=torch.bool)
    maybe_back = facing_any(scene, one_way=True) if backfaces == "auto" else torch.ones(F, dtype=torch.bool)
    ray_cast = torch.nonzero(occ).reshape(-1)
    back_only = torch.nonzero(maybe_back & ~occ).reshape(-1)
    caster = RayCaster.of(sc) if ray_cast.numel() or back_only.numel() else None
    if ray_cast.numel():  # one first-hit cast gives both counts
        e, b = hemisphere_fractions(sc, ray_cast, samples=sky_samples, points=8, caster=caster)
        escape[ray_cast] = e  # type: ignore[assignment]
        rows[ray_cast] -= b  # type: ignore[operator]
    if back_only.numel():
        b = hemisphere_fractions(sc, back_only, samples=sky_samples, points=8, escape=False, caster=caster)[1]
        escape[back_only] -= b  # type: ignore[operator]
        rows[back_only] -= b  # type: ignore[operator]
    return escape.clamp_min(0.0), rows
