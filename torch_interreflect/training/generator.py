"""Synthetic colour-constancy data: random concave scenes rendered with exact spectral interreflection.

One sample = one random scene (:mod:`.random_scenes`), random reflectances per part, a random illuminant and
light geometry, a random pinhole view, rendered through a real camera's spectral sensitivities:

- ``{i:06d}.png`` / ``{i:06d}.npy``: the linear camera-RGB image with infinite bounces (16-bit PNG, clipped to
  [0, 1]; float32 ``[H, W, 3]`` array, not clipped), both times the sample's ``exposure``;
- ``{i:06d}_b{n}.png`` / ``.npy``: the same view with the ``n``-bounce model (``n = 1``: direct light only);
- ``{i:06d}_geometry.npz``: what a physics-informed model needs to re-render the sample (form factors, light
  factor, pixel × facet coverage, per-part reflectances; see :func:`load_geometry`);
- ``{i:06d}.json``: the sidecar, written last (its presence marks a complete sample): the illuminant spectrum
  and its camera RGB (the colour-constancy ground truth), scene, material, light and view parameters, seed,
  index, library version and the list of files.

Determinism: everything random in sample ``i`` comes from ``numpy.random.default_rng([seed, i])``; rendering
runs on one torch thread in float64; PNGs are written by :mod:`.pngio` and ``.npz`` files with fixed zip
timestamps, so the same configuration gives the same bytes, whatever the sharding or the order.

Resumability: every file is written to a temporary name and moved into place with :func:`os.replace`; complete
samples (sidecar present, every listed file present) are skipped; each shard keeps a manifest
(``manifest/shard-{i}-of-{n}.json``) of the indices it completed. Shards partition the index range
(``index % n == i``), so local processes, SLURM array jobs or Ray tasks can run them in parallel.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import io
import json
import math
import os
import sys
import time
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import spectral
from .._version import __version__
from ..camera.sensor import Camera
from ..errors import SpectralDataError
from ..formfactors.quadrature import form_factors
from ..solver.api import radiance, solve
from .pngio import encode_png16
from .random_scenes import (
    ILLUMINANT_KINDS,
    SCENE_KINDS,
    random_illuminant,
    random_light,
    random_reflectances,
    random_scene,
    random_view,
)

__all__ = [
    "GenerateResult",
    "GeneratorConfig",
    "Sample",
    "add_generate_parser",
    "generate",
    "is_complete",
    "load_geometry",
    "main_generate",
    "parse_shard",
    "render_sample",
    "sample_files",
    "shard_indices",
]

CONFIG_FILE = "dataset.json"
MANIFEST_DIR = "manifest"


@dataclasses.dataclass(frozen=True)
class GeneratorConfig:
    """What to generate. Two runs with equal configs write identical files.

    Attributes:
        count: Number of samples (indices ``0 … count − 1``).
        seed: Base seed; sample ``i`` draws from ``numpy.random.default_rng([seed, i])``.
        scenes: Scene kinds to draw from (:data:`~.random_scenes.SCENE_KINDS`).
        illuminants: Illuminant families (:data:`~.random_scenes.ILLUMINANT_KINDS`).
        camera: Camera sensitivities (:meth:`torch_interreflect.Camera.from_colour` name).
        size: Image ``(height, width)`` in pixels.
        bounces: Variants to render: ``None`` (infinite bounces, always the main image) and ``n ≥ 1``.
        supersample: Sub-pixels per pixel side for the coverage (anti-aliasing).
        wavelengths: ``(start, stop, step)`` of the grid in nm.
        geometry: Also write the ``_geometry.npz`` file.
        basis_components: Components of the reflectance PCA basis random spectra are drawn from.
    """

    count: int = 100
    seed: int = 0
    scenes: tuple[str, ...] = SCENE_KINDS
    illuminants: tuple[str, ...] = ILLUMINANT_KINDS
    camera: str = "Nikon 5100 (NPL)"
    size: tuple[int, int] = (64, 64)
    bounces: tuple[int | None, ...] = (None, 1, 2)
    supersample: int = 2
    wavelengths: tuple[float, float, float] = (400.0, 700.0, 10.0)
    geometry: bool = True
    basis_components: int = 6

    def __post_init__(self) -> None:
        if isinstance(self.count, bool) or not isinstance(self.count, int) or self.count < 0:
            raise ValueError(f"count must be an integer >= 0; got {self.count!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0; got {self.seed!r}")
        object.__setattr__(self, "scenes", tuple(self.scenes))
        object.__setattr__(self, "illuminants", tuple(self.illuminants))
        for kinds, allowed, what in ((self.scenes, SCENE_KINDS, "scenes"),
                                     (self.illuminants, ILLUMINANT_KINDS, "illuminants")):
            bad = [k for k in kinds if k not in allowed]
            if bad or not kinds:
                raise ValueError(f"{what} must be a non-empty list from {list(allowed)}; got {list(kinds)}")
        h, w = (int(v) for v in self.size)
        if h < 1 or w < 1:
            raise ValueError(f"size must be two positive integers (height, width); got {self.size!r}")
        object.__setattr__(self, "size", (h, w))
        b = tuple(None if v is None else int(v) for v in self.bounces)
        if None not in b or any(v is not None and v < 1 for v in b) or len(set(b)) != len(b):
            raise ValueError(f"bounces must hold None (infinite, the main image) and distinct n >= 1; got {b}")
        object.__setattr__(self, "bounces", (None, *sorted(v for v in b if v is not None)))
        if int(self.supersample) < 1:
            raise ValueError(f"supersample must be >= 1; got {self.supersample!r}")
        object.__setattr__(self, "wavelengths", tuple(float(v) for v in self.wavelengths))

    def to_json(self) -> dict[str, Any]:
        """The config as JSON-able data (``bounces``: ``"inf"`` for ``None``)."""
        d = dataclasses.asdict(self)
        d["bounces"] = ["inf" if v is None else v for v in self.bounces]
        d["scenes"], d["illuminants"] = list(self.scenes), list(self.illuminants)
        d["size"], d["wavelengths"] = list(self.size), list(self.wavelengths)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> GeneratorConfig:
        """Inverse of :meth:`to_json`."""
        d = dict(d)
        d["bounces"] = tuple(None if v == "inf" else int(v) for v in d["bounces"])
        d["size"] = tuple(d["size"])
        d["wavelengths"] = tuple(d["wavelengths"])
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in fields})


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


def variant_suffix(bounces: int | None) -> str:
    """File-name suffix of a variant: ``""`` for infinite bounces, ``"_b{n}"`` otherwise."""
    return "" if bounces is None else f"_b{int(bounces)}"


def sample_files(config: GeneratorConfig, index: int) -> list[str]:
    """Names of the files of sample ``index`` (sidecar last)."""
    stem = f"{index:06d}"
    names = []
    for b in config.bounces:
        names += [f"{stem}{variant_suffix(b)}.png", f"{stem}{variant_suffix(b)}.npy"]
    if config.geometry:
        names.append(f"{stem}_geometry.npz")
    return [*names, f"{stem}.json"]


def shard_indices(count: int, shard: int = 0, num_shards: int = 1) -> range:
    """Indices of one shard: ``range(shard, count, num_shards)``; the shards partition ``range(count)``.

    Raises:
        ValueError: ``num_shards < 1`` or ``shard`` outside ``[0, num_shards)``.

    Example:
        >>> from torch_interreflect.training.generator import shard_indices
        >>> list(shard_indices(7, 1, 3))
        [1, 4]
    """
    if num_shards < 1 or not 0 <= shard < num_shards:
        raise ValueError(f"shard must satisfy 0 <= shard < num_shards (num_shards >= 1); got {shard}/{num_shards}")
    return range(shard, count, num_shards)


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` → ``(i, n)`` (e.g. a SLURM array: ``--shard $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT``)."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError as exc:
        raise ValueError(f"shard must look like 'i/n' (e.g. '0/4'); got {text!r}") from exc
    shard_indices(0, i, n)
    return i, n


# ------------------------------------------------------------------------------------------------ rendering
@functools.lru_cache(maxsize=4)
def _resources(wl_spec: tuple[float, float, float], camera: str, k: int) -> dict[str, Any]:
    from ..layers import fit_reflectance_basis, reflectance_data

    wl = spectral.wavelengths(*wl_spec, dtype=torch.float64)
    try:
        cam = Camera.from_colour(camera, wl)
    except SpectralDataError:  # e.g. the Sigma data end at 680 nm
        cam = Camera.from_colour(camera, wl, extrapolate="zero")
    data = reflectance_data(wl)
    mean, comps = fit_reflectance_basis(data, k)
    sigma = ((data - mean) @ comps.T).std(0)
    return {"wl": wl, "camera": cam, "data": data, "basis": (mean, comps, sigma)}


def _r(x: float, digits: int = 8) -> float:
    return float(f"{float(x):.{digits}g}")


def render_sample(config: GeneratorConfig, index: int) -> Sample:
    """Render sample ``index`` of ``config`` in memory (deterministic; see the module docstring).

    Args:
        config: The generator configuration.
        index: Sample index (any integer ≥ 0; need not be below ``config.count``).

    Returns:
        The :class:`Sample`: images ``[H, W, 3]`` float32 per variant, sidecar metadata and geometry arrays.
    """
    from ..camera.projection import project

    res = _resources(config.wavelengths, config.camera, config.basis_components)
    wl, cam = res["wl"], res["camera"]
    rng = np.random.default_rng([config.seed, index])
    scene, scene_params = random_scene(rng, config.scenes)
    K = form_factors(scene)
    names = scene.material_names or ["all"]
    material = scene.material if scene.material is not None else torch.zeros(scene.num_facets, dtype=torch.long)
    refl, refl_params = random_reflectances(rng, len(names), res["data"], res["basis"])
    spd, ill_params = random_illuminant(rng, wl, config.illuminants)
    g, light_params = random_light(rng, scene, K.row_sums())
    view = random_view(rng, scene)
    h, w = config.size
    proj = project(scene, (view["eye"], view["target"]), h, w, up=view["up"], fov_deg=view["fov_deg"],
                   supersample=config.supersample)

    r = refl[material]  # [F, L]
    e0 = g[:, None] * spd[None, :]
    raw: dict[int | None, Tensor] = {}
    for b in config.bounces:
        E = solve(K, r, e0, bounces=b)
        rgb = cam(radiance(E, r))  # [F, 3]
        raw[b] = proj(rgb)[0].permute(1, 2, 0)  # [H, W, 3]
    white = cam(spd[None, :] / math.pi)[0]  # camera RGB of a perfect white diffuser under the illuminant
    p99 = float(torch.quantile(raw[None].reshape(-1), 0.99))
    exposure = 0.9 / p99 if p99 > 0 else 1.0
    tiny = float(np.finfo(np.float32).tiny)  # flush float32 subnormals (they slow CPU arithmetic downstream)
    images = {b: np.where(np.abs(a := (im * exposure).numpy()) < tiny, 0.0, a).astype(np.float32)
              for b, im in raw.items()}

    white_n = white / white.norm()
    meta: dict[str, Any] = {
        "index": index,
        "seed": config.seed,
        "library": "torch_interreflect",
        "version": __version__,
        "camera": config.camera,
        "size": [h, w],
        "exposure": _r(exposure),
        "illuminant": {
            **{k: (_r(v) if isinstance(v, float) else v) for k, v in ill_params.items()},
            "wavelengths": [_r(v) for v in wl.tolist()],
            "spd": [_r(v) for v in spd.tolist()],
            "rgb": [_r(v) for v in white.tolist()],
            "rgb_normalized": [_r(v) for v in white_n.tolist()],
        },
        "scene": _round_tree(scene_params),
        "num_facets": scene.num_facets,
        "materials": [
            {"name": n, **_round_tree(p), "reflectance": [_r(v, 6) for v in refl[k].tolist()]}
            for k, (n, p) in enumerate(zip(names, refl_params, strict=True))
        ],
        "light": _round_tree(light_params),
        "view": _round_tree(view),
        "variants": {("inf" if b is None else str(b)): f"{index:06d}{variant_suffix(b)}" for b in config.bounces},
        "files": sample_files(config, index),
    }
    geometry: dict[str, np.ndarray] = {}
    if config.geometry:
        dense = K.to_dense().double()
        nz = torch.nonzero(dense).T
        cov = proj.coverage.to_sparse_coo().coalesce()
        geometry = {
            "ff_indices": nz.numpy().astype(np.int32),
            "ff_values": dense[nz[0], nz[1]].numpy().astype(np.float32),
            "areas": scene.areas.double().numpy().astype(np.float32),
            "light_factor": g.numpy().astype(np.float32),
            "material": material.numpy().astype(np.int32),
            "reflectance": refl.numpy().astype(np.float32),
            "coverage_indices": cov.indices().numpy().astype(np.int32),
            "coverage_values": cov.values().double().numpy().astype(np.float32),
            "background": proj.background.double().numpy().astype(np.float32),
        }
    return Sample(index, images, meta, geometry)


def _round_tree(x: Any) -> Any:
    if isinstance(x, float):
        return _r(x)
    if isinstance(x, dict):
        return {k: _round_tree(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round_tree(v) for v in x]
    return x


# ------------------------------------------------------------------------------------------------ writing
def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` (readable by :func:`numpy.load`) with fixed timestamps, so the bytes are reproducible."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, _npy_bytes(arrays[name]))
    return buf.getvalue()


def _json_bytes(obj: Any) -> bytes:
    return (json.dumps(obj, indent=1, sort_keys=True, ensure_ascii=False) + "\n").encode()


def write_sample(out: str | Path, sample: Sample) -> None:
    """Write a sample's files atomically, the sidecar last."""
    out = Path(out)
    stem = f"{sample.index:06d}"
    for b, img in sample.images.items():
        name = f"{stem}{variant_suffix(b)}"
        q = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
        _atomic_write(out / f"{name}.png", encode_png16(q))
        _atomic_write(out / f"{name}.npy", _npy_bytes(img))
    if sample.geometry:
        _atomic_write(out / f"{stem}_geometry.npz", _npz_bytes(sample.geometry))
    _atomic_write(out / f"{stem}.json", _json_bytes(sample.metadata))


def is_complete(out: str | Path, index: int) -> bool:
    """Whether sample ``index`` is complete in ``out``: its sidecar exists and every file it lists exists."""
    out = Path(out)
    side = out / f"{index:06d}.json"
    if not side.is_file():
        return False
    try:
        files = json.loads(side.read_text())["files"]
    except (ValueError, KeyError):
        return False
    return all((out / f).is_file() for f in files)


def load_geometry(
    source: str | Path | Mapping[str, np.ndarray], dtype: torch.dtype = torch.float64
) -> dict[str, Any]:
    """Tensors a physics-informed model can re-render with, from a ``_geometry.npz`` file or its arrays.

    Args:
        source: The file, or the arrays themselves (``Sample.geometry``).
        dtype: Floating dtype of the results.

    Returns:
        ``{"form_factors": FormFactors (dense [F, F]), "light_factor": [F], "material": [F] int64,
        "reflectance": [M, L], "coverage": sparse CSR [H·W, F], "background": [H, W]}``.
    """
    import warnings

    from ..formfactors.operator import FormFactors

    z = np.load(source) if isinstance(source, (str, Path)) else source
    areas = torch.from_numpy(np.asarray(z["areas"])).to(dtype)
    n = areas.shape[0]
    idx = torch.from_numpy(np.asarray(z["ff_indices"]).astype(np.int64))
    mat = torch.zeros(n, n, dtype=dtype)
    mat[idx[0], idx[1]] = torch.from_numpy(np.asarray(z["ff_values"])).to(dtype)
    bg = torch.from_numpy(np.asarray(z["background"])).to(dtype)
    ci = torch.from_numpy(np.asarray(z["coverage_indices"]).astype(np.int64))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        cov = torch.sparse_coo_tensor(ci, torch.from_numpy(np.asarray(z["coverage_values"])).to(dtype),
                                      (bg.numel(), n)).coalesce().to_sparse_csr()
    return {
        "form_factors": FormFactors(mat, areas),
        "light_factor": torch.from_numpy(np.asarray(z["light_factor"])).to(dtype),
        "material": torch.from_numpy(np.asarray(z["material"]).astype(np.int64)),
        "reflectance": torch.from_numpy(np.asarray(z["reflectance"])).to(dtype),
        "coverage": cov,
        "background": bg,
    }


# ------------------------------------------------------------------------------------------------ driver
@dataclasses.dataclass
class GenerateResult:
    """What :func:`generate` did.

    Attributes:
        written: Indices rendered and written in this run.
        skipped: Indices found complete and skipped.
        seconds: Wall time in seconds.
    """

    written: list[int]
    skipped: list[int]
    seconds: float

    @property
    def samples_per_second(self) -> float:
        """Samples written per second of wall time."""
        return len(self.written) / self.seconds if self.seconds > 0 else float("nan")


def _check_config_file(out: Path, config: GeneratorConfig) -> None:
    path = out / CONFIG_FILE
    content = {"generator": config.to_json(), "library": "torch_interreflect", "version": __version__}
    if path.is_file():
        try:
            old = json.loads(path.read_text())["generator"]
        except (ValueError, KeyError) as exc:
            raise ValueError(f"{path} exists but is not a generator config; use another --out") from exc
        if old != config.to_json():
            diff = {k: (old.get(k), v) for k, v in config.to_json().items() if old.get(k) != v}
            raise ValueError(
                f"{out} holds samples of another configuration (differences, existing vs requested: {diff}); "
                "use another --out or the same options"
            )
        return
    _atomic_write(path, _json_bytes(content))


def _write_manifest(out: Path, shard: tuple[int, int], config: GeneratorConfig, done: list[int]) -> None:
    (out / MANIFEST_DIR).mkdir(exist_ok=True)
    i, n = shard
    body = {"shard": [i, n], "count": config.count, "seed": config.seed, "done": sorted(done),
            "complete": len(done) == len(shard_indices(config.count, i, n))}
    _atomic_write(out / MANIFEST_DIR / f"shard-{i:04d}-of-{n:04d}.json", _json_bytes(body))


def generate(
    out: str | Path,
    config: GeneratorConfig,
    *,
    shard: tuple[int, int] = (0, 1),
    progress: bool = True,
    limit: int | None = None,
    threads: int | None = 1,
) -> GenerateResult:
    """Render and write the samples of one shard, skipping complete ones (resumable; see the module docstring).

    Args:
        out: Output folder (created).
        config: What to generate; must equal the config already stored in ``out`` if any.
        shard: ``(i, n)``: this process renders indices ``i, i + n, i + 2n, …`` below ``config.count``.
        progress: Show a tqdm progress bar.
        limit: Stop after writing this many samples (for tests of interrupted runs).
        threads: Torch threads while rendering (1 = deterministic bytes whatever the machine; ``None`` keeps the
            current setting).

    Returns:
        A :class:`GenerateResult`.

    Raises:
        ValueError: a bad shard, or ``out`` holding samples of another configuration.
    """
    from tqdm.auto import tqdm

    out = Path(out)
    indices = shard_indices(config.count, *shard)
    out.mkdir(parents=True, exist_ok=True)
    _check_config_file(out, config)
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    t0 = time.perf_counter()
    written: list[int] = []
    skipped: list[int] = []
    done: list[int] = []
    try:
        bar = tqdm(indices, desc=f"generate {shard[0]}/{shard[1]}", unit="sample", disable=not progress)
        for k in bar:
            if is_complete(out, k):
                skipped.append(k)
                done.append(k)
                continue
            if limit is not None and len(written) >= limit:
                break
            write_sample(out, render_sample(config, k))
            written.append(k)
            done.append(k)
            if len(written) % 50 == 0:
                _write_manifest(out, shard, config, done)
        bar.close()
        _write_manifest(out, shard, config, done)
    finally:
        torch.set_num_threads(old_threads)
    return GenerateResult(written, skipped, time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------------ CLI
def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"size must look like HxW (e.g. 64x64); got {text!r}") from exc
    return h, w


def _bounces(text: str) -> int | None:
    if text.lower() in ("inf", "infinite", "none"):
        return None
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"bounces must be 'inf' or an integer >= 1; got {text!r}") from exc


def _shard(text: str) -> tuple[int, int]:
    try:
        return parse_shard(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def add_generate_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``generate`` sub-command to an ``argparse`` sub-parsers object (``parser.add_subparsers()``)."""
    p = sub.add_parser("generate", help="synthetic colour-constancy data: random concave scenes, exact interreflection",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--count", type=int, required=True, help="number of samples (indices 0 … count-1)")
    p.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    p.add_argument("--shard", type=_shard, default=(0, 1), help="i/n: render indices i, i+n, … (default 0/1)")
    p.add_argument("--scenes", nargs="+", default=list(SCENE_KINDS), choices=SCENE_KINDS, help="scene kinds")
    p.add_argument("--illuminants", nargs="+", default=list(ILLUMINANT_KINDS), choices=ILLUMINANT_KINDS,
                   help="illuminant families")
    p.add_argument("--camera", default="Nikon 5100 (NPL)", help="camera sensitivities (default Nikon 5100 (NPL))")
    p.add_argument("--size", type=_size, default=(64, 64), help="image size HxW (default 64x64)")
    p.add_argument("--bounces", type=_bounces, nargs="+", default=[None, 1, 2],
                   help="variants: inf (always written) and n-bounce models, e.g. 1 (direct only) 2 (default: inf 1 2)")
    p.add_argument("--supersample", type=int, default=2, help="sub-pixels per pixel side (default 2)")
    p.add_argument("--no-geometry", action="store_true", help="do not write the _geometry.npz files")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run_generate)
    return p


def _run_generate(args: argparse.Namespace) -> int:
    bounces = list(args.bounces)
    if None not in bounces:
        bounces.insert(0, None)
    config = GeneratorConfig(
        count=args.count, seed=args.seed, scenes=tuple(args.scenes), illuminants=tuple(args.illuminants),
        camera=args.camera, size=args.size, bounces=tuple(dict.fromkeys(bounces)), supersample=args.supersample,
        geometry=not args.no_geometry,
    )
    res = generate(args.out, config, shard=args.shard, progress=not args.no_progress)
    print(f"shard {args.shard[0]}/{args.shard[1]}: wrote {len(res.written)} samples, skipped {len(res.skipped)} "
          f"complete ones, in {res.seconds:.1f} s ({res.samples_per_second:.2f} samples/s) -> {args.out}")
    return 0


def main_generate(argv: Sequence[str] | None = None) -> int:
    """``interreflect generate`` as a stand-alone entry point (``python -m torch_interreflect.training.generator``)."""
    parser = argparse.ArgumentParser(prog="interreflect")
    sub = parser.add_subparsers(dest="command", required=True)
    add_generate_parser(sub)
    args = parser.parse_args(["generate", *(argv if argv is not None else sys.argv[1:])])
    return int(args.func(args))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main_generate())
