"""Interreflection removal: the one-bounce (direct-only) observation from an observed one, with known geometry
and light (:func:`remove_interreflections`). The maths: :mod:`torch_interreflect.inverse`."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from ..camera.sensor import Camera
from ..formfactors.operator import FormFactors
from ..solver.api import radiance
from ._common import alternating, basis_parts, check_facets, check_form_factors, fmatmul, safe_div

__all__ = ["remove_interreflections"]


def remove_interreflections(
    form_factors: FormFactors,
    observed: Tensor,
    E0: Tensor,
    *,
    camera: Camera | None = None,
    basis: Any = None,
    max_iter: int = 100,
    tol: float | None = None,
) -> Tensor:
    """The one-bounce (direct-only) observation from an observed one, with known geometry and light.

    ``B1 = B · E0 / (E0 + F B)`` (module docstring; ``B1 = (I − R F) B`` with ``R`` eliminated). Facets with zero
    irradiance get 0.

    - Spectral radiance (``camera=None``): exact per wavelength; returns direct radiance ``[..., F, L]``.
    - Camera RGB with ``camera`` and no ``basis``: the formula per channel, with ``E0`` replaced by its camera
      response ``camera(E0)`` (exact for narrow-band channels; an approximation for real cameras).
    - Camera RGB with ``camera`` and a linear ``basis`` (e.g. :class:`~torch_interreflect.layers.RGBToSpectrum`):
      reflectances are recovered in the basis by alternating least squares (:func:`estimate_reflectance`) and
      the direct-only RGB ``camera(R E0 / π)`` is rendered (exact when the reflectances lie in the basis).

    Args:
        form_factors: The scene's form factors.
        observed: Radiance ``[..., F, L]`` or camera RGB ``[..., F, C]`` of every facet (all facets are needed:
            unseen facets still send light to the others).
        E0: Direct irradiance in W·m⁻²·nm⁻¹. Shape ``[..., F, L]``.
        camera: The camera for RGB observations.
        basis: Linear reflectance basis for the exact-in-basis RGB method.
        max_iter: Alternating iterations (basis method).
        tol: Alternating tolerance (basis method); default 1e-9 in float64, 1e-5 in float32.

    Returns:
        Direct-only radiance ``[..., F, L]`` or camera RGB ``[..., F, C]``.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.solver import solve, radiance
        >>> from torch_interreflect.inverse import remove_interreflections
        >>> K = ti.form_factors(ti.scenes.v_groove(45.0, divisions=2)).to(torch.float64)
        >>> r = torch.full((8, 31), 0.8, dtype=torch.float64); E0 = torch.ones(8, 31, dtype=torch.float64)
        >>> L1 = remove_interreflections(K, radiance(solve(K, r, E0), r), E0)
        >>> bool(torch.allclose(L1, radiance(E0, r)))
        True
    """
    ff = check_form_factors(form_factors)
    n = ff.num_facets
    E0 = check_facets(E0, "E0", n, None, "[..., F, L]")
    if camera is None:
        observed = check_facets(observed, "observed", n, E0.shape[-1], "[..., F, L] (spectral radiance)")
        B = math.pi * observed
        return observed * safe_div(E0, E0 + fmatmul(ff, B))
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera; got {type(camera).__name__}")
    observed = check_facets(observed, "observed", n, camera.num_channels, "[..., F, C] (camera RGB)")
    if basis is None:
        e0c = camera(E0).to(observed)  # camera response of the irradiance (π × that of a white diffuser)
        B = math.pi * observed
        return observed * safe_div(e0c, e0c + fmatmul(ff, B))
    mean, comps, space = basis_parts(basis, observed)
    if space != "linear":
        raise ValueError("remove_interreflections needs a linear basis (space='linear')")
    with torch.no_grad():
        r, _, _, _ = alternating(
            ff, camera, observed, E0.to(observed), mean, comps, bounces=None, max_iter=max_iter, tol=tol
        )
    return camera(radiance(E0.to(observed), r))
