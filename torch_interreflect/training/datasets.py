"""``torch.utils.data.Dataset``\\ s of generated samples: from a folder written by ``interreflect generate``, or
rendered on the fly from a :class:`~.generator.GeneratorConfig` (same samples, same bytes).

Every item is a dict:

- ``"image"``: linear camera RGB times the sample's exposure, float32 ``[3, H, W]`` (kornia layout);
- ``"illuminant"``: the camera RGB of the illuminant (a perfect white diffuser under it), unit norm,
  float32 ``[3]`` (the colour-constancy target);
- ``"mask"``: pixels that see a facet, bool ``[H, W]``;
- ``"index"``: the sample index (int);
- with ``geometry=True`` also ``"geometry"``: the dict of :func:`~.generator.load_geometry` (form factors,
  light factor, coverage, ...; float64), which :func:`collate` keeps as a list (facet counts differ).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from .config import CONFIG_FILE, GeneratorConfig, variant_suffix
from .sample import render_sample
from .storage import is_complete, load_geometry

__all__ = ["GeneratedDataset", "RenderedDataset", "collate", "split_indices"]


def _variant(v: int | str | None) -> int | None:
    if v is None or (isinstance(v, str) and v.lower() in ("inf", "infinite", "none")):
        return None
    if isinstance(v, bool) or int(v) < 1:
        raise ValueError(f"variant must be 'inf' (None) or a bounce count >= 1; got {v!r}")
    return int(v)


def split_indices(count: int, test_fraction: float = 0.2) -> tuple[list[int], list[int]]:
    """Train / test indices: the last ``test_fraction`` of the indices are held out.

    Every index is its own random scene (geometry, materials, light and view), so the test scenes are never seen
    in training.

    Example:
        >>> from torch_interreflect.training.datasets import split_indices
        >>> split_indices(10, 0.2)
        ([0, 1, 2, 3, 4, 5, 6, 7], [8, 9])
    """
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction must lie in (0, 1); got {test_fraction}")
    n_test = max(1, round(count * test_fraction))
    if n_test >= count:
        raise ValueError(f"need more than {n_test} samples to hold out {n_test}; got count={count}")
    return list(range(count - n_test)), list(range(count - n_test, count))


class GeneratedDataset(Dataset):
    """Samples of a folder written by :func:`~.generator.generate` (only complete samples are listed).

    Args:
        root: The folder.
        variant: Which image: ``"inf"`` / ``None`` (infinite bounces) or ``n`` (the n-bounce variant, 1 = direct
            only); must have been generated.
        indices: Sample indices to use (default: every complete sample, sorted).
        geometry: Also load the ``_geometry.npz`` data.

    Shape:
        - image: ``[3, H, W]`` float32; illuminant: ``[3]`` float32; mask: ``[H, W]`` bool

    Raises:
        FileNotFoundError: no generator config in ``root``, or a requested index that is not complete.
        ValueError: a variant or geometry that was not generated.
    """

    def __init__(
        self,
        root: str | Path,
        variant: int | str | None = None,
        indices: Sequence[int] | None = None,
        *,
        geometry: bool = False,
    ) -> None:
        self.root = Path(root)
        cfg_path = self.root / CONFIG_FILE
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{root} has no {CONFIG_FILE}: not a folder written by `interreflect generate`")
        self.config = GeneratorConfig.from_json(json.loads(cfg_path.read_text())["generator"])
        self.variant = _variant(variant)
        if self.variant not in self.config.bounces:
            raise ValueError(f"variant {variant!r} was not generated; the folder has {list(self.config.bounces)}")
        if geometry and not self.config.geometry:
            raise ValueError("geometry=True but the folder was generated with --no-geometry")
        self.geometry = geometry
        if indices is None:
            indices = [i for i in range(self.config.count) if is_complete(self.root, i)]
        else:
            missing = [i for i in indices if not is_complete(self.root, i)]
            if missing:
                raise FileNotFoundError(f"samples {missing[:10]} are not complete in {root}")
        self.indices = [int(i) for i in indices]

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int) -> dict[str, Any]:
        i = self.indices[k]
        stem = self.root / f"{i:06d}"
        img = torch.from_numpy(np.load(f"{stem}{variant_suffix(self.variant)}.npy")).permute(2, 0, 1).contiguous()
        meta = json.loads(Path(f"{stem}.json").read_text())
        item: dict[str, Any] = {
            "image": img.float(),
            "illuminant": torch.tensor(meta["illuminant"]["rgb_normalized"], dtype=torch.float32),
            "index": i,
        }
        if self.geometry:
            geo = load_geometry(f"{stem}_geometry.npz")
            item["geometry"] = geo
            item["mask"] = geo["background"] < 1.0
        else:
            item["mask"] = img.abs().sum(0) > 0
        return item


class RenderedDataset(Dataset):
    """Samples rendered on the fly by :func:`~.generator.render_sample` (identical to the generated files).

    Rendering costs about 0.2–0.5 s a sample (form factors dominate); ``cache=True`` keeps rendered items.

    Args:
        config: The generator configuration (its ``count`` is the default length).
        variant: ``"inf"`` / ``None`` or ``n``; must be in ``config.bounces``.
        indices: Sample indices (default ``range(config.count)``).
        geometry: Also return the geometry (needs ``config.geometry``).
        cache: Keep rendered items in memory.

    Shape:
        As :class:`GeneratedDataset`.
    """

    def __init__(
        self,
        config: GeneratorConfig,
        variant: int | str | None = None,
        indices: Sequence[int] | None = None,
        *,
        geometry: bool = False,
        cache: bool = False,
    ) -> None:
        self.config = config
        self.variant = _variant(variant)
        if self.variant not in config.bounces:
            raise ValueError(f"variant {variant!r} is not in config.bounces {list(config.bounces)}")
        if geometry and not config.geometry:
            raise ValueError("geometry=True needs config.geometry=True")
        self.geometry = geometry
        self.indices = list(range(config.count)) if indices is None else [int(i) for i in indices]
        self._cache: dict[int, dict[str, Any]] | None = {} if cache else None

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int) -> dict[str, Any]:
        i = self.indices[k]
        if self._cache is not None and i in self._cache:
            return self._cache[i]
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            s = render_sample(self.config, i)
        finally:
            torch.set_num_threads(threads)
        img = torch.from_numpy(s.images[self.variant]).permute(2, 0, 1).contiguous()
        item: dict[str, Any] = {
            "image": img,
            "illuminant": torch.tensor(s.metadata["illuminant"]["rgb_normalized"], dtype=torch.float32),
            "index": i,
        }
        if self.geometry:
            geo = load_geometry(s.geometry)
            item["geometry"] = geo
            item["mask"] = geo["background"] < 1.0
        else:
            item["mask"] = img.abs().sum(0) > 0
        if self._cache is not None:
            self._cache[i] = item
        return item


def collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Batch items: tensors are stacked (``image [B, 3, H, W]``, ``illuminant [B, 3]``, ``mask [B, H, W]``,
    ``index [B]``); ``geometry`` stays a list of dicts."""
    out: dict[str, Any] = {
        "image": torch.stack([it["image"] for it in items]),
        "illuminant": torch.stack([it["illuminant"] for it in items]),
        "mask": torch.stack([it["mask"] for it in items]),
        "index": torch.tensor([it["index"] for it in items]),
    }
    if "geometry" in items[0]:
        out["geometry"] = [it["geometry"] for it in items]
    return out
