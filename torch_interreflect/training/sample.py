"""Render one sample in memory: :func:`render_sample` (deterministic per ``(config.seed, index)``).

Everything random in sample ``i`` comes from ``numpy.random.default_rng([seed, i])``; rendering runs in float64
(on one torch thread when the caller pins it, as :func:`~.generator.generate` does), so the same configuration
gives the same arrays whatever the sharding or the order.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import spectral
from .._version import __version__
from ..camera.gather import gather_operator, gathered_image, mix_direct, source_irradiance
from ..camera.projection import project
from ..camera.sensor import Camera
from ..camera.view import View
from ..errors import SpectralDataError
from ..formfactors.quadrature import form_factors
from ..geometry.contacts import split_at_contacts
from ..solver.api import radiance, solve
from ..spectral.reflectances import fit_reflectance_basis, reflectance_data
from .config import GeneratorConfig, sample_files, variant_suffix
from .random_scenes import random_illuminant, random_light, random_reflectances, random_scene, random_view

__all__ = ["Sample", "load_resources", "render_sample"]


@dataclasses.dataclass
class Sample:
    """One rendered sample (in memory).

    Attributes:
        index: Sample index.
        images: Linear camera RGB times ``exposure`` per variant (``None`` = infinite bounces), float32
            ``[H, W, 3]``.
        metadata: The JSON sidecar's content.
        geometry: Arrays of the ``_geometry.npz`` file (see :func:`load_geometry`).
    """

    index: int
    images: dict[int | None, np.ndarray]
    metadata: dict[str, Any]
    geometry: dict[str, np.ndarray]


@functools.lru_cache(maxsize=4)
def _cached_resources(wl_spec: tuple[float, float, float], camera: str, k: int) -> dict[str, Any]:
    wl = spectral.wavelengths(*wl_spec, dtype=torch.float64)
    try:
        cam = Camera.from_colour(camera, wl)
    except SpectralDataError:  # e.g. the Sigma data end at 680 nm; an unknown name raises again, naming the choices
        cam = Camera.from_colour(camera, wl, extrapolate="zero")
    data = reflectance_data(wl)
    mean, comps = fit_reflectance_basis(data, k)
    sigma = ((data - mean) @ comps.T).std(0)
    return {"wl": wl, "camera": cam, "data": data, "basis": (mean, comps, sigma)}


def load_resources(config: GeneratorConfig) -> dict[str, Any]:
    """The wavelength grid, camera, reflectance data and PCA basis of ``config`` (cached; shared, do not modify).

    Also the check that the configuration can render at all (an unknown camera fails here, before anything is
    written).

    Returns:
        ``{"wl": [L], "camera": Camera, "data": [N, L], "basis": (mean [L], components [K, L], sigma [K])}``.

    Raises:
        SpectralDataError: an unknown camera name (the message lists the available ones).
    """
    return _cached_resources(config.wavelengths, config.camera, config.basis_components)


def _r(x: float, digits: int = 8) -> float:
    return float(f"{float(x):.{digits}g}")


def _round_tree(x: Any) -> Any:
    if isinstance(x, float):
        return _r(x)
    if isinstance(x, dict):
        return {k: _round_tree(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round_tree(v) for v in x]
    return x


@dataclasses.dataclass
class _Drawn:
    """What one sample drew: scene, form factors, materials, illuminant, light and view."""

    scene: Any
    K: Any
    names: list[str]
    material: Tensor
    refl: Tensor
    spd: Tensor
    g: Tensor
    view: dict[str, Any]
    params: dict[str, Any]


def _draw(config: GeneratorConfig, index: int, res: dict[str, Any]) -> _Drawn:
    rng = np.random.default_rng([config.seed, index])
    scene, scene_params = random_scene(rng, config.scenes)
    if config.split_contacts:
        scene = split_at_contacts(scene)[0]  # draws nothing: the random numbers below stay the same
    K = form_factors(scene)
    names = scene.material_names or ["all"]
    material = scene.material if scene.material is not None else torch.zeros(scene.num_facets, dtype=torch.long)
    refl, refl_params = random_reflectances(rng, len(names), res["data"], res["basis"])
    spd, ill_params = random_illuminant(rng, res["wl"], config.illuminants)
    g, light_params = random_light(rng, scene, K.row_sums())
    view = random_view(rng, scene)
    params = {"scene": scene_params, "materials": refl_params, "illuminant": ill_params, "light": light_params}
    return _Drawn(scene, K, names, material, refl, spd, g, view, params)


def _render_variants(
    config: GeneratorConfig, d: _Drawn, cam: Camera, device: torch.device | None
) -> tuple[dict[int | None, np.ndarray], float, Any]:
    """Images per variant times the exposure (float32 ``[H, W, 3]``), the exposure, and the view's geometry (an
    object with ``coverage [H·W, F]`` and ``background [H, W]``)."""
    K, r, e0, cam_d = d.K, d.refl[d.material], d.g[:, None] * d.spd[None, :], cam  # r, e0: [F, L]
    if device is not None:
        K, r, e0, cam_d = K.to(device), r.to(device), e0.to(device), copy.deepcopy(cam).to(device)
    raw = (_gathered if config.shading == "gather" else _flat)(config, d, K, r, e0, cam_d)
    p99 = float(torch.quantile(raw[None][0].reshape(-1), 0.99))
    exposure = 0.9 / p99 if p99 > 0 else 1.0
    tiny = float(np.finfo(np.float32).tiny)  # flush float32 subnormals (they slow CPU arithmetic downstream)
    images = {b: np.where(np.abs(a := (im * exposure).numpy()) < tiny, 0.0, a).astype(np.float32)
              for b, (im, _) in raw.items()}
    return images, exposure, raw[None][1]


def _flat(config: GeneratorConfig, d: _Drawn, K: Any, r: Tensor, e0: Tensor, cam: Camera) -> dict[int | None, Any]:
    """One colour per facet: ``{variant: (image [H, W, 3], projection)}``."""
    h, w = config.size
    proj = project(d.scene, (d.view["eye"], d.view["target"]), h, w, up=d.view["up"], fov_deg=d.view["fov_deg"],
                   supersample=config.supersample)
    raw = {}
    for b in config.bounces:
        rgb = cam(radiance(solve(K, r, e0, bounces=b), r)).cpu()  # [F, 3]
        raw[b] = (proj(rgb)[0].permute(1, 2, 0), proj)  # [H, W, 3]
    return raw


def _gathered(config: GeneratorConfig, d: _Drawn, K: Any, r: Tensor, e0: Tensor,
              cam: Camera) -> dict[int | None, Any]:
    """Per-pixel final gather: ``{variant: (image [H, W, 3], gather operator)}``.

    The light mixes an ambient part (uniform, or the sky's open fraction at each point) and the sun (shadow ray per
    sub-pixel ray) with the sample's weight, as ``g`` does per facet. The ``n``-bounce variant gathers the
    ``(n − 1)``-bounce facet irradiance (none for ``n = 1``: direct light only).
    """
    h, w = config.size
    v, light = d.view, d.params["light"]
    view = View(v["eye"], v["target"], v["up"], fov_deg=v["fov_deg"], height=h, width=w)
    sun = torch.tensor(light["sun_direction"], dtype=torch.float64)
    op = gather_operator(d.scene, view, sun, supersample=config.supersample, samples=config.visibility_samples,
                         stride=config.gather_stride, cache=False, edge_supersample=config.edge_supersample)
    direct = mix_direct(op, light["ambient_weight"], light["ambient"] == "sky")  # [K]
    E = torch.stack([source_irradiance(K, r, e0, b) for b in config.bounces])  # [V, F, L]
    images = gathered_image(op, r, E, d.spd.to(e0), cam, direct=direct).cpu()  # [V, 3, H, W], one sparse product
    return {b: (images[k].permute(1, 2, 0), op) for k, b in enumerate(config.bounces)}


def _metadata(config: GeneratorConfig, index: int, d: _Drawn, white: Tensor, exposure: float,
              wl: Tensor) -> dict[str, Any]:
    white_n = white / white.norm()
    ill = d.params["illuminant"]
    return {
        "index": index,
        "seed": config.seed,
        "library": "torch_interreflect",
        "version": __version__,
        "camera": config.camera,
        "size": list(config.size),
        "exposure": _r(exposure),
        "illuminant": {
            **{k: (_r(v) if isinstance(v, float) else v) for k, v in ill.items()},
            "wavelengths": [_r(v) for v in wl.tolist()],
            "spd": [_r(v) for v in d.spd.tolist()],
            "rgb": [_r(v) for v in white.tolist()],
            "rgb_normalized": [_r(v) for v in white_n.tolist()],
        },
        "scene": _round_tree(d.params["scene"]),
        "num_facets": d.scene.num_facets,
        "materials": [
            {"name": n, **_round_tree(p), "reflectance": [_r(v, 6) for v in d.refl[k].tolist()]}
            for k, (n, p) in enumerate(zip(d.names, d.params["materials"], strict=True))
        ],
        "light": _round_tree(d.params["light"]),
        "view": _round_tree(d.view),
        "variants": {("inf" if b is None else str(b)): f"{index:06d}{variant_suffix(b)}" for b in config.bounces},
        "files": sample_files(config, index),
    }


def _geometry(config: GeneratorConfig, d: _Drawn, proj: Any) -> dict[str, np.ndarray]:
    dense = d.K.to_dense().double()
    nz = torch.nonzero(dense).T
    cov = proj.coverage.to_sparse_coo().coalesce()
    extra = {}
    if config.shading == "gather":  # what rebuilds the image's own model: the facets, the view and the light mix
        v, light = d.view, d.params["light"]
        extra = {
            "corners": d.scene.corners.double().numpy(),
            "is_triangle": d.scene.is_triangle.numpy(),
            "view": np.array([*v["eye"], *v["target"], *v["up"], v["fov_deg"], *config.size], dtype=np.float64),
            "gather": np.array([config.supersample, config.visibility_samples, config.gather_stride,
                                *([] if config.edge_supersample is None else [config.edge_supersample])],
                               dtype=np.int64),
            "sun": np.array(light["sun_direction"], dtype=np.float64),
            "ambient": np.array([light["ambient"] == "sky", light["ambient_weight"]], dtype=np.float64),
        }
    return {
        "ff_indices": nz.numpy().astype(np.int32),
        "ff_values": dense[nz[0], nz[1]].numpy().astype(np.float32),
        "areas": d.scene.areas.double().numpy().astype(np.float32),
        "light_factor": d.g.numpy().astype(np.float32),
        "material": d.material.numpy().astype(np.int32),
        "reflectance": d.refl.numpy().astype(np.float32),
        "coverage_indices": cov.indices().numpy().astype(np.int32),
        "coverage_values": cov.values().double().numpy().astype(np.float32),
        "background": proj.background.double().numpy().astype(np.float32),
        **extra,
    }


def render_sample(config: GeneratorConfig, index: int, *, device: torch.device | str | None = None) -> Sample:
    """Render sample ``index`` of ``config`` in memory (deterministic; see the module docstring).

    Args:
        config: The generator configuration.
        index: Sample index (any integer ≥ 0; need not be below ``config.count``).
        device: Where the solves and the camera run (default: CPU, where the bytes are reproducible; another
            device agrees to float64 rounding, not bit for bit). Scenes, form factors and projection stay on the CPU.

    Returns:
        The :class:`Sample`: images ``[H, W, 3]`` float32 per variant, sidecar metadata and geometry arrays.

    Raises:
        SpectralDataError: an unknown camera.
    """
    res = load_resources(config)
    d = _draw(config, index, res)
    dev = None if device is None else torch.device(device)
    images, exposure, view_geometry = _render_variants(config, d, res["camera"], dev)
    white = res["camera"](d.spd[None, :] / math.pi)[0]  # camera RGB of a perfect white diffuser under the illuminant
    meta = _metadata(config, index, d, white, exposure, res["wl"])
    return Sample(index, images, meta, _geometry(config, d, view_geometry) if config.geometry else {})
