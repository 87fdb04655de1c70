"""Synthetic colour-constancy data: random concave scenes rendered with exact spectral interreflection.

One sample = one random scene (:mod:`.random_scenes`), random reflectances per part, a random illuminant and
light geometry, a random pinhole view, rendered through a real camera's spectral sensitivities
(:func:`~.sample.render_sample`) and written by :func:`~.storage.write_sample`:

- ``{i:06d}.png`` / ``{i:06d}.npy``: the linear camera-RGB image with infinite bounces (16-bit PNG, clipped to
  [0, 1]; float32 ``[H, W, 3]`` array, not clipped), both times the sample's ``exposure``;
- ``{i:06d}_b{n}.png`` / ``.npy``: the same view with the ``n``-bounce model (``n = 1``: direct light only);
- ``{i:06d}_geometry.npz``: what a physics-informed model needs to re-render the sample (form factors, light
  factor, pixel × facet coverage, per-part reflectances; see :func:`~.storage.load_geometry`);
- ``{i:06d}.json``: the sidecar, written last (its presence marks a complete sample): the illuminant spectrum
  and its camera RGB (the colour-constancy ground truth), scene, material, light and view parameters, seed,
  index, library version and the list of files.

Determinism: everything random in sample ``i`` comes from ``numpy.random.default_rng([seed, i])``; rendering
runs on one torch thread in float64; PNGs are written by kornia-rs and ``.npz`` files with fixed zip timestamps,
so the same configuration gives the same bytes, whatever the sharding or the order.

Resumability: every file is written to a temporary name and moved into place with :func:`os.replace`; complete
samples (sidecar present, every listed file present) are skipped; temporary files a killed run left behind are
removed; each shard keeps a manifest (``manifest/shard-{i}-of-{n}.json``) of the indices it completed. Shards
partition the index range (``index % n == i``), so local processes, SLURM array jobs or Ray tasks can run them in
parallel. Within one shard, ``workers`` processes render at once (:mod:`.workers`: this one and spawned ones; the
command line's default, ``--workers auto``, starts one per 32 samples to render, up to the usable cores), with the
same bytes. A folder can grow: a run with a larger ``count`` (and otherwise the same configuration) adds samples.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from pathlib import Path

import torch

from .._checks import check_count
from .._deprecation import moved_attribute
from .._version import __version__
from ..errors import AccuracyWarning
from .config import CONFIG_FILE, MANIFEST_DIR, GeneratorConfig, parse_shard, sample_files, shard_indices, variant_suffix
from .sample import Sample, load_resources, render_sample
from .storage import (
    atomic_write,
    is_complete,
    json_bytes,
    load_geometry,
    remove_stale_temporaries,
    write_sample,
)
from .workers import auto_workers, check_workers, processes, render_indices

__all__ = [
    "CONFIG_FILE",
    "MANIFEST_DIR",
    "GenerateResult",
    "GeneratorConfig",
    "Sample",
    "generate",
    "is_complete",
    "load_geometry",
    "parse_shard",
    "read_config",
    "render_sample",
    "sample_files",
    "shard_indices",
    "variant_suffix",
    "write_sample",
]

_MOVED = {name: "torch_interreflect.training.commands" for name in ("add_generate_parser", "main_generate")}


def __getattr__(name: str) -> object:
    return moved_attribute(__name__, name, _MOVED)


@dataclasses.dataclass
class GenerateResult:
    """What :func:`generate` did.

    Attributes:
        written: Indices rendered and written in this run.
        skipped: Indices found complete and skipped.
        seconds: Wall time in seconds.
        removed: Stale temporary files removed before the run.
        inaccurate: Indices whose solves warned that their error bound is above the solver's tolerance
            (:class:`~torch_interreflect.errors.AccuracyWarning`; bright closed rooms, where the form factors'
            closure error, amplified by ``1/(1 − r ρ)``, bounds the error at ~1–2 %). They are reported by one
            warning at the end of the run, not one per sample.
        workers: Processes that rendered (1: this process only; at most one per sample written).
    """

    written: list[int]
    skipped: list[int]
    seconds: float
    removed: list[Path] = dataclasses.field(default_factory=list)
    inaccurate: list[int] = dataclasses.field(default_factory=list)
    workers: int = 1

    @property
    def samples_per_second(self) -> float:
        """Samples written per second of wall time."""
        return len(self.written) / self.seconds if self.seconds > 0 else float("nan")


def read_config(out: str | Path) -> GeneratorConfig | None:
    """The configuration stored in a generated folder, or ``None`` when it has none.

    Raises:
        ValueError: ``out/dataset.json`` exists but is not a generator configuration.
    """
    path = Path(out) / CONFIG_FILE
    if not path.is_file():
        return None
    try:
        return GeneratorConfig.from_json(json.loads(path.read_text())["generator"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} exists but is not a generator config; use another --out") from exc


def _has_samples(out: Path) -> bool:
    return any(p.name[:6].isdigit() for p in out.iterdir())


def _stored_config(out: Path, config: GeneratorConfig) -> GeneratorConfig | None:
    """Check ``config`` against the folder's; return the config to store (``None``: nothing to write)."""
    old = read_config(out)
    if old is None or (not old.same_samples(config) and not _has_samples(out)):
        return config  # a new folder, or one a failed start left without samples: take the new configuration
    if not old.same_samples(config):
        a, b = old.to_json(), config.to_json()
        diff = {k: (a.get(k), v) for k, v in b.items() if a.get(k) != v and k != "count"}
        hint = (" (a folder of uniform rays, written before 0.2.0, grows with --edge-supersample 1)"
                if "edge_supersample" in diff and old.edge_supersample is None else "")
        raise ValueError(
            f"{out} holds samples of another configuration (differences, existing vs requested: {diff}); "
            f"use another --out or the same options{hint}"
        )
    return config if config.count > old.count else None  # grow; never shrink what is listed


def _write_manifest(out: Path, shard: tuple[int, int], config: GeneratorConfig, done: list[int]) -> None:
    (out / MANIFEST_DIR).mkdir(exist_ok=True)
    i, n = shard
    body = {"shard": [i, n], "count": config.count, "seed": config.seed, "done": sorted(done),
            "complete": len(done) == len(shard_indices(config.count, i, n))}
    atomic_write(out / MANIFEST_DIR / f"shard-{i:04d}-of-{n:04d}.json", json_bytes(body))


def _prepare(out: Path, config: GeneratorConfig, indices: range) -> list[Path]:
    """Check everything that can fail before writing anything; then create the folder and store the config."""
    load_resources(config)  # an unknown camera fails here, before the folder exists
    to_store = _stored_config(out, config) if out.is_dir() else config
    out.mkdir(parents=True, exist_ok=True)
    removed = remove_stale_temporaries(out, indices)
    if to_store is not None:
        content = {"generator": to_store.to_json(), "library": "torch_interreflect", "version": __version__}
        atomic_write(out / CONFIG_FILE, json_bytes(content))
    return removed


def generate(
    out: str | Path,
    config: GeneratorConfig,
    *,
    shard: tuple[int, int] = (0, 1),
    progress: bool = True,
    limit: int | None = None,
    threads: int | None = 1,
    workers: int | str = 1,
) -> GenerateResult:
    """Render and write the samples of one shard, skipping complete ones (resumable; see the module docstring).

    Args:
        out: Output folder (created).
        config: What to generate; apart from ``count``, must equal the config already stored in ``out`` if any
            (a larger ``count`` grows the folder).
        shard: ``(i, n)``: this process renders indices ``i, i + n, i + 2n, …`` below ``config.count``.
        progress: Show a tqdm progress bar.
        limit: Stop after writing this many samples (``>= 0``; for tests of interrupted runs).
        threads: Torch threads while rendering (1 = deterministic bytes whatever the machine; ``None`` keeps the
            current setting), in this process or in each worker.
        workers: Processes rendering at once (the same bytes whatever the number; at most one per sample), or
            ``"auto"``: one per :data:`~.workers.MIN_SAMPLES_PER_WORKER` samples left to render, up to the usable
            cores over ``threads`` (a worker's start-up costs about 20 samples at 64 × 64). ``1`` renders in this
            process. Warnings raised in the other processes are raised again here.

    Returns:
        A :class:`GenerateResult`.

    Raises:
        ValueError: a bad shard, ``workers`` or ``limit``, or ``out`` holding samples of another configuration
            (nothing is written).
        SpectralDataError: an unknown camera (nothing is written).
    """
    from tqdm.auto import tqdm

    out = Path(out)
    indices = shard_indices(config.count, *shard)
    workers = check_workers(workers)
    limit = check_count(limit, "limit", minimum=0, optional=True)
    removed = _prepare(out, config, indices)
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    threads = torch.get_num_threads()  # what every process renders with
    t0 = time.perf_counter()
    complete = [is_complete(out, k) for k in indices]
    skipped = [k for k, c in zip(indices, complete, strict=True) if c]
    todo = [k for k, c in zip(indices, complete, strict=True) if not c][:limit]
    n_workers = processes(auto_workers(len(todo), threads) if workers == "auto" else int(workers), len(todo))
    written: list[int] = []
    inaccurate: dict[int, str] = {}
    try:
        desc = f"generate {shard[0]}/{shard[1]}" + (f" ({n_workers} processes)" if n_workers > 1 else "")
        with tqdm(total=len(indices), initial=len(skipped), desc=desc, unit="sample", disable=not progress) as bar:
            for k, warning in render_indices(out, config, todo, workers=n_workers, threads=threads):
                if warning is not None:
                    inaccurate[k] = warning
                written.append(k)
                bar.update()
                if len(written) % 50 == 0:
                    _write_manifest(out, shard, config, sorted(written + skipped))
        _write_manifest(out, shard, config, sorted(written + skipped))
    finally:
        torch.set_num_threads(old_threads)
    if inaccurate:
        first = min(inaccurate.items())
        warnings.warn(f"generate: the solves of {len(inaccurate)} of {len(written)} samples warned that their error "
                      f"bound is above the solver's tolerance (GenerateResult.inaccurate lists them); sample "
                      f"{first[0]}: {first[1]}", AccuracyWarning, stacklevel=2)
    return GenerateResult(sorted(written), skipped, time.perf_counter() - t0, removed, sorted(inaccurate),
                          n_workers)
