"""Illuminant estimation: fit a daylight or blackbody illuminant and a scale to observed RGB through the renderer
(:func:`estimate_illuminant`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ValueRangeError
from ..layers.illuminant import IlluminantBasis
from ..layers.interreflection import Interreflection
from ..spectral.illuminants import CCT_RANGE, cct_to_daylight_coefficients
from ._common import observed_from, rel_residual

__all__ = ["IlluminantEstimate", "estimate_illuminant"]


@dataclass
class IlluminantEstimate:
    """Result of :func:`estimate_illuminant`.

    Attributes:
        spectrum: Fitted spectrum including the scale, ``[..., L]`` (W·m⁻²·nm⁻¹ for a uniform light).
        scale: Multiplier of the relative spectrum (100 at 560 nm), ``[...]``.
        parameters: ``(M1, M2)`` ``[..., 2]`` or the temperature in K ``[...]``.
        cct: Temperature in K for ``"cct"``/``"blackbody"``; for ``"coefficients"`` the CCT whose daylight
            ``(M1, M2)`` is nearest (grid search on the locus), for reporting.
        residual: Relative RMS RGB residual.
        iterations: L-BFGS iterations.
    """

    spectrum: Tensor
    scale: Tensor
    parameters: Tensor
    cct: Tensor
    residual: float
    iterations: int


def _nearest_cct(m: Tensor) -> Tensor:
    grid = torch.linspace(CCT_RANGE[0], CCT_RANGE[1], 4201, dtype=torch.float64)
    locus = cct_to_daylight_coefficients(grid)  # [G, 2]
    d = (m.detach().double().cpu()[..., None, :] - locus).pow(2).sum(-1)
    return grid[d.argmin(-1)].to(m.device)


def estimate_illuminant(
    model: Interreflection,
    reflectance: Tensor,
    observed: Tensor,
    *,
    parametrisation: str = "coefficients",
    init: float = 6500.0,
    steps: int = 100,
) -> IlluminantEstimate:
    """Fit an illuminant (daylight basis or blackbody, with a scale) to observed RGB through the renderer.

    The spectrum is ``scale · S(θ)`` with ``S`` from :class:`~torch_interreflect.layers.IlluminantBasis`
    (``"coefficients"``: ``θ = (M1, M2)``; ``"cct"``: ``θ = T`` on the daylight locus, kept in 4000–25000 K by a
    sigmoid; ``"blackbody"``: ``θ = T > 0`` through ``exp``). ``θ`` and ``log scale`` are fitted by L-BFGS to the
    relative squared RGB error of ``model(reflectance, scale · S(θ))``, starting from ``init`` K with the best scale
    for it (closed form, the rendering is linear in the scale).

    Args:
        model: The renderer (geometry, light, camera, bounces).
        reflectance: Known reflectance (or the model's reflectance input). Shape ``[..., F, L]``.
        observed: Observed camera RGB. Shape ``[..., F, C]``; leading dims fit separate illuminants.
        parametrisation: ``"coefficients"``, ``"cct"`` or ``"blackbody"``.
        init: Starting temperature in K.
        steps: L-BFGS iterations.

    Returns:
        An :class:`IlluminantEstimate`.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.layers import Interreflection
        >>> from torch_interreflect.inverse import estimate_illuminant
        >>> wl = ti.spectral.wavelengths(dtype=torch.float64)
        >>> layer = Interreflection(ti.scenes.v_groove(45.0, divisions=2, dtype=torch.float64), wl)
        >>> r = ti.spectral.colorchecker(wl)[0][:8]
        >>> obs = layer(r, 2.0 * ti.spectral.illuminant(5000.0, wl))
        >>> est = estimate_illuminant(layer, r, obs, parametrisation="cct")
        >>> abs(float(est.cct) - 5000) < 5, abs(float(est.scale) - 2) < 1e-2
        (True, True)
    """
    if parametrisation not in IlluminantBasis.MODELS:
        raise ValueError(f"parametrisation must be one of {list(IlluminantBasis.MODELS)}; got {parametrisation!r}")
    if not (isinstance(init, (int, float)) and init > 0):
        raise ValueRangeError(f"init must be a temperature in K (> 0); got {init!r}")
    obs = observed_from(model, observed).detach()
    ill = IlluminantBasis(model.wavelengths, model=parametrisation).to(obs)
    batch = obs.shape[:-2]
    lo, hi = CCT_RANGE
    t0 = min(max(float(init), lo + 1.0), hi - 1.0)
    if parametrisation == "coefficients":
        theta0 = cct_to_daylight_coefficients(torch.tensor(t0, dtype=torch.float64)).to(obs).expand(*batch, 2)
    elif parametrisation == "cct":
        theta0 = torch.logit(torch.tensor((t0 - lo) / (hi - lo))).to(obs).expand(batch)
    else:
        theta0 = torch.tensor(math.log(float(init))).to(obs).expand(batch)

    def spectrum_of(theta: Tensor) -> Tensor:
        if parametrisation == "cct":
            return ill(lo + (hi - lo) * torch.sigmoid(theta))
        if parametrisation == "blackbody":
            return ill(torch.exp(theta))
        return ill(theta)

    dims = tuple(range(-2, 0))
    with torch.no_grad():
        pred = model(reflectance, spectrum_of(theta0))
        pred = pred[0] if isinstance(pred, tuple) else pred
        s0 = (pred * obs).sum(dims) / pred.pow(2).sum(dims).clamp_min(1e-300)
    theta = theta0.clone().requires_grad_(True)
    log_s = torch.log(s0.clamp_min(1e-30)).clone().requires_grad_(True)
    opt = torch.optim.LBFGS(
        [theta, log_s],
        lr=1.0,
        max_iter=steps,
        tolerance_grad=1e-12,
        tolerance_change=1e-15,
        line_search_fn="strong_wolfe",
    )
    norm = obs.pow(2).sum().clamp_min(1e-300)

    def closure() -> Tensor:
        opt.zero_grad()
        out = model(reflectance, spectrum_of(theta) * torch.exp(log_s)[..., None])
        out = out[0] if isinstance(out, tuple) else out
        loss = (out - obs).pow(2).sum() / norm
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        spec = spectrum_of(theta) * torch.exp(log_s)[..., None]
        out = model(reflectance, spec)
        out = out[0] if isinstance(out, tuple) else out
        if parametrisation == "cct":
            params = lo + (hi - lo) * torch.sigmoid(theta)
            cct = params
        elif parametrisation == "blackbody":
            params = torch.exp(theta)
            cct = params
        else:
            params = theta.detach().clone()
            cct = _nearest_cct(params)
    n_iter = int(opt.state[opt._params[0]].get("n_iter", steps))
    return IlluminantEstimate(spec, torch.exp(log_s).detach(), params.detach(), cct, rel_residual(out, obs), n_iter)
