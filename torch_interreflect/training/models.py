"""Illuminant-estimation networks: an FC4-style CNN and a physics-informed variant that re-renders its input.

- :class:`FC4Net`: a small fully convolutional network in the spirit of FC4 (Hu, Wang & Lin, CVPR 2017): every
  location predicts an illuminant colour and a confidence; the estimate is the confidence-weighted (softmax over
  locations) sum of the unit-norm local estimates.
- :class:`PhysicsInformedNet`: the same backbone predicts the illuminant as CIE daylight coefficients
  ``(M1, M2)`` (:class:`~torch_interreflect.layers.IlluminantBasis`, confidence-weighted pooling again) and
  per-pixel reflectance coefficients of a PCA basis (:class:`~torch_interreflect.layers.ReflectanceBasis`).
  :meth:`PhysicsInformedNet.rerender` pools the pixel coefficients onto the scene's facets (coverage-weighted
  mean), solves the infinite-bounce interreflection with the predicted illuminant spectrum
  (:func:`torch_interreflect.solve`, adjoint gradients) and projects camera RGB back to an image. The training
  loss (:func:`physics_loss`) adds the scale-invariant reconstruction error of that image to the angular error.

Both take linear camera RGB ``[B, 3, H, W]`` (any exposure: the input is divided by its maximum and gamma-encoded
inside) and return unit-norm illuminant RGB ``[B, 3]``.
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


def preprocess(image: Tensor) -> Tensor:
    """Scale each image to max 1 and gamma-encode (1/2.2): ``[B, 3, H, W]`` → ``[B, 3, H, W]`` in [0, 1]."""
    peak = image.detach().amax(dim=(1, 2, 3), keepdim=True).clamp_min(1e-12)
    return (image / peak).clamp(0.0, 1.0).add(1e-6).pow(1.0 / 2.2)


def _backbone(width: int) -> nn.Sequential:
    w = int(width)
    return nn.Sequential(
        nn.Conv2d(3, w, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(w, 2 * w, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(2 * w, 2 * w, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(2 * w, 2 * w, 3, padding=1), nn.ReLU(inplace=True),
    )


def _confidence_pool(values: Tensor, logits: Tensor) -> Tensor:
    """``Σ_x softmax(logits)_x values[:, :, x]``: ``[B, C, h, w]``, ``[B, h, w]`` → ``[B, C]``.

    The logits are squashed to (−15, 15) first: confidences then differ by at most e³⁰, and no weight underflows
    to a subnormal float (which makes CPU arithmetic many times slower).
    """
    w = torch.softmax(15.0 * torch.tanh(logits.flatten(1) / 15.0), dim=1)
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

    def forward(self, image: Tensor) -> Tensor:
        out = self.head(self.features(preprocess(image)))
        rgb = nnf.normalize(nnf.softplus(out[:, :3]) + 1e-4, dim=1)
        return nnf.normalize(_confidence_pool(rgb, out[:, 3]), dim=1)


class PhysicsInformedNet(nn.Module):
    """Illuminant (daylight basis) and per-pixel reflectance from an image, with a differentiable re-renderer.

    Args:
        wavelengths: Grid in nm (the generator's). Shape ``[L]``.
        camera: Camera sensitivities name (the generator's camera) or a :class:`~torch_interreflect.Camera`.
        width: Backbone width, as :class:`FC4Net`.
        reflectance_components: ``K`` of the reflectance PCA basis.
        tol: Relative residual of the interreflection solves in :meth:`rerender` (a training signal needs no
            more than a few digits).

    Shape:
        - Input: linear camera RGB ``[B, 3, H, W]``
        - Output of ``forward``: dict with ``"rgb"`` (unit-norm illuminant RGB ``[B, 3]``), ``"coefficients"``
          (daylight ``(M1, M2)`` ``[B, 2]``), ``"spectrum"`` (relative spectrum ``[B, L]``, 100 at 560 nm) and
          ``"reflectance_coefficients"`` (``[B, K, H, W]``).
    """

    #: ``(M1, M2) = centre + half_range · tanh(raw)``: a box around the daylight locus from 4000 K to 25 000 K
    #: (M1 in [−1.5, 2.9], M2 in [−0.7, 2.8] there).
    COEF_CENTRE = torch.tensor([0.7, 1.0])
    COEF_HALF_RANGE = torch.tensor([2.5, 2.0])

    def __init__(
        self,
        wavelengths: Tensor,
        camera: str | Camera = "Nikon 5100 (NPL)",
        *,
        width: int = 16,
        reflectance_components: int = 3,
        tol: float = 1e-4,
    ) -> None:
        from ..layers import IlluminantBasis, ReflectanceBasis

        super().__init__()
        self.tol = float(tol)
        wl = spectral.check_wavelengths(wavelengths, min_samples=2).to(torch.float64)
        if isinstance(camera, str):
            try:
                camera = Camera.from_colour(camera, wl)
            except ValueError:
                camera = Camera.from_colour(camera, wl, extrapolate="zero")
        self.camera = camera
        self.illuminant = IlluminantBasis(wl, model="coefficients")
        self.reflectance = ReflectanceBasis(wl, reflectance_components)
        self.features = _backbone(width)
        self.illum_head = nn.Conv2d(2 * width, 3, 1)  # (M1, M2, confidence) per location
        d65 = torch.tensor([-0.2937, -0.6891])  # cct_to_daylight_coefficients(6504 K)
        with torch.no_grad():
            self.illum_head.bias[:2].copy_(torch.atanh((d65 - self.COEF_CENTRE) / self.COEF_HALF_RANGE))
        k = int(reflectance_components)
        self.refl_head = nn.Sequential(
            nn.Conv2d(3 + 2 * width, 2 * width, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(2 * width, k, 1),
        )

    def illuminant_rgb(self, coefficients: Tensor) -> tuple[Tensor, Tensor]:
        """``(unit-norm camera RGB [B, 3], spectrum [B, L])`` of daylight coefficients ``[B, 2]``."""
        spd = self.illuminant(coefficients.to(self.illuminant.basis.dtype)).clamp_min(0.0)
        rgb = self.camera(spd[:, None, :] / math.pi)[:, 0]
        return nnf.normalize(rgb, dim=-1), spd

    def forward(self, image: Tensor) -> dict[str, Tensor]:
        x = preprocess(image)
        f = self.features(x)
        out = self.illum_head(f)
        raw = _confidence_pool(out[:, :2], out[:, 2])
        coef = self.COEF_CENTRE.to(raw) + self.COEF_HALF_RANGE.to(raw) * torch.tanh(raw)
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
