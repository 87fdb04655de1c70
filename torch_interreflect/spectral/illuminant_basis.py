"""A non-negative spectral basis for any illuminant: daylight, blackbody, fluorescent, LED, HID and measured lamps.

The CIE daylight basis (:mod:`.illuminants`) cannot express a 2500 K blackbody or a fluorescent tube; this module
fits a small basis to a dense library of every common illuminant family (:func:`illuminant_library`) and decodes
coefficients to spectra that are never negative:

``S(c) = softplus(μ + (c ⊙ σ) Φ)``  (relative spectrum, mean about 1 over the grid)

with ``μ [L]``, ``Φ [K, L]`` and the coefficient scales ``σ [K]`` fitted jointly with one code per library spectrum
(:func:`fit_illuminant_basis`), so that the spectra re-render what a camera sees: the fit minimises the
scale-invariant error ``1 − cos²`` between the camera responses of a set of reflectances (white, and colour-science's
measured reflectances) under the decoded and under the true spectrum. :func:`coefficients_from_illuminant` fits the
code of any spectrum the same way; :func:`illuminant_basis` returns the (cached) basis for a grid and camera.

Representation floors of the default basis (12 components, Nikon 5100, 400–700 nm; ``benchmarks/colour_constancy.py
--floors`` measures them): the camera-RGB angular error of the white point is at most 0.1° for every family of
:func:`illuminant_library` (see the benchmark's table for the per-family numbers).

Units: nm; spectra are relative (their scale is irrelevant to colour constancy).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import Tensor

from ..errors import ShapeError
from .data import camera_sensitivities, illuminant
from .grid import check_wavelengths, grid_numpy, integration_weights
from .reflectances import reflectance_data

__all__ = [
    "ILLUMINANT_FAMILIES",
    "coefficients_from_illuminant",
    "fit_illuminant_basis",
    "illuminant_basis",
    "illuminant_from_coefficients",
    "illuminant_library",
]

#: Families of :func:`illuminant_library`, in order.
ILLUMINANT_FAMILIES: tuple[str, ...] = (
    "daylight", "blackbody", "F1-F12", "FL3.x", "LED", "HP", "other CIE", "measured lamps",
)


def _named(name: str, wl: Tensor) -> Tensor:
    return illuminant(name, wl, extrapolate="constant")


def _measured_lamps(wl: Tensor) -> list[tuple[str, Tensor]]:
    import colour

    from .data import sample_spd

    g = grid_numpy(wl)
    return [(k, torch.tensor(sample_spd(sd, g, "constant", k), dtype=wl.dtype, device=wl.device))
            for k, sd in colour.SDS_LIGHT_SOURCES.items()]


def illuminant_library(
    wavelengths: Tensor | Sequence[float] | np.ndarray,
    *,
    daylight_cct: tuple[float, float, float] = (4000.0, 25000.0, 100.0),
    blackbody_t: tuple[float, float, float] = (1500.0, 15000.0, 50.0),
) -> tuple[Tensor, list[str], list[str]]:
    """A dense library of illuminant spectra, each scaled to mean 1 over the grid.

    Families (:data:`ILLUMINANT_FAMILIES`): CIE daylight on ``daylight_cct`` (start, stop, step in K), blackbodies
    on ``blackbody_t``, CIE F1–F12, FL3.1–FL3.15, LED-B1…B5, BH1, RGB1, V1, V2, HP1–HP5, other CIE tables (A, B, C,
    E, ID50, ID65, ISO 7589) and colour-science's measured light sources (``colour.SDS_LIGHT_SOURCES``: 56 lamps,
    from sodium and mercury lamps to RGB LEDs). Tables are repeated outward beyond 380–780 nm; a spectrum that is
    zero on every grid point (a line lamp on a coarse grid) is left out.

    Args:
        wavelengths: Grid in nm. Shape ``[L]``.
        daylight_cct: ``(start, stop, step)`` in K, inside 4000–25000.
        blackbody_t: ``(start, stop, step)`` in K.

    Returns:
        ``(spectra [N, L], names [N], families [N])`` (spectra on the grid's dtype and device).
    """
    wl = check_wavelengths(wavelengths, min_samples=2)
    import colour

    out: list[tuple[str, str, Tensor]] = []
    for t in np.arange(daylight_cct[0], daylight_cct[1] + 1e-9, daylight_cct[2]):
        out.append(("daylight", f"D{t:.0f}K", illuminant(float(t), wl)))
    for t in np.arange(blackbody_t[0], blackbody_t[1] + 1e-9, blackbody_t[2]):
        out.append(("blackbody", f"blackbody:{t:.0f}", illuminant(f"blackbody:{float(t)!r}", wl)))
    for name in colour.SDS_ILLUMINANTS:
        if name.startswith("FL3."):
            fam = "FL3.x"
        elif name.startswith("FL"):
            fam = "F1-F12"
        elif name.startswith("LED"):
            fam = "LED"
        elif name.startswith("HP"):
            fam = "HP"
        elif name.startswith("D"):  # the daylight family covers D50 … D75
            continue
        else:
            fam = "other CIE"
        out.append((fam, name, _named(name, wl)))
    out += [("measured lamps", name, s) for name, s in _measured_lamps(wl)]
    out = [o for o in out if float(o[2].max()) > 0.0]  # a coarse grid can miss every line of a sodium lamp
    spectra = torch.stack([s for _, _, s in out])
    spectra = spectra / spectra.mean(-1, keepdim=True)
    return spectra, [n for _, n, _ in out], [f for f, _, _ in out]


def _response_matrix(sensitivities: Tensor, reflectances: Tensor, wl: Tensor) -> Tensor:
    """``A [3·J, L]``: the camera responses of ``J`` reflectances (white first) are ``A @ spectrum``."""
    kernel = sensitivities * integration_weights(wl).to(sensitivities)  # [3, L]
    white = torch.ones(1, kernel.shape[-1], dtype=kernel.dtype, device=kernel.device)
    refl = torch.cat([white, reflectances.to(kernel)])
    a = (refl[:, None, :] * kernel[None]).reshape(-1, kernel.shape[-1])
    return a / a.norm()


def _cos2_loss(decoded: Tensor, target: Tensor, a: Tensor) -> Tensor:
    """Per spectrum ``1 − cos²`` between the stacked camera responses ``a @ decoded`` and ``a @ target``."""
    p, q = decoded @ a.T, target @ a.T
    return 1.0 - (p * q).sum(-1) ** 2 / ((p * p).sum(-1) * (q * q).sum(-1)).clamp_min(1e-300)


def illuminant_from_coefficients(coefficients: Tensor, mean: Tensor, components: Tensor, scale: Tensor) -> Tensor:
    """Decode ``S(c) = softplus(μ + (c ⊙ σ) Φ)`` (non-negative, differentiable).

    Args:
        coefficients: ``c``. Shape ``[..., K]``.
        mean: ``μ``. Shape ``[L]``.
        components: ``Φ``. Shape ``[K, L]``.
        scale: ``σ`` (so that fitted codes are of order 1). Shape ``[K]``.

    Returns:
        Relative spectrum. Shape ``[..., L]``.

    Raises:
        ShapeError: mismatched shapes.
    """
    k = components.shape[0]
    if coefficients.shape[-1] != k or mean.shape[-1] != components.shape[-1] or scale.shape != (k,):
        raise ShapeError(f"coefficients [..., K], mean [L], components [K, L] and scale [K] must agree; got "
                         f"{list(coefficients.shape)}, {list(mean.shape)}, {list(components.shape)}, "
                         f"{list(scale.shape)}")
    dt = torch.promote_types(coefficients.dtype, components.dtype)
    z = mean.to(dt) + (coefficients.to(dt) * scale.to(dt)) @ components.to(dt)
    return nnf.softplus(z)


def fit_illuminant_basis(
    spectra: Tensor,
    num_components: int,
    sensitivities: Tensor,
    wavelengths: Tensor,
    *,
    reflectances: Tensor | None = None,
    weights: Tensor | None = None,
    steps: int = 1500,
    lr: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor]:
    """Fit ``(μ, Φ, σ)`` of :func:`illuminant_from_coefficients` to ``spectra`` (see the module docstring).

    Starts from a weighted PCA (mean and the first ``K`` right singular vectors, times 3) and runs Adam on
    ``μ``, ``Φ`` and one code per spectrum, minimising the weighted mean of the scale-invariant response error.
    Deterministic on a given machine (no random initialisation).

    Args:
        spectra: Training spectra, any scale. Shape ``[N, L]``.
        num_components: ``K``.
        sensitivities: Camera sensitivities. Shape ``[3, L]``.
        wavelengths: Grid in nm. Shape ``[L]``.
        reflectances: Surfaces whose responses the metric uses besides white (default: every third of
            :func:`~.reflectances.reflectance_data`). Shape ``[J, L]``.
        weights: Weight of each spectrum (default uniform). Shape ``[N]``.
        steps: Adam iterations.
        lr: Adam learning rate.

    Returns:
        ``(mean [L], components [K, L], scale [K])`` in float64.
    """
    wl = check_wavelengths(wavelengths, min_samples=2).to(torch.float64)
    x = spectra.detach().to(torch.float64)
    x = x / x.mean(-1, keepdim=True).clamp_min(1e-300)
    if reflectances is None:
        reflectances = reflectance_data(wl)[::3]
    a = _response_matrix(sensitivities.detach().to(torch.float64), reflectances.detach(), wl)
    w = torch.ones(x.shape[0], dtype=torch.float64) if weights is None else weights.detach().to(torch.float64)
    w = w / w.sum()
    mu0 = (w[:, None] * x).sum(0)
    _, _, vt = torch.linalg.svd((x - mu0) * w.sqrt()[:, None], full_matrices=False)
    k = int(num_components)
    mu = (3.0 * mu0).requires_grad_(True)
    comps = vt[:k].clone().requires_grad_(True)
    codes = (3.0 * (x - mu0) @ vt[:k].T).requires_grad_(True)
    ones = torch.ones(k, dtype=torch.float64)
    opt = torch.optim.Adam([mu, comps, codes], lr=lr)
    for _ in range(int(steps)):
        loss = (w * _cos2_loss(illuminant_from_coefficients(codes, mu, comps, ones), x, a)).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    scale = codes.detach().std(0).clamp_min(1e-12)
    return mu.detach(), comps.detach(), scale


def coefficients_from_illuminant(
    spectra: Tensor,
    basis: tuple[Tensor, Tensor, Tensor],
    sensitivities: Tensor,
    wavelengths: Tensor,
    *,
    reflectances: Tensor | None = None,
    steps: int = 300,
) -> Tensor:
    """The codes that best re-render ``spectra`` (same metric as :func:`fit_illuminant_basis`; L-BFGS from 0).

    Args:
        spectra: Spectra, any scale. Shape ``[N, L]``.
        basis: ``(mean, components, scale)``.
        sensitivities: Camera sensitivities. Shape ``[3, L]``.
        wavelengths: Grid in nm. Shape ``[L]``.
        reflectances: As :func:`fit_illuminant_basis`.
        steps: L-BFGS iterations.

    Returns:
        Codes. Shape ``[N, K]`` (float64).
    """
    wl = check_wavelengths(wavelengths, min_samples=2).to(torch.float64)
    mean, comps, scale = (t.detach().to(torch.float64) for t in basis)
    x = spectra.detach().to(torch.float64)
    x = x / x.mean(-1, keepdim=True).clamp_min(1e-300)
    if reflectances is None:
        reflectances = reflectance_data(wl)[::3]
    a = _response_matrix(sensitivities.detach().to(torch.float64), reflectances.detach(), wl)
    codes = torch.zeros(x.shape[0], comps.shape[0], dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([codes], lr=1.0, max_iter=int(steps), tolerance_grad=1e-14, tolerance_change=1e-16,
                            line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = _cos2_loss(illuminant_from_coefficients(codes, mean, comps, scale), x, a).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return codes.detach()


@functools.lru_cache(maxsize=8)
def _basis_cached(grid: tuple[float, ...], camera: str, k: int) -> tuple[Tensor, Tensor, Tensor]:
    wl = torch.tensor(grid, dtype=torch.float64)
    try:
        sens = camera_sensitivities(camera, wl)
    except ValueError:
        sens = camera_sensitivities(camera, wl, extrapolate="zero")
    spectra, _, fams = illuminant_library(wl)
    counts = {f: fams.count(f) for f in set(fams)}
    w = torch.tensor([1.0 / counts[f] for f in fams], dtype=torch.float64)  # each family weighs the same
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is fastest, and the result does not depend on the machine
    try:
        return fit_illuminant_basis(spectra, k, sens, wl, weights=w)
    finally:
        torch.set_num_threads(threads)


def illuminant_basis(
    wavelengths: Tensor | Sequence[float] | np.ndarray,
    camera: str = "Nikon 5100 (NPL)",
    num_components: int = 12,
) -> tuple[Tensor, Tensor, Tensor]:
    """The basis fitted to :func:`illuminant_library` (families weighted equally) for a grid and camera.

    Fitted on first use (a few seconds) and cached per ``(grid, camera, K)``.

    Args:
        wavelengths: Grid in nm. Shape ``[L]``.
        camera: Camera (or observer) name of :func:`~.data.camera_sensitivities`.
        num_components: ``K``.

    Returns:
        ``(mean [L], components [K, L], scale [K])`` on the grid's dtype and device (fresh tensors).

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> mean, comps, scale = spectral.illuminant_basis(spectral.wavelengths(400, 700, 20))
        >>> comps.shape
        torch.Size([12, 16])
    """
    wl = check_wavelengths(wavelengths, min_samples=2)
    grid = tuple(grid_numpy(wl).tolist())
    out = _basis_cached(grid, camera, int(num_components))
    return tuple(t.to(dtype=wl.dtype if wl.is_floating_point() else torch.get_default_dtype(), device=wl.device)
                 for t in out)  # type: ignore[return-value]
