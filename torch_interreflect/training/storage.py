"""The files of a generated folder: atomic writes, formats, completeness, geometry, stale temporaries.

Formats: ``.npy`` / ``.npz`` (fixed zip timestamps, so the bytes are reproducible), JSON (sorted keys) and 16-bit
RGB PNG through :mod:`kornia.io` (kornia-rs's encoder: lossless, deterministic, and read back bit-exactly by
:func:`read_png`; Pillow opens such files as 8-bit RGB, so read them with :func:`read_png` or
``kornia.io.load_image(path, ImageLoadType.UNCHANGED)``).

Every file is written to a temporary name beside its target (``.{stem}.tmp{pid}{suffix}``) and moved into place
with :func:`os.replace`; a failed write (a full disk, an interrupt) removes its temporary file, and
:func:`remove_stale_temporaries` removes those a killed process left behind.
"""

from __future__ import annotations

import io
import json
import os
import re
import time
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._sparse import sparse_matrix
from ..formfactors.operator import FormFactors
from .config import variant_suffix
from .sample import Sample

__all__ = [
    "atomic_write",
    "is_complete",
    "json_bytes",
    "load_geometry",
    "npy_bytes",
    "npz_bytes",
    "read_png",
    "remove_stale_temporaries",
    "temporary_path",
    "write_png16",
    "write_sample",
]

#: Temporary files: ``.{stem}.tmp{pid}{suffix}`` (and the ``.{name}.tmp{pid}`` of earlier versions).
_TEMPORARY = re.compile(r"^\.(?P<stem>[^/]+?)\.tmp\d+(?P<suffix>\.[A-Za-z0-9]+)?$")


def temporary_path(path: Path) -> Path:
    """The temporary name ``path`` is written under before it is moved into place."""
    return path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")


def atomic_write(path: str | Path, data: bytes | Callable[[Path], None]) -> None:
    """Write ``path`` atomically: to :func:`temporary_path`, then :func:`os.replace`.

    Args:
        path: The target.
        data: The bytes, or a function that writes the file at the path it is given.

    Raises:
        OSError: the write or the move failed (e.g. a full disk); the temporary file is removed first.
    """
    path = Path(path)
    tmp = temporary_path(path)
    try:
        if callable(data):
            data(tmp)
        else:
            tmp.write_bytes(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def remove_stale_temporaries(
    out: str | Path, indices: Iterable[int], *, others_older_than: float = 600.0
) -> list[Path]:
    """Remove temporary files a failed or killed run left in ``out`` (the caller's samples only).

    Args:
        out: The folder (and its ``manifest/`` folder).
        indices: Sample indices this process owns (its shard): their temporary files are removed whatever their
            age (shards partition the indices, so no other process writes them).
        others_older_than: Temporary files of no sample (the config, manifests) are removed when older than this
            many seconds (another shard may be writing a fresh one).

    Returns:
        The files removed.
    """
    out = Path(out)
    own = {f"{i:06d}" for i in indices}
    removed = []
    now = time.time()
    for folder in (out, out / "manifest"):
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            m = _TEMPORARY.match(p.name)
            if m is None or not p.is_file():
                continue
            index = m["stem"][:6]
            if index in own or (not index.isdigit() and now - p.stat().st_mtime > others_older_than):
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


def write_png16(path: str | Path, image: np.ndarray) -> None:
    """Write a 16-bit RGB PNG with :func:`kornia.io.write_image` (not atomic by itself; see :func:`atomic_write`).

    Args:
        path: The file (its name must end in ``.png``).
        image: ``uint16`` array. Shape ``[H, W, 3]``.

    Raises:
        ValueError: not a ``uint16`` ``[H, W, 3]`` array.
    """
    import kornia.io

    if not isinstance(image, np.ndarray) or image.dtype != np.uint16 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(
            f"image must be a uint16 array [H, W, 3]; got {getattr(image, 'dtype', type(image).__name__)} "
            f"{getattr(image, 'shape', '')}"
        )
    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)
    kornia.io.write_image(Path(path), t.contiguous())


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG at its bit depth: 16-bit files as ``uint16`` (bit-exact), 8-bit ones as ``uint8`` RGB.

    Unlike Pillow, which opens 16-bit RGB files as 8-bit without a warning, nothing is lost; palette and grey
    8-bit files are expanded to RGB.

    Args:
        path: The file.

    Returns:
        ``uint16`` or ``uint8`` array. Shape ``[H, W, C]`` (``C = 3``; 4 for 16-bit RGBA, 1 for 16-bit grey).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a decodable image.
    """
    from kornia.io import ImageLoadType, load_image

    img = load_image(Path(path), ImageLoadType.UNCHANGED)
    if img.dtype == torch.uint8:
        img = load_image(Path(path), ImageLoadType.RGB8)
    return img.permute(1, 2, 0).contiguous().numpy()


def npy_bytes(a: np.ndarray) -> bytes:
    """The bytes of ``a`` as an ``.npy`` file (no pickles)."""
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` (readable by :func:`numpy.load`) with fixed timestamps, so the bytes are reproducible."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, npy_bytes(arrays[name]))
    return buf.getvalue()


def json_bytes(obj: Any) -> bytes:
    """Indented, key-sorted UTF-8 JSON with a final newline (reproducible bytes)."""
    return (json.dumps(obj, indent=1, sort_keys=True, ensure_ascii=False) + "\n").encode()


def write_sample(out: str | Path, sample: Sample) -> None:
    """Write a sample's files atomically, the sidecar last (see the module docstring for the formats)."""
    out = Path(out)
    stem = f"{sample.index:06d}"
    for b, img in sample.images.items():
        name = f"{stem}{variant_suffix(b)}"
        q = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
        atomic_write(out / f"{name}.png", lambda tmp, q=q: write_png16(tmp, q))
        atomic_write(out / f"{name}.npy", npy_bytes(img))
    if sample.geometry:
        atomic_write(out / f"{stem}_geometry.npz", npz_bytes(sample.geometry))
    atomic_write(out / f"{stem}.json", json_bytes(sample.metadata))


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
        "reflectance": [M, L], "coverage": sparse CSR [H·W, F], "background": [H, W]}``, and for a gathered sample
        ``"shading"``: the facets' corners, the view, the gather's settings and the light mix (sun direction, sky or
        uniform ambient and its weight) that rebuild the image's per-pixel model.
    """
    z = np.load(source) if isinstance(source, (str, Path)) else source
    areas = torch.from_numpy(np.asarray(z["areas"])).to(dtype)
    n = areas.shape[0]
    idx = torch.from_numpy(np.asarray(z["ff_indices"]).astype(np.int64))
    mat = torch.zeros(n, n, dtype=dtype)
    mat[idx[0], idx[1]] = torch.from_numpy(np.asarray(z["ff_values"])).to(dtype)
    bg = torch.from_numpy(np.asarray(z["background"])).to(dtype)
    ci = torch.from_numpy(np.asarray(z["coverage_indices"]).astype(np.int64))
    cov = sparse_matrix(ci[0], ci[1], torch.from_numpy(np.asarray(z["coverage_values"])).to(dtype), (bg.numel(), n),
                        dtype)
    out: dict[str, Any] = {
        "form_factors": FormFactors(mat, areas),
        "light_factor": torch.from_numpy(np.asarray(z["light_factor"])).to(dtype),
        "material": torch.from_numpy(np.asarray(z["material"]).astype(np.int64)),
        "reflectance": torch.from_numpy(np.asarray(z["reflectance"])).to(dtype),
        "coverage": cov,
        "background": bg,
    }
    if "corners" in z:  # a gathered sample: what rebuilds its per-pixel model (training.refine uses it)
        view, gather, amb = np.asarray(z["view"]), np.asarray(z["gather"]), np.asarray(z["ambient"])
        out["shading"] = {
            "corners": torch.from_numpy(np.asarray(z["corners"])).to(dtype),
            "is_triangle": torch.from_numpy(np.asarray(z["is_triangle"]).astype(bool)),
            "view": {"eye": view[0:3].tolist(), "target": view[3:6].tolist(), "up": view[6:9].tolist(),
                     "fov_deg": float(view[9]), "height": int(view[10]), "width": int(view[11])},
            "supersample": int(gather[0]), "samples": int(gather[1]), "stride": int(gather[2]),
            "edge_supersample": int(gather[3]) if gather.size > 3 else None,  # absent: uniform (before 0.2.0)
            "sun": torch.from_numpy(np.asarray(z["sun"])).to(torch.float64),
            "sky": bool(amb[0]), "ambient_weight": float(amb[1]),
        }
    return out
