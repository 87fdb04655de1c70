"""What the generator makes: :class:`GeneratorConfig`, the file names of a sample, and the shards.

The configuration says everything that decides a sample's bytes except its index; ``count`` only says how many
indices a run covers (sample ``i`` does not depend on it, so a data set can grow).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from .random_scenes import ILLUMINANT_KINDS, SCENE_KINDS

__all__ = [
    "CONFIG_FILE",
    "MANIFEST_DIR",
    "SHADINGS",
    "GeneratorConfig",
    "parse_shard",
    "sample_files",
    "shard_indices",
    "variant_suffix",
]

#: The configuration file of a generated folder.
CONFIG_FILE = "dataset.json"
#: The folder of the per-shard manifests.
MANIFEST_DIR = "manifest"
#: Image shadings of :attr:`GeneratorConfig.shading`.
SHADINGS: tuple[str, ...] = ("gather", "flat")
#: Values of fields added after the first release, for configurations stored before them.
_BEFORE_FIELD: dict[str, Any] = {"shading": "flat", "split_contacts": False, "edge_supersample": None}


def _check_int(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}; got {value!r}")
    return value


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
        supersample: Sub-pixel rays per pixel side (anti-aliasing: coverage, hit points and sun shadows).
        edge_supersample: With ``"gather"``: ``e``, for ``e²`` rays (a Sobol net) in the pixels where the
            ``supersample`` rays see an edge (``edge_supersample`` of
            :func:`~torch_interreflect.camera.gather_operator`); ``None``: uniform rays. The image then approximates
            the pixel integral of a camera or of a path tracer's box filter. Against Mitsuba 3 at 2 × 2,048 spp on
            three sun + sky test scenes at 32 × 32, the per-pixel RMS difference was 3.2–6.7 % with uniform 2 × 2
            rays (the default before 0.2.0, which folders written then keep), 1.0–1.3 % with ``e = 8`` and
            0.9–1.2 % with 16, Mitsuba's own noise being 0.9–1.0 %. On 4 generator scenes at 32 × 32 against ``e = 64``,
            relative RMS over the whole image: 0.4–0.7 % with 8, 0.1–0.2 % with 16 (per pixel, over the bright
            ones: 1.2–1.8 % and ~0.5 %). The cost: 15 % fewer samples per second at 64 × 64 with 8
            (``benchmarks/results/generator.md``), ~8 % at 32 × 32; ~24 % with 16 at 32 × 32.
        wavelengths: ``(start, stop, step)`` of the grid in nm.
        geometry: Also write the ``_geometry.npz`` file.
        basis_components: Components of the reflectance PCA basis random spectra are drawn from.
        shading: ``"gather"`` (per-pixel final gather: irradiance varies inside a facet, soft shadows, as in a
            path tracer's image) or ``"flat"`` (one colour per facet, the only mode of 0.1.0; faster).
        split_contacts: Split facets where another facet stands on them
            (:func:`~torch_interreflect.geometry.split_at_contacts`) before the form factors, so the floor under a
            block does not share the radiosity of its lit part.
        visibility_samples: With ``"gather"``: visibility rays per side of a target facet for pairs a third
            facet could block (``samples²`` rays per pixel and facet; see
            :func:`~torch_interreflect.camera.point_form_factors`).
        gather_stride: With ``"gather"``: gather at one point per ``stride × stride`` pixels and facet, and
            interpolate (``stride`` of :func:`~torch_interreflect.camera.gather_operator`); 1 gathers at every pixel.

    Folders written before ``shading`` and ``split_contacts`` existed read back as ``"flat"`` and ``False`` (what
    made their bytes), so growing such a folder still adds samples of the same kind.

    Raises:
        ValueError: a field out of its range (the message names the field, what it must be and what came).
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
    shading: str = "gather"
    split_contacts: bool = True
    visibility_samples: int = 2
    gather_stride: int = 1
    edge_supersample: int | None = 8

    def __post_init__(self) -> None:
        _check_int("count", self.count, 0)
        _check_int("seed", self.seed, 0)
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
        _check_int("supersample", self.supersample, 1)
        _check_int("basis_components", self.basis_components, 1)
        if self.shading not in SHADINGS:
            raise ValueError(f"shading must be one of {list(SHADINGS)}; got {self.shading!r}")
        if not isinstance(self.split_contacts, bool):
            raise ValueError(f"split_contacts must be True or False; got {self.split_contacts!r}")
        _check_int("visibility_samples", self.visibility_samples, 1)
        _check_int("gather_stride", self.gather_stride, 1)
        if self.edge_supersample is not None:
            _check_int("edge_supersample", self.edge_supersample, 1)
            if self.edge_supersample <= self.supersample:  # uniform rays: one identity, as None
                object.__setattr__(self, "edge_supersample", None)
        object.__setattr__(self, "wavelengths", tuple(float(v) for v in self.wavelengths))

    def same_samples(self, other: GeneratorConfig) -> bool:
        """Whether ``other`` makes the same sample ``i`` as this config for every ``i`` (all fields but ``count``)."""
        return self._identity() == other._identity()

    def _identity(self) -> GeneratorConfig:
        """The fields that decide a sample's bytes (``count`` never; the gather's settings only when gathering)."""
        d = dataclasses.replace(self, count=0)
        if d.shading == "flat":
            default = GeneratorConfig()
            d = dataclasses.replace(d, visibility_samples=default.visibility_samples,
                                    gather_stride=default.gather_stride, edge_supersample=default.edge_supersample)
        return d

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
        for name, old in _BEFORE_FIELD.items():  # folders of earlier versions: what made their bytes
            d.setdefault(name, old)
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in fields})


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
