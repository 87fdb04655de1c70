"""A trained illuminant estimator a user can apply: checkpoints with their configuration, and ``predict``.

Input rules (what the networks were trained on; :meth:`IlluminantEstimator.predict` checks what it can):

- **linear** RGB of the **training camera** (``config["camera"]``, by default the Nikon 5100 sensitivities of
  colour-science): raw values after black-level subtraction and demosaicking, before any white balance, colour
  matrix or gamma; an sRGB JPEG is none of these;
- any exposure (the image is divided by the 99th percentile of its brightest channel, so a few hot or saturated
  pixels do not move the estimate); saturated pixels should still be masked out (``mask``) if there are many;
- shape ``[B, 3, H, W]`` or ``[3, H, W]``, any size (the networks are fully convolutional; the generator's images
  are 64 × 64).

A checkpoint (:func:`save_estimator`) is one ``torch.save`` file holding ``{"format", "format_version",
"library_version", "config", "state_dict"}``; :func:`load_estimator` rebuilds the network from ``config`` and
refuses a file written by another library version (:class:`CheckpointError`), unless asked not to.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from .. import spectral
from .._version import __version__
from ..errors import ShapeError
from .models import FC4Net, PhysicsInformedNet

__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "IlluminantEstimator",
    "load_estimator",
    "make_network",
    "save_estimator",
]

#: The ``format`` field of a checkpoint, and its version.
CHECKPOINT_FORMAT = "torch_interreflect.illuminant_estimator"
FORMAT_VERSION = 1
#: File names :func:`load_estimator` tries, in order, when given a folder (``interreflect train-cc``'s output).
PREFERRED_FILES = ("physics.pt", "fc4_inf.pt", "fc4_b2.pt", "fc4_direct.pt", "model.pt")


class CheckpointError(ValueError):
    """A file that is not an estimator checkpoint of this library version."""


def make_network(config: dict[str, Any], illuminant_basis: tuple[Tensor, Tensor, Tensor] | None = None) -> nn.Module:
    """The (untrained) network a configuration describes.

    Args:
        config: ``{"kind": "fc4" | "physics", "width", "camera", "wavelengths": [start, stop, step],
            "illuminant_components", "reflectance_components"}`` (the last four for ``"physics"``).
        illuminant_basis: For ``"physics"``: the basis to use instead of fitting it.

    Raises:
        CheckpointError: an unknown kind.
    """
    kind = config.get("kind")
    if kind == "fc4":
        return FC4Net(int(config["width"]))
    if kind == "physics":
        wl = spectral.wavelengths(*config["wavelengths"], dtype=torch.float64)
        return PhysicsInformedNet(wl, config["camera"], width=int(config["width"]),
                                  reflectance_components=int(config.get("reflectance_components", 3)),
                                  illuminant_components=int(config.get("illuminant_components", 12)),
                                  illuminant_basis=illuminant_basis)
    raise CheckpointError(f"config kind must be 'fc4' or 'physics'; got {kind!r}")


class IlluminantEstimator(nn.Module):
    """A network and its configuration: ``predict(image, geometry=None) → unit-norm illuminant RGB [B, 3]``.

    Args:
        network: :class:`~.models.FC4Net` or :class:`~.models.PhysicsInformedNet`.
        config: What :func:`make_network` rebuilds it from, plus anything worth keeping (``"camera"`` is the
            training camera; ``"percentile"`` the input normalisation level).
    """

    def __init__(self, network: nn.Module, config: dict[str, Any]) -> None:
        super().__init__()
        self.network = network
        self.config = dict(config)

    @property
    def camera(self) -> str:
        """The camera whose linear RGB the model expects."""
        return str(self.config.get("camera", "Nikon 5100 (NPL)"))

    def forward(self, image: Tensor, mask: Tensor | None = None) -> Tensor:
        out = self.network(image, mask)
        return out["rgb"] if isinstance(out, dict) else out

    @torch.no_grad()
    def predict(
        self,
        image: Tensor,
        geometry: dict[str, Any] | list[dict[str, Any]] | None = None,
        *,
        mask: Tensor | None = None,
        bounces: int | None = None,
    ) -> Tensor:
        """Estimate the illuminant colour of linear camera-RGB images (see the module docstring for the rules).

        Without geometry the network answers. With geometry (per image, the dict of
        :func:`~.storage.load_geometry`: form factors, light factor, coverage, material index) its estimate is
        refined by analysis by synthesis through the interreflection model (:func:`~.refine.refine_illuminant`).

        Args:
            image: Linear RGB. Shape ``[B, 3, H, W]`` or ``[3, H, W]``.
            geometry: One dict per image (or one dict for a single image), or ``None``.
            mask: Pixels to use. Shape ``[B, H, W]`` or ``[H, W]``; default: all (with geometry: the pixels that
                see a facet).
            bounces: Light transport of the refinement: ``None`` (infinite), ``1`` (direct only) or ``2``.

        Returns:
            Unit-norm illuminant RGB in the training camera's space. Shape ``[B, 3]``.

        Raises:
            ShapeError: not ``[B, 3, H, W]`` / ``[3, H, W]``, or a mask / geometry that does not match.
            ValueError: non-finite values, or an all-zero image.
        """
        x, m = _check_image(image, mask)
        self.eval()
        geos = [geometry] if isinstance(geometry, dict) else geometry
        if geos is not None and len(geos) != x.shape[0]:
            raise ShapeError(f"geometry must hold one dict per image ({x.shape[0]}); got {len(geos)}")
        if geos is not None and m is None:
            m = torch.stack([g["background"].reshape(x.shape[-2:]) < 1.0 for g in geos])
        rgb = self(x, m)
        if geos is None:
            return rgb
        from .refine import refine_illuminant

        return torch.stack([refine_illuminant(self, x[b], geos[b], rgb[b], bounces=bounces).rgb.to(rgb)
                            for b in range(x.shape[0])])


def _check_image(image: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor | None]:
    if not isinstance(image, Tensor) or image.ndim not in (3, 4) or image.shape[-3] != 3:
        got = list(image.shape) if isinstance(image, Tensor) else type(image).__name__
        raise ShapeError(f"image must be linear RGB [B, 3, H, W] or [3, H, W] (channels first); got {got}")
    x = image[None] if image.ndim == 3 else image
    x = x if x.is_floating_point() else x.float()
    if not bool(torch.isfinite(x).all()):
        raise ValueError("image holds NaN or infinite values; mask them out or replace them before predicting")
    if bool((x.flatten(1).amax(1) <= 0).any()):
        raise ValueError("an image is all zero (or negative): nothing to estimate an illuminant from")
    x = x.clamp_min(0.0)  # noise below the black level
    if mask is None:
        return x, None
    m = mask[None] if mask.ndim == 2 else mask
    if m.shape != (x.shape[0], *x.shape[-2:]):
        raise ShapeError(f"mask must be [B, H, W] = {[x.shape[0], *x.shape[-2:]]}; got {list(mask.shape)}")
    return x, m.to(torch.bool)


def save_estimator(network: nn.Module, config: dict[str, Any], path: str | Path) -> None:
    """Save ``network`` (or an :class:`IlluminantEstimator`) with its configuration and the library version.

    Args:
        network: The network (its ``state_dict`` is saved).
        config: The :func:`make_network` configuration (JSON-able values).
        path: The file.
    """
    net = network.network if isinstance(network, IlluminantEstimator) else network
    net = net.module if hasattr(net, "module") else net
    torch.save({"format": CHECKPOINT_FORMAT, "format_version": FORMAT_VERSION, "library_version": __version__,
                "config": dict(config), "state_dict": net.state_dict()}, Path(path))


def _resolve(path: Path) -> Path:
    if path.is_dir():
        for name in PREFERRED_FILES:
            if (path / name).is_file():
                return path / name
        raise FileNotFoundError(f"{path} holds none of {', '.join(PREFERRED_FILES)}; pass a checkpoint file, or "
                                "the --out folder of `interreflect train-cc`")
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    return path


def load_estimator(
    path: str | Path, *, map_location: str | torch.device = "cpu", allow_version_mismatch: bool = False
) -> IlluminantEstimator:
    """Load a checkpoint of :func:`save_estimator` (a file, or a folder: its ``physics.pt``, else ``fc4_inf.pt``…).

    Args:
        path: The file or folder.
        map_location: Where the tensors go.
        allow_version_mismatch: Load a checkpoint of another library version anyway (its numbers may differ).

    Returns:
        The :class:`IlluminantEstimator`, in eval mode.

    Raises:
        FileNotFoundError: no such file (or no checkpoint in the folder).
        CheckpointError: not an estimator checkpoint (e.g. a bare ``state_dict`` of an earlier version), or one
            written by another library version.
    """
    file = _resolve(Path(path))
    try:
        ckpt = torch.load(file, map_location=map_location, weights_only=True)
    except Exception as exc:  # a truncated file, or not a torch file at all
        raise CheckpointError(f"{file} is not a readable torch checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{file} is not an illuminant-estimator checkpoint (a bare state_dict from an earlier "
                              "version?); retrain with `interreflect train-cc`, which saves the configuration too")
    version = ckpt.get("library_version")
    if version != __version__ and not allow_version_mismatch:
        raise CheckpointError(f"{file} was written by torch_interreflect {version}, this is {__version__}; retrain "
                              f"with this version, install {version}, or pass allow_version_mismatch=True")
    state = ckpt["state_dict"]
    basis = None
    if "ill_mean" in state:
        basis = (state["ill_mean"], state["ill_components"], state["ill_scale"])
    net = make_network(ckpt["config"], basis)
    net.load_state_dict(state)
    est = IlluminantEstimator(net, {**ckpt["config"], "library_version": version})
    return est.eval()
