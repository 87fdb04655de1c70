"""Recolouring: change the reflectance of some facets and re-render; the colour bleeding onto every other facet
follows (:func:`recolor`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..camera.facet_rgb import facet_rgb
from ..errors import ShapeError
from ..layers.interreflection import Interreflection
from ._common import e0_from, observed_from

__all__ = ["Recolored", "recolor"]


@dataclass
class Recolored:
    """Result of :func:`recolor`.

    Attributes:
        reflectance: The new reflectance ``[..., F, L]``.
        rgb: Camera RGB after the change ``[..., F, C]`` (``observed`` + predicted change when observed is given).
        image: Image after the change ``[B, C, H, W]`` when the model has a projection, else None.
        change: Predicted change of camera RGB ``[..., F, C]`` (after − before, model only).
    """

    reflectance: Tensor
    rgb: Tensor
    image: Tensor | None
    change: Tensor


def recolor(
    model: Interreflection,
    reflectance: Tensor,
    select: str | Tensor | list[str],
    new_reflectance: Tensor,
    illuminant: Tensor | None = None,
    *,
    E0: Tensor | None = None,
    observed: Tensor | None = None,
) -> Recolored:
    """Change the reflectance of some facets and re-render: colour bleeding onto the others follows exactly.

    Args:
        model: The renderer.
        reflectance: Current per-facet reflectance. Shape ``[..., F, L]``.
        select: The facets to change: material name(s), boolean mask ``[F]`` or facet indices.
        new_reflectance: Their new reflectance, ``[L]`` (one spectrum) or ``[..., K, L]`` (per selected facet).
        illuminant: Spectrum ``[..., L]`` (or ``E0`` by keyword).
        E0: Direct irradiance ``[..., F, L]``.
        observed: Optional observed RGB ``[..., F, C]`` of the current scene; the result is then
            ``observed + model(new) − model(current)`` (keeps what the model does not explain).

    Returns:
        A :class:`Recolored`.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.layers import Interreflection
        >>> from torch_interreflect.inverse import recolor
        >>> wl = ti.spectral.wavelengths()
        >>> layer = Interreflection(ti.scenes.v_groove(45.0, divisions=2), wl)
        >>> r = ti.spectral.reflectance("grey", wl).expand(8, -1)
        >>> out = recolor(layer, r, "plate_a", ti.spectral.reflectance("red", wl), ti.spectral.illuminant("D65", wl))
        >>> bool(out.change[4:, 0].min() > 0)   # the grey plate B gets redder from plate A's bleeding
        True
    """
    mask = model.facets_of(select)
    r = model.reflectance(reflectance) if model.reflectance_model is None else reflectance
    if not isinstance(new_reflectance, Tensor):
        raise TypeError(f"new_reflectance must be a tensor [L] or [..., K, L]; got {type(new_reflectance).__name__}")
    if new_reflectance.shape[-1] != model.num_wavelengths:
        raise ShapeError(
            f"new_reflectance must end with L = {model.num_wavelengths} wavelengths; got {list(new_reflectance.shape)}"
        )
    new = new_reflectance.to(r)
    if new.ndim >= 2:
        k = int(mask.sum())
        if new.shape[-2] != k:
            raise ShapeError(f"new_reflectance [..., K, L] needs K = {k} (selected facets); got {list(new.shape)}")
        full = torch.zeros(*new.shape[:-2], model.num_facets, new.shape[-1], dtype=new.dtype, device=new.device)
        full[..., mask, :] = new
        new = full
    r_new = torch.where(mask[:, None].to(r.device), new, r)
    e0 = e0_from(model, illuminant, E0)
    bounces, tol = model.bounces, model.tol
    rgb_old = facet_rgb(model.form_factors, r, e0, model.camera, bounces=bounces, tol=tol)
    rgb_new = facet_rgb(model.form_factors, r_new, e0, model.camera, bounces=bounces, tol=tol)
    change = rgb_new - rgb_old
    if observed is not None:
        obs = observed_from(model, observed)
        rgb_new = obs + change
    image = None
    if model.projection is not None:
        image = model.projection(rgb_new.reshape(-1, *rgb_new.shape[-2:]))
    return Recolored(r_new, rgb_new, image, change)
