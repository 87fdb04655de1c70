"""Settings of the geometry refinement (:func:`torch_interreflect.training.refine_illuminant`) on the path-traced
colour-constancy set, started away from the answer.

Each image of ``out/cc-pathtraced-{size}-{spp}spp`` (``python -m benchmarks.cc_pathtraced`` writes it) is refined
from its true illuminant's camera RGB turned by ``--offset`` degrees in a random direction (seeded by the image's
index), so every setting starts from the same points. A start at the true illuminant itself misleads: along the
ambiguity ``S · a ↔ R / a`` a weakly held fit stays where it starts. Errors are angular (degrees), median and mean
over the images and the median per scene kind. Settings are JSON keyword sets of ``refine_illuminant``; images are
split over ``--workers`` processes (one torch thread each).

``--image library`` refines, instead of Mitsuba's image, the library's own noise-free render of the same spectra and
geometry (the model the refinement fits, exactly): what is left is the fit's own error (the ``S · a ↔ R / a``
ambiguity where the interreflections are weak, and local minima), not the path tracer's noise or the model's
mismatch. ``--start-model PT`` starts each image from a trained model's estimate instead (as the study does, about
8° off for its networks; the model also lends its illuminant basis). ``--out`` defaults to
``results/cc_refine{_library}{_network}.md``.

    python -m benchmarks.cc_refine --count 100 --settings '{}' '{"optimizer": "lbfgs", "reflectance_prior": 1e-4}'
    python -m benchmarks.cc_refine --count 100 --image library
    python -m benchmarks.cc_refine --count 200 --start-model out/cc-study/study-seed0/physics.pt \
        --settings '{}' '{"stop_rtol": 1e-4}'
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

from torch_interreflect import spectral
from torch_interreflect.camera import Camera
from torch_interreflect.errors import AccuracyWarning
from torch_interreflect.training import GeneratedDataset, load_estimator, refine_illuminant
from torch_interreflect.training.metrics import angular_error

from .cc_pathtraced import library_image
from .colour_constancy import scene_kinds

RESULTS = Path(__file__).resolve().parent / "results"


def _start(rgb: torch.Tensor, index: int, degrees: float) -> torch.Tensor:
    """``rgb`` turned by ``degrees`` towards a random direction orthogonal to it (seeded by ``index``)."""
    v = torch.nn.functional.normalize(rgb.double(), dim=0)
    u = torch.randn(3, generator=torch.Generator().manual_seed(index), dtype=torch.float64)
    u = u - (u @ v) * v
    a = math.radians(degrees)
    return (math.cos(a) * v + math.sin(a) * u / u.norm()).clamp_min(1e-3)


def noise_free_image(root: Path, index: int, geometry: dict, camera: Camera) -> torch.Tensor:
    """The library's final-gather image ``[3, H, W]`` of image ``index``'s geometry and spectra (its sidecar's), scaled
    to a maximum of 1."""
    meta = json.loads((root / f"{index:06d}.json").read_text())
    spd = torch.tensor(meta["illuminant"]["spd"], dtype=torch.float64)
    refl = torch.tensor([m["reflectance"] for m in meta["materials"]], dtype=torch.float64)
    img = torch.from_numpy(library_image(geometry, refl, spd, camera)).permute(2, 0, 1)
    return (img / img.abs().max()).float()


def _work(root: str, indices: list[int], settings: dict, degrees: float, image: str = "mitsuba",
          start_model: str | None = None) -> list[float]:
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", AccuracyWarning)  # refine_illuminant's solves warn of closure errors, per image
    test = GeneratedDataset(root, None, indices, geometry=True)
    conf = {"camera": test.config.camera, "wavelengths": list(test.config.wavelengths)}
    cam = Camera.from_colour(conf["camera"], spectral.wavelengths(*conf["wavelengths"], dtype=torch.float64))
    net = None if start_model is None else load_estimator(start_model)
    out = []
    for it in test:
        img = it["image"] if image == "mitsuba" else noise_free_image(test.root, int(it["index"]), it["geometry"], cam)
        start = _start(it["illuminant"], int(it["index"]), degrees) if net is None else net.predict(img)[0].double()
        r = refine_illuminant(conf if net is None else net, img, it["geometry"], start, **settings)
        out.append(float(angular_error(r.rgb.float(), it["illuminant"])))
    return out


def run(root: str, count: int, settings: dict, degrees: float, workers: int, image: str = "mitsuba",
        start_model: str | None = None) -> dict:
    idx = json.loads((Path(root) / "dataset.json").read_text())["indices"][:count]
    t = time.perf_counter()
    e = np.empty(len(idx))
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as ex:
        futures = [ex.submit(_work, root, idx[k::workers], settings, degrees, image, start_model)
                   for k in range(workers)]
        for k, f in enumerate(futures):
            e[k::workers] = f.result()
    kinds = np.array(scene_kinds(GeneratedDataset(root, None, idx)))
    return {"settings": settings, "images": len(e), "median": float(np.median(e)), "mean": float(e.mean()),
            "kinds": {k: float(np.median(e[kinds == k])) for k in sorted(set(kinds))},
            "seconds": time.perf_counter() - t}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default="out/cc-pathtraced-32-2048spp")
    p.add_argument("--count", type=int, default=100, help="the first images of the set")
    p.add_argument("--offset", type=float, default=6.0, help="degrees between the start and the true illuminant")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--settings", nargs="+", default=[
        "{}", '{"reflectance_prior": 1e-4}', '{"optimizer": "lbfgs", "reflectance_prior": 1e-4}',
        '{"optimizer": "lbfgs", "reflectance_prior": 1e-5, "steps": 400}'])
    p.add_argument("--image", choices=("mitsuba", "library"), default="mitsuba",
                   help="Mitsuba's image, or the library's noise-free render of the same spectra")
    p.add_argument("--start-model", default=None, metavar="PT",
                   help="start from this trained model's estimate (and its illuminant basis) instead of --offset")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    stem = "cc_refine" + ("" if a.image == "mitsuba" else "_library") + ("" if a.start_model is None else "_network")
    out = a.out or str(RESULTS / f"{stem}.md")
    if not (Path(a.root) / "dataset.json").is_file():
        raise SystemExit(f"{a.root} has no path-traced set: run `python -m benchmarks.cc_pathtraced` first")
    rows = []
    for s in a.settings:
        rows.append(run(a.root, a.count, json.loads(s), a.offset, a.workers, a.image, a.start_model))
        print(rows[-1], flush=True)
    kinds = sorted({k for r in rows for k in r["kinds"]})
    flag = ("" if a.image == "mitsuba" else " --image library") + (
        "" if a.start_model is None else f" --start-model {a.start_model}")
    started = (f"started {a.offset:g}° off the true illuminant" if a.start_model is None
               else f"started from the estimate of `{a.start_model}`")
    lines = [f"# Geometry refinement settings, {started}",
             "", f"Generated by `python -m benchmarks.cc_refine{flag}` on "
             f"the first {a.count} images of `{a.root}` ({a.workers} processes, one thread each)"
             + ("" if a.image == "mitsuba" else ", each replaced by the library's noise-free render of the same "
                "spectra and geometry: the model the refinement fits, exactly") + ". Angular errors in degrees.", "",
             "| settings | images | median | mean | " + " | ".join(f"median, {k}" for k in kinds) + " | seconds |",
             "|---|---:|---:|---:|" + "---:|" * len(kinds) + "---:|"]
    for r in rows:
        per = " | ".join(f"{r['kinds'].get(k, float('nan')):.2f}" for k in kinds)
        lines.append(f"| `{json.dumps(r['settings'])}` | {r['images']} | {r['median']:.2f} | {r['mean']:.2f} | {per} | "
                     f"{r['seconds']:.0f} |")
    Path(out).write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
