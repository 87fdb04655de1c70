"""``interreflect predict IMAGE… --model DIR``: illuminant estimates as JSON, and white-balanced previews.

Images: 16-bit PNGs (read bit-exactly with :func:`~torch_interreflect.training.read_png`, values / 65535), 8-bit
PNGs (/ 255; they must hold linear values, not sRGB) or ``.npy`` float arrays ``[H, W, 3]`` — linear RGB of the
model's training camera (see :mod:`torch_interreflect.training.estimator`). With ``--geometry`` a file
``<stem>_geometry.npz`` beside an image (the generator's format) is used when present: the network's estimate is
then refined through the interreflection model.

Writes ``<out>/predictions.json`` (per image: the file, the unit-norm illuminant RGB, whether geometry was used)
and ``<out>/<stem>_wb.png``: the image divided by the estimate per channel (von Kries), scaled to its 99th
percentile and gamma-encoded (1/2.2), 8-bit (a preview in camera RGB, without a colour matrix).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["add_predict_parser", "read_linear_image", "white_balanced_preview"]


def read_linear_image(path: str | Path) -> torch.Tensor:
    """``[3, H, W]`` float32 from a 16- or 8-bit PNG or a ``.npy`` ``[H, W, 3]`` array (see the module docstring).

    Raises:
        FileNotFoundError: no such file.
        ValueError: another format, or not three channels.
    """
    from ..training.storage import read_png

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no image at {p}")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        a = np.load(p, allow_pickle=False).astype(np.float32)
    elif suffix == ".png":
        raw = read_png(p)
        a = raw.astype(np.float32) / (65535.0 if raw.dtype == np.uint16 else 255.0)
    else:
        raise ValueError(f"{p}: expected a .png or .npy image; got {suffix or 'no suffix'}")
    if a.ndim != 3 or a.shape[2] < 3:
        raise ValueError(f"{p}: expected an RGB image [H, W, 3]; got shape {list(a.shape)}")
    return torch.from_numpy(np.ascontiguousarray(a[..., :3])).permute(2, 0, 1).contiguous()


def white_balanced_preview(image: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
    """``uint8 [3, H, W]``: ``image / rgb`` per channel, 99th percentile → 1, clipped, gamma 1/2.2."""
    wb = image / (rgb.to(image) * 3.0**0.5).clamp_min(1e-6)[:, None, None]
    q = float(torch.quantile(wb.amax(0).flatten().double(), 0.99)) or 1.0
    return ((wb / q).clamp(0.0, 1.0) ** (1.0 / 2.2) * 255.0 + 0.5).to(torch.uint8)


def add_predict_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``predict`` sub-command to an ``argparse`` sub-parsers object."""
    p = sub.add_parser("predict", help="estimate the illuminant of linear camera-RGB images with a trained model",
                       description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("images", nargs="+", help="16-bit PNG or .npy [H, W, 3] images (linear camera RGB)")
    p.add_argument("--model", required=True,
                   help="checkpoint file, or the --out folder of train-cc (physics.pt, else fc4_inf.pt, ...)")
    p.add_argument("--out", default="predictions", help="output folder (default: predictions)")
    p.add_argument("--geometry", action="store_true",
                   help="refine with <stem>_geometry.npz beside each image when present (slower)")
    p.add_argument("--bounces", choices=["inf", "1", "2"], default="inf",
                   help="light transport of the geometry refinement (default inf)")
    p.add_argument("--allow-version-mismatch", action="store_true",
                   help="load a checkpoint written by another library version")
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show the full traceback of an error")
    p.set_defaults(func=run_predict)
    return p


def run_predict(args: argparse.Namespace) -> int:
    """Run ``interreflect predict`` (see the module docstring)."""
    from ..training.estimator import load_estimator
    from ..training.storage import load_geometry

    est = load_estimator(args.model, allow_version_mismatch=args.allow_version_mismatch)
    images = [read_linear_image(p) for p in args.images]  # read all first: a bad file fails before any output
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bounces = None if args.bounces == "inf" else int(args.bounces)
    rows = []
    for path, img in zip(args.images, images, strict=True):
        geo_file = Path(path).with_name(Path(path).stem + "_geometry.npz")
        geo = load_geometry(geo_file) if args.geometry and geo_file.is_file() else None
        rgb = est.predict(img, geo, bounces=bounces)[0]
        preview = out / f"{Path(path).stem}_wb.png"
        import kornia.io

        kornia.io.write_image(preview, white_balanced_preview(img, rgb))
        rows.append({"image": str(path), "rgb": [round(float(v), 6) for v in rgb], "geometry": geo is not None,
                     "preview": str(preview)})
        print(f"{path}: illuminant RGB {' '.join(f'{v:.4f}' for v in rgb.tolist())}"
              f"{' (refined with geometry)' if geo is not None else ''}")
    doc = {"model": str(args.model), "camera": est.camera, "library_version": est.config.get("library_version"),
           "predictions": rows}
    (out / "predictions.json").write_text(json.dumps(doc, indent=1) + "\n")
    print(f"Wrote {out / 'predictions.json'} and {len(rows)} previews.")
    return 0
