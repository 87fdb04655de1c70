"""Illuminant-estimation networks: an FC4-style CNN and a physics-informed variant that re-renders its input.

- :class:`FC4Net`: a small fully convolutional network in the spirit of FC4 (Hu, Wang & Lin, CVPR 2017): every
  location predicts an illuminant colour and a confidence; the estimate is the confidence-weighted (softmax over
  locations) sum of the unit-norm local estimates.
- :class:`PhysicsInformedNet`: the same backbone predicts the illuminant as codes of a non-negative spectral basis
  fitted to every common illuminant family (:func:`~torch_interreflect.spectral.illuminant_basis`: daylight,
  blackbody, fluorescent, LED, HID, measured lamps; confidence-weighted pooling again) and
  per-pixel reflectance coefficients of a PCA basis (:class:`~torch_interreflect.layers.ReflectanceBasis`).
  :meth:`PhysicsInformedNet.rerender` pools the pixel coefficients onto the scene's facets (coverage-weighted
  mean), solves the infinite-bounce interreflection with the predicted illuminant spectrum
  (:func:`torch_interreflect.solve`, adjoint gradients) and projects camera RGB back to an image. The training
  loss (:func:`physics_loss`) adds the scale-invariant reconstruction error of that image to the angular error.

Both take linear camera RGB ``[B, 3, H, W]`` of the training camera (any exposure: :func:`preprocess` divides by the
99th percentile of the brightest channel, clips and gamma-encodes inside) and an optional mask ``[B, H, W]`` of the
pixels to use, and return unit-norm illuminant RGB ``[B, 3]``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as nnf
from torch import Tensor, nn

from .. import spectral
from ..camera.sensor import Camera
from ..solver.api import radiance, solve
from .metrics import angular_error

__all__ = ["FC4Net", "PhysicsInformedNet", "physics_loss", "preprocess"]


def preprocess(image: Tensor, mask: Tensor | None = None, *, percentile: float = 99.0) -> Tensor:
    """Robust exposure normalisation and gamma: ``[B, 3, H, W]`` → ``[B, 3, H, W]`` in [0, 1].

    Each image is divided by the ``percentile``-th percentile of its pixels' brightest channel (over the ``mask``
    pixels when given; masked-out pixels are set to 0), clipped to [0, 1] and gamma-encoded (1/2.2). Unlike the
    maximum, a percentile is not moved by a few hot or saturated pixels (they are clipped to 1 instead).

    Args:
        image: Linear camera RGB, any exposure. Shape ``[B, 3, H, W]``.
        mask: Pixels to use. Shape ``[B, H, W]`` (bool), or ``None`` for all.
        percentile: The level mapped to 1, in (0, 100].
    """
    x = image.detach()
    peak_map = x.amax(dim=1).flatten(1)  # [B, HW]
    if mask is not None:
        m = mask.reshape(peak_map.shape).to(torch.bool)
        peak_map = torch.where(m, peak_map, torch.full_like(peak_map, float("nan")))
    q = torch.nanquantile(peak_map.double(), float(percentile) / 100.0, dim=1).to(image.dtype)
    q = torch.nan_to_num(q, nan=1.0).clamp_min(1e-12)[:, None, None, None]
    out = (image / q).clamp(0.0, 1.0)
    if mask is not None:
        out = out * mask.reshape(mask.shape[0], 1, *image.shape[-2:]).to(out.dtype)
    return out.add(1e-6).pow(1.0 / 2.2)


def _pool_mask(mask: Tensor | None, size: tuple[int, int]) -> Tensor | None:
    """``[B, H, W]`` → ``[B, h, w]``: True where any pixel of the cell is in the mask."""
    if mask is None:
        return None
    return nnf.adaptive_max_pool2d(mask[:, None].to(torch.float32), size)[:, 0] > 0


def _backbone(width: int) -> nn.Sequential:
    w = int(width)
    return nn.Sequential(
        nn.Conv2d(3, w, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(w, 2 * w, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(2 * w, 2 * w, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(2 * w, 2 * w, 3, padding=1), nn.ReLU(inplace=True),
    )


def _confidence_pool(values: Tensor, logits: Tensor, mask: Tensor | None = None) -> Tensor:
    """``Σ_x softmax(logits)_x values[:, :, x]``: ``[B, C, h, w]``, ``[B, h, w]`` → ``[B, C]``.

    The logits are squashed to (−15, 15) first: confidences then differ by at most e³⁰, and no weight underflows
    to a subnormal float (which makes CPU arithmetic many times slower). Cells outside ``mask`` ``[B, h, w]`` get
    no weight (unless a sample has no cell at all).
    """
    z = 15.0 * torch.tanh(logits.flatten(1) / 15.0)
    if mask is not None:
        m = mask.flatten(1)
        m = m | ~m.any(1, keepdim=True)
        z = z.masked_fill(~m, -1e4)
    w = torch.softmax(z, dim=1)
    return (values.flatten(2) * w[:, None, :]).sum(-1)


class FC4Net(nn.Module):
    """FC4-style illuminant estimator with confidence-weighted pooling.

    Args:
        width: Channels of the first layer (the backbone has ``width, 2·width, 2·width, 2·width``).

    Shape:
        - Input: linear camera RGB ``[B, 3, H, W]``
        - Output: unit-norm illuminant RGB ``[B, 3]``

    Example:
        >>> import torch
        >>> from torch_interreflect.training.models import FC4Net
        >>> FC4Net(8)(torch.rand(2, 3, 32, 32)).shape
        torch.Size([2, 3])
    """

    def __init__(self, width: int = 16) -> None:
        super().__init__()
        self.features = _backbone(width)
        self.head = nn.Conv2d(2 * width, 4, 1)

    def forward(self, image: Tensor, mask: Tensor | None = None) -> Tensor:
        out = self.head(self.features(preprocess(image, mask)))
        rgb = nnf.normalize(nnf.softplus(out[:, :3]) + 1e-4, dim=1)
        return nnf.normalize(_confidence_pool(rgb, out[:, 3], _pool_mask(mask, out.shape[-2:])), dim=1)


class PhysicsInformedNet(nn.Module):
    """Illuminant (any-illuminant basis) and per-pixel reflectance from an image, with a differentiable re-renderer.

    Args:
        wavelengths: Grid in nm (the generator's). Shape ``[L]``.
        camera: Camera sensitivities name (the generator's camera) or a :class:`~torch_interreflect.Camera`.
        width: Backbone width, as :class:`FC4Net`.
        reflectance_components: ``K`` of the reflectance PCA basis.
        illuminant_components: ``K`` of the illuminant basis (:func:`~torch_interreflect.spectral.illuminant_basis`,
            fitted to daylight, blackbodies, fluorescent, LED, HID and measured lamps; floors ≤ 0.07° at 12).
        tol: Relative residual of the interreflection solves in :meth:`rerender` (a training signal needs no
            more than a few digits).
        illuminant_basis: ``(mean, components, scale)`` to use instead of fitting the default (a checkpoint
            carries its own in the state dict).

    Shape:
        - Input: linear camera RGB ``[B, 3, H, W]``; optional mask ``[B, H, W]``
        - Output of ``forward``: dict with ``"rgb"`` (unit-norm illuminant RGB ``[B, 3]``), ``"coefficients"``
          (illuminant-basis codes ``[B, K]``), ``"spectrum"`` (relative spectrum ``[B, L]``, mean about 1) and
          ``"reflectance_coefficients"`` (``[B, K_r, H, W]``).
    """

    def __init__(
        self,
        wavelengths: Tensor,
        camera: str | Camera = "Nikon 5100 (NPL)",
        *,
        width: int = 16,
        reflectance_components: int = 3,
        illuminant_components: int = 12,
        tol: float = 1e-4,
        illuminant_basis: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> None:
        from ..layers import ReflectanceBasis

        super().__init__()
        self.tol = float(tol)
        wl = spectral.check_wavelengths(wavelengths, min_samples=2).to(torch.float64)
        camera_name = camera if isinstance(camera, str) else "Nikon 5100 (NPL)"
        if isinstance(camera, str):
            try:
                camera = Camera.from_colour(camera, wl)
            except ValueError:
                camera = Camera.from_colour(camera, wl, extrapolate="zero")
        self.camera = camera
        k_ill = int(illuminant_components)
        if illuminant_basis is None:
            illuminant_basis = spectral.illuminant_basis(wl, camera_name, k_ill)
        mean, comps, scale = (t.detach().to(torch.float64).clone() for t in illuminant_basis)
        k_ill = comps.shape[0]
        self.register_buffer("ill_mean", mean)
        self.register_buffer("ill_components", comps)
        self.register_buffer("ill_scale", scale)
        self.reflectance = ReflectanceBasis(wl, reflectance_components)
        self.features = _backbone(width)
        self.illum_head = nn.Conv2d(2 * width, k_ill + 1, 1)  # (codes, confidence) per location
        d65 = spectral.illuminant("D65", wl)[None]
        code = spectral.coefficients_from_illuminant(d65, (mean, comps, scale), camera.sensitivities.to(wl), wl)
        with torch.no_grad():
            self.illum_head.bias[:k_ill].copy_(code[0].to(self.illum_head.bias))
        k = int(reflectance_components)
        self.refl_head = nn.Sequential(
            nn.Conv2d(3 + 2 * width, 2 * width, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(2 * width, k, 1),
        )

    def illuminant_spectrum(self, coefficients: Tensor) -> Tensor:
        """Relative spectrum ``[B, L]`` (float64, non-negative) of basis codes ``[B, K]``."""
        return spectral.illuminant_from_coefficients(coefficients.to(torch.float64), self.ill_mean,
                                                     self.ill_components, self.ill_scale)

    def illuminant_rgb(self, coefficients: Tensor) -> tuple[Tensor, Tensor]:
        """``(unit-norm camera RGB [B, 3], spectrum [B, L])`` of basis codes ``[B, K]``."""
        spd = self.illuminant_spectrum(coefficients)
        rgb = self.camera(spd[:, None, :].to(self.camera.sensitivities.dtype) / math.pi)[:, 0]
        return nnf.normalize(rgb, dim=-1), spd

    def forward(self, image: Tensor, mask: Tensor | None = None) -> dict[str, Tensor]:
        x = preprocess(image, mask)
        f = self.features(x)
        out = self.illum_head(f)
        k = out.shape[1] - 1
        coef = _confidence_pool(out[:, :k], out[:, k], _pool_mask(mask, out.shape[-2:]))
        rgb, spd = self.illuminant_rgb(coef)
        up = nnf.interpolate(f, size=x.shape[-2:], mode="bilinear", align_corners=False)
        refl = self.refl_head(torch.cat([x, up], dim=1))
        return {"rgb": rgb.to(image.dtype), "coefficients": coef, "spectrum": spd, "reflectance_coefficients": refl}

    def rerender(self, outputs: dict[str, Tensor], geometry: list[dict[str, Any]]) -> Tensor:
        """Re-render each input from the predicted illuminant and reflectance with exact interreflection.

        Per sample: facet coefficients = coverage-weighted mean of the pixel coefficients (0, the basis mean, for
        facets no pixel sees); reflectance from the basis; ``E0 = g ⊗ spectrum``; ``E`` by
        :func:`torch_interreflect.solve` (infinite bounces); camera RGB of ``R E / π``; image =
        ``coverage @ rgb``. Differentiable in both predictions (adjoint of the solve).

        Args:
            outputs: The dict of :meth:`forward`.
            geometry: Per sample, the dict of :func:`~.generator.load_geometry` (float64).

        Returns:
            Re-rendered linear camera RGB, unknown overall scale. Shape ``[B, 3, H, W]`` (float64).
        """
        coefs = outputs["reflectance_coefficients"]
        b, k, h, w = coefs.shape
        images = []
        for i in range(b):
            geo = geometry[i]
            cov = geo["coverage"].to_dense() if geo["coverage"].layout != torch.strided else geo["coverage"]
            cov = cov.to(torch.float64)
            counts = cov.sum(0)
            pix = coefs[i].reshape(k, h * w).T.to(torch.float64)  # [HW, K]
            fc = (cov.T @ pix) / counts.clamp_min(1e-9)[:, None]
            fc = torch.where((counts > 1e-9)[:, None], fc, torch.zeros_like(fc))
            # reflectance from the basis, kept below 0.95 (as the generator's) so no enclosure traps the light
            r = self.reflectance(fc.to(self.reflectance.mean.dtype)).to(torch.float64).clamp(0.0, 0.95)  # [F, L]
            spd = outputs["spectrum"][i].to(torch.float64)
            e0 = geo["light_factor"].to(torch.float64)[:, None] * spd[None, :]
            E = solve(geo["form_factors"], r, e0, tol=self.tol)
            rgb = self.camera(radiance(E, r).to(self.camera.sensitivities.dtype)).to(torch.float64)  # [F, 3]
            images.append((cov @ rgb).T.reshape(3, h, w))
        return torch.stack(images)


def physics_loss(
    model: nn.Module,
    outputs: dict[str, Tensor],
    batch: dict[str, Any],
    *,
    weight: float = 10.0,
) -> tuple[Tensor, dict[str, float]]:
    """Angular error (degrees) plus ``weight`` × the scale-invariant reconstruction error of the re-rendering.

    The reconstruction error of sample ``b`` is ``min_s ‖s·Î_b − I_b‖² / ‖I_b‖²`` (``s`` in closed form), with
    ``Î`` from :meth:`PhysicsInformedNet.rerender` and ``I`` the input image.

    Args:
        model: The :class:`PhysicsInformedNet` (or a DistributedDataParallel wrapping one).
        outputs: Its ``forward`` outputs.
        batch: The batch (``image``, ``illuminant``, ``geometry``) from :func:`~.datasets.collate`.
        weight: Weight of the reconstruction term.

    Returns:
        ``(loss, {"angular": …, "reconstruction": …})``.
    """
    net = model.module if hasattr(model, "module") else model
    ang = angular_error(outputs["rgb"], batch["illuminant"]).mean()
    rendered = net.rerender(outputs, batch["geometry"])
    target = batch["image"].to(torch.float64)
    num = (rendered * target).flatten(1).sum(1)
    den = (rendered * rendered).flatten(1).sum(1).clamp_min(1e-30)
    s = num / den
    err = ((s[:, None, None, None] * rendered - target) ** 2).flatten(1).sum(1)
    rec = err / (target**2).flatten(1).sum(1).clamp_min(1e-30)
    rec = rec.mean().to(ang.dtype)
    return ang + weight * rec, {"angular": float(ang.detach()), "reconstruction": float(rec.detach())}
