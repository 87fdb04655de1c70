"""Inverse tools with known geometry: recover reflectance or illuminant, remove interreflections, recolour.

Notation (DESIGN.md §1): ``E = E0 + F B`` with radiosity ``B = R E = π L``; camera RGB ``ρ = camera(L)``.

**Reflectance from spectral radiance (exact).** With ``B = π L`` observed on every facet, the irradiance is
``E = E0 + F B`` (one product), so ``R = B / (E0 + F B)`` per facet and wavelength (:func:`reflectance_from_radiance`).
No solve is needed.

**Reflectance from camera RGB (least squares).** With reflectance in a linear basis, ``r_f = m + c_f P``, the camera
response ``ρ_f = K (r_f ⊙ E_f)`` (``K = C Δλ / π``) is linear in ``c_f`` *for a given irradiance* ``E_f``. The
``"alternating"`` method solves the small per-facet least-squares problems for ``c`` with ``E`` fixed (starting from
``E = E0``, which is the estimate that ignores interreflection), then updates ``E = solve(F, R, E0)``, and repeats
to a fixed point; with ``bounces=1`` (interreflection not modelled) it stops after the first step. The
``"gradient"`` method minimises the relative squared RGB error through the differentiable renderer with L-BFGS
(any basis, e.g. the sigmoid one), starting from the alternating solution.

**Interreflection removal.** The one-bounce (direct-only) radiosity is ``B1 = R E0``. From ``E = E0 + F B`` and
``R = B / E``: ``B1 = R (E − F B) = B − R F B = B · E0 / (E0 + F B)``. This is the cancellation idea of Seitz et al.
(2005), ``B1 = (I − R F) B``, with the unknown reflectance eliminated by the known light, exact per wavelength
(:func:`remove_interreflections` with spectral radiance). From camera RGB the same formula applied per channel
(``E0`` replaced by its camera response) is exact only for narrow-band channels; the ``basis`` option instead
recovers reflectances in a basis (above) and renders ``R E0``, exact when the true reflectances lie in the basis.

**Illuminant estimation.** :func:`estimate_illuminant` fits an illuminant model (CIE daylight by ``M1, M2`` or by
CCT, or a blackbody) and a scale to observed RGB by L-BFGS through the renderer.

**Recolouring.** :func:`recolor` changes the reflectance of some facets and re-solves: the colour bleeding onto
every other facet follows. With an ``observed`` image, the *change* predicted by the model is added to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..camera.facet_rgb import facet_rgb as render
from ..camera.sensor import Camera
from ..errors import ShapeError, ValueRangeError
from ..formfactors.operator import FormFactors
from ..layers.illuminant import IlluminantBasis
from ..layers.interreflection import Interreflection
from ..layers.reflectance import RGBToSpectrum
from ..solver.api import radiance as _radiance
from ..solver.api import solve as _solve
from ..spectral.illuminants import CCT_RANGE, cct_to_daylight_coefficients

__all__ = [
    "IlluminantEstimate",
    "Recolored",
    "ReflectanceEstimate",
    "estimate_illuminant",
    "estimate_reflectance",
    "recolor",
    "reflectance_from_radiance",
    "remove_interreflections",
]


# ------------------------------------------------------------------------------------------------ helpers
def _check_ff(form_factors: Any) -> FormFactors:
    if not isinstance(form_factors, FormFactors):
        raise TypeError(f"form_factors must be a FormFactors; got {type(form_factors).__name__}")
    return form_factors


def _check_facets(t: Any, name: str, n: int, last: int | None, what: str) -> Tensor:
    if not isinstance(t, Tensor) or not t.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor {what}; got {type(t).__name__}")
    if t.ndim < 2 or t.shape[-2] != n or (last is not None and t.shape[-1] != last):
        raise ShapeError(f"{name} must have shape {what} with F = {n}" + (f", last = {last}" if last else "")
                         + f"; got {list(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueRangeError(f"{name} must be finite; got NaN or inf")
    return t


def _safe_div(num: Tensor, den: Tensor) -> Tensor:
    ok = den > 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _fmatmul(ff: FormFactors, x: Tensor) -> Tensor:
    return ff.to(x.dtype).matmul(x) if ff.dtype != x.dtype else ff.matmul(x)


# ------------------------------------------------------------------------------------- exact spectral tools
def reflectance_from_radiance(form_factors: FormFactors, radiance: Tensor, E0: Tensor) -> Tensor:
    """Exact reflectance from observed spectral radiance: ``R = B / (E0 + F B)`` with ``B = π L``.

    Facets with zero irradiance ``E0 + F B`` get reflectance 0 (undetermined). Differentiable.

    Args:
        form_factors: The scene's form factors ``[F, F]``.
        radiance: Observed radiance in W·sr⁻¹·m⁻²·nm⁻¹ of every facet. Shape ``[..., F, L]``.
        E0: Direct irradiance in W·m⁻²·nm⁻¹, broadcastable. Shape ``[..., F, L]``.

    Returns:
        Reflectance. Shape ``[..., F, L]``.

    Raises:
        ShapeError, ValueRangeError: bad shapes, non-finite or negative values.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.solver import solve, radiance
        >>> from torch_interreflect.inverse import reflectance_from_radiance
        >>> K = ti.form_factors(ti.scenes.v_groove(45.0, divisions=2))
        >>> r = torch.rand(8, 31, dtype=torch.float64); E0 = torch.ones(8, 31, dtype=torch.float64)
        >>> L = radiance(solve(K.to(torch.float64), r, E0), r)
        >>> bool(torch.allclose(reflectance_from_radiance(K, L, E0), r))
        True
    """
    ff = _check_ff(form_factors)
    n = ff.num_facets
    radiance = _check_facets(radiance, "radiance", n, None, "[..., F, L]")
    E0 = _check_facets(E0, "E0", n, None, "[..., F, L]")
    if bool((radiance.detach() < 0).any()) or bool((E0.detach() < 0).any()):
        raise ValueRangeError("radiance and E0 must be non-negative")
    B = math.pi * radiance
    return _safe_div(B, E0 + _fmatmul(ff, B))


def _camera_kernel(camera: Camera, like: Tensor) -> Tensor:
    """``K [C, L] = C(λ) Δλ / π`` so that ``rgb = (r ⊙ E) @ Kᵀ``."""
    return (camera.sensitivities * camera.weights / math.pi).to(device=like.device, dtype=like.dtype)


# ---------------------------------------------------------------------------------------- reflectance (RGB)
@dataclass
class ReflectanceEstimate:
    """Result of :func:`estimate_reflectance`.

    Attributes:
        reflectance: Recovered reflectance ``[..., F, L]`` in [0, 1].
        coefficients: Basis coefficients ``[..., F, K]`` (None for spectral observations).
        iterations: Alternating iterations (or L-BFGS steps) used.
        residual: Relative RMS RGB (or radiance) residual of the re-rendered estimate.
        converged: Whether the fixed point / optimiser met its tolerance.
    """

    reflectance: Tensor
    coefficients: Tensor | None
    iterations: int
    residual: float
    converged: bool
    info: dict[str, Any] = field(default_factory=dict)


def _basis_parts(basis: Any, like: Tensor) -> tuple[Tensor, Tensor, str]:
    mean, comps = getattr(basis, "mean", None), getattr(basis, "components", None)
    if not isinstance(mean, Tensor) or not isinstance(comps, Tensor):
        raise TypeError(
            "basis must expose tensors `mean` [L] and `components` [K, L] (ReflectanceBasis, RGBToSpectrum); got "
            f"{type(basis).__name__}"
        )
    return mean.to(like), comps.to(like), getattr(basis, "space", "linear")


def _alternating(
    ff: FormFactors,
    camera: Camera,
    observed: Tensor,
    E0: Tensor,
    mean: Tensor,
    comps: Tensor,
    *,
    bounces: int | None,
    max_iter: int,
    tol: float | None,
) -> tuple[Tensor, Tensor, int, bool]:
    """Fixed point: least-squares coefficients for fixed E, then E = solve(F, R, E0)."""
    if tol is None:
        tol = 1e-9 if observed.dtype == torch.float64 else 1e-5
    kern = _camera_kernel(camera, observed)  # [C, L]
    shape = torch.broadcast_shapes(observed.shape[:-1], E0.shape[:-1])
    obs = observed.expand(*shape, observed.shape[-1])
    E = E0.expand(*shape, E0.shape[-1])
    r_prev: Tensor | None = None
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        ke = kern * E[..., None, :]  # [..., F, C, L]
        A = ke @ comps.T  # [..., F, C, K]
        b = obs - ke @ mean  # [..., F, C]
        c = torch.linalg.lstsq(A, b[..., None], driver="gelsd" if A.device.type == "cpu" else None).solution[..., 0]
        r = (mean + c @ comps).clamp(0.0, 1.0)
        if bounces == 1:
            converged = True
            break
        if r_prev is not None and float((r - r_prev).abs().max()) <= tol:
            converged = True
            break
        r_prev = r
        if bounces is None:
            # E ← E0 + F (r ⊙ E): the radiosity r ⊙ E already matches the observation through the camera, so this
            # converges much faster than re-solving with the current r (same fixed point, E = E0 + F R E)
            E = E0 + _fmatmul(ff, r * E)
        else:
            E = _solve(ff, r, E0, bounces=bounces, tol=max(0.1 * tol, 1e-14)).expand(*shape, E0.shape[-1])
    return r, c, it, converged


def _observed_from(model: Interreflection, observed: Tensor) -> Tensor:
    return _check_facets(observed, "observed", model.num_facets, model.camera.num_channels, "[..., F, C]")


def _e0_from(model: Interreflection, illuminant: Tensor | None, E0: Tensor | None) -> Tensor:
    if (illuminant is None) == (E0 is None):
        raise ValueError("give exactly one of illuminant (a spectrum [..., L]) and E0 ([..., F, L])")
    if E0 is not None:
        return _check_facets(E0, "E0", model.num_facets, model.num_wavelengths, "[..., F, L]")
    return model.direct(illuminant)


def _rel_residual(pred: Tensor, obs: Tensor) -> float:
    return float((pred - obs).norm() / obs.norm().clamp_min(1e-300))


def estimate_reflectance(
    model: Interreflection | FormFactors,
    observed: Tensor,
    illuminant: Tensor | None = None,
    *,
    E0: Tensor | None = None,
    basis: Any = None,
    bounces: int | str | None = "model",
    method: str = "alternating",
    max_iter: int = 100,
    tol: float | None = None,
    steps: int = 50,
) -> ReflectanceEstimate:
    """Recover per-facet reflectance from observations, with known geometry and light.

    Two cases (module docstring):

    - ``model`` is a :class:`~torch_interreflect.FormFactors` and ``observed`` is spectral radiance
      ``[..., F, L]``: exact, ``R = B / (E0 + F B)`` (``E0`` required).
    - ``model`` is an :class:`~torch_interreflect.layers.Interreflection` and ``observed`` camera RGB
      ``[..., F, 3]``: reflectance in a linear ``basis`` by alternating least squares (``method="alternating"``)
      or, in addition, L-BFGS through the renderer (``method="gradient"``; works with non-linear bases).

    Args:
        model: Form factors (spectral case) or the renderer (RGB case: its form factors, camera, light).
        observed: Radiance ``[..., F, L]`` or camera RGB ``[..., F, C]`` of every facet.
        illuminant: Spectrum ``[..., L]`` turned into ``E0`` by the model's light (RGB case).
        E0: Direct irradiance ``[..., F, L]`` (instead of ``illuminant``; required in the spectral case).
        basis: Reflectance basis with ``mean [L]``, ``components [K, L]`` (and ``forward`` for the gradient
            method): :class:`~torch_interreflect.layers.ReflectanceBasis` (``space="linear"`` for alternating) or
            :class:`~torch_interreflect.layers.RGBToSpectrum` (default). ``K ≤ 3`` makes the per-facet problems
            determined.
        bounces: Interreflection model used for the inversion: ``"model"`` (the renderer's), ``None`` (infinite),
            or ``n`` (``1`` = ignore interreflection).
        method: ``"alternating"`` or ``"gradient"``.
        max_iter: Alternating iterations at most.
        tol: Stop when the reflectance changes by at most ``tol`` (alternating); default 1e-9 in float64,
            1e-5 in float32.
        steps: L-BFGS iterations (gradient).

    Returns:
        A :class:`ReflectanceEstimate`.

    Raises:
        ShapeError, ValueRangeError, TypeError: bad inputs; ValueError: unknown method, missing light.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.layers import Interreflection, RGBToSpectrum
        >>> from torch_interreflect.inverse import estimate_reflectance
        >>> wl = ti.spectral.wavelengths(dtype=torch.float64)
        >>> up = RGBToSpectrum(wl)
        >>> layer = Interreflection(ti.scenes.v_groove(45.0, divisions=2, dtype=torch.float64), wl)
        >>> r_true = up(torch.rand(8, 3, dtype=torch.float64) * 0.9)
        >>> D65 = ti.spectral.illuminant("D65", wl)
        >>> est = estimate_reflectance(layer, layer(r_true, D65), D65, basis=up)
        >>> bool((est.reflectance - r_true).abs().max() < 1e-6)
        True
    """
    if isinstance(model, FormFactors):
        if E0 is None:
            raise ValueError("the spectral case (model = FormFactors) needs E0 [..., F, L]")
        r = reflectance_from_radiance(model, observed, E0)
        with torch.no_grad():
            res = _rel_residual(_radiance(_solve(model, r.clamp(0, 1), E0), r.clamp(0, 1)), observed)
        return ReflectanceEstimate(r, None, 0, res, True)
    if not isinstance(model, Interreflection):
        raise TypeError(f"model must be an Interreflection layer or FormFactors; got {type(model).__name__}")
    if method not in ("alternating", "gradient"):
        raise ValueError(f"method must be 'alternating' or 'gradient'; got {method!r}")
    obs = _observed_from(model, observed)
    e0 = _e0_from(model, illuminant, E0).to(obs)
    if bounces == "model":
        bounces = model.bounces
    if basis is None:
        basis = RGBToSpectrum(model.wavelengths).to(obs)
    mean, comps, space = _basis_parts(basis, obs)
    ff = model.form_factors
    with torch.no_grad():
        if space == "linear":
            r, c, it, conv = _alternating(
                ff, model.camera, obs.detach(), e0.detach(), mean, comps, bounces=bounces, max_iter=max_iter, tol=tol
            )
        else:  # a non-linear basis: start from the mean spectrum
            c = torch.zeros(*torch.broadcast_shapes(obs.shape[:-1], e0.shape[:-1]), comps.shape[0]).to(obs)
            r, it, conv = basis(c), 0, False
    if method == "gradient":
        c = c.detach().clone().requires_grad_(True)
        opt = torch.optim.LBFGS([c], lr=1.0, max_iter=steps, tolerance_grad=1e-12, tolerance_change=1e-14,
                                line_search_fn="strong_wolfe")
        scale = obs.detach().pow(2).sum().clamp_min(1e-300)

        def closure() -> Tensor:
            opt.zero_grad()
            pred = render(ff, basis(c), e0, model.camera, bounces=bounces, tol=model.tol)
            loss = (pred - obs.detach()).pow(2).sum() / scale
            loss.backward()
            return loss

        opt.step(closure)
        c = c.detach()
        r = basis(c).detach()
        it = int(opt.state[opt._params[0]].get("n_iter", steps))
        conv = True
    with torch.no_grad():
        pred = render(ff, r, e0, model.camera, bounces=bounces, tol=model.tol)
    return ReflectanceEstimate(r, c, it, _rel_residual(pred, obs), conv, {"method": method, "bounces": bounces})


# ------------------------------------------------------------------------------------ interreflection removal
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
    ff = _check_ff(form_factors)
    n = ff.num_facets
    E0 = _check_facets(E0, "E0", n, None, "[..., F, L]")
    if camera is None:
        observed = _check_facets(observed, "observed", n, E0.shape[-1], "[..., F, L] (spectral radiance)")
        B = math.pi * observed
        return observed * _safe_div(E0, E0 + _fmatmul(ff, B))
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera; got {type(camera).__name__}")
    observed = _check_facets(observed, "observed", n, camera.num_channels, "[..., F, C] (camera RGB)")
    if basis is None:
        e0c = camera(E0).to(observed)  # camera response of the irradiance (π × that of a white diffuser)
        B = math.pi * observed
        return observed * _safe_div(e0c, e0c + _fmatmul(ff, B))
    mean, comps, space = _basis_parts(basis, observed)
    if space != "linear":
        raise ValueError("remove_interreflections needs a linear basis (space='linear')")
    with torch.no_grad():
        r, _, _, _ = _alternating(ff, camera, observed, E0.to(observed), mean, comps, bounces=None,
                                  max_iter=max_iter, tol=tol)
    return camera(_radiance(E0.to(observed), r))


# ---------------------------------------------------------------------------------------------- illuminant
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
    obs = _observed_from(model, observed).detach()
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
    opt = torch.optim.LBFGS([theta, log_s], lr=1.0, max_iter=steps, tolerance_grad=1e-12, tolerance_change=1e-15,
                            line_search_fn="strong_wolfe")
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
    return IlluminantEstimate(spec, torch.exp(log_s).detach(), params.detach(), cct, _rel_residual(out, obs), n_iter)


# ---------------------------------------------------------------------------------------------- recolouring
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
    e0 = _e0_from(model, illuminant, E0)
    bounces, tol = model.bounces, model.tol
    rgb_old = render(model.form_factors, r, e0, model.camera, bounces=bounces, tol=tol)
    rgb_new = render(model.form_factors, r_new, e0, model.camera, bounces=bounces, tol=tol)
    change = rgb_new - rgb_old
    if observed is not None:
        obs = _observed_from(model, observed)
        rgb_new = obs + change
    image = None
    if model.projection is not None:
        image = model.projection(rgb_new.reshape(-1, *rgb_new.shape[-2:]))
    return Recolored(r_new, rgb_new, image, change)
