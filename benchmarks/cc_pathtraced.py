"""A colour-constancy test set path-traced by Mitsuba 3, each image with its geometry file.

The scenes, views and sun + sky light are drawn by the generator (:func:`torch_interreflect.training.render_sample`,
seed :data:`TEST_SEED`, never used for training): V-grooves, W folds and rooms open on one side with one or two
blocks. Only samples whose ambient light is a sky are kept (the generator's other ambient, a uniform irradiance on
every facet whatever it sees, has no path-traced counterpart). Then, per sample (``numpy.random.default_rng([
TEST_SEED, i, 1])``):

- **illuminant**: with probability :data:`P_OUTSIDE`, a spectrum from a family the training never draws
  (:data:`OUTSIDE_FAMILIES`: LEDs, high-pressure lamps, FL3.x, colour-science's measured lamps; blackbodies at
  2000–2500 K or 8000–10000 K; CIE daylight at 10000–20000 K), else the generator's own draw;
- **reflectances**: each material, with probability :data:`P_OUTSIDE`, a smooth random spectrum outside the
  training's PCA family: ``sigmoid(c₀x² + c₁x + c₂)``, ``x = (λ − 550 nm) / 150 nm`` (the form of Jakob & Hanika
  2019), clipped to the generator's [0.02, 0.95].

Mitsuba 3 (``llvm_ad_spectral``) renders the image: the facets' meshes (one per material, one-sided ``diffuse``),
a ``directional`` sun of irradiance ``(1 − a) S(λ)`` and a ``constant`` sky of radiance ``a S(λ) / π`` (the
generator's light mix ``g = a g_sky + (1 − a) g_sun``), a ``perspective`` sensor with the generator's view and a
``specfilm`` whose three bands are the camera's sensitivities, the ``path`` integrator with ``max_depth = −1``.
Every spectrum is a step function over the 10 nm bins of the grid, so Mitsuba solves the same discrete-wavelength
problem as the library; everything else (paths, visibility, per-pixel light, noise) is Mitsuba's. The scene is
centred and scaled to max |coordinate| 100 (radiance does not change; see ``_common/mitsuba.py``).

The folder has the generator's layout (``dataset.json``, ``000042.npy/.png/.json``, ``000042_geometry.npz``), so
:class:`torch_interreflect.training.GeneratedDataset` reads it, ``geometry=True`` included. The image is Mitsuba's
times an exposure (99th percentile → 0.9); the sidecar holds the spectra actually used, the illuminant's camera RGB
(the ground truth), ``"renderer"`` and, as a check of the two renderers against each other, ``"ours_vs_mitsuba"``:
the relative RMS difference between the library's final-gather image of the same spectra and Mitsuba's over the
covered pixels (noise included).

Run: ``python -m benchmarks.cc_pathtraced --count 200 --size 32`` (141 s for the 200 images on a 2-core CPU at
32 × 32 and 2,048 spp, 91 s of it Mitsuba's, the rest mostly the generator's render of every sample scanned). Writes
``out/cc-pathtraced-{size}-{spp}spp`` (not committed); ``benchmarks.colour_constancy --study`` renders it when
missing and scores every method on its first ``--pathtraced`` images. Why 2,048 spp: at 256 spp Mitsuba's noise
(about 4 % per pixel at 32 × 32) dominated what the refinement could not fit (see :data:`SPP`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from benchmarks._common import mitsuba as mr
from torch_interreflect import spectral
from torch_interreflect.camera import gathered_image, source_irradiance
from torch_interreflect.training import GeneratorConfig, Sample, load_geometry, render_sample
from torch_interreflect.training.config import CONFIG_FILE
from torch_interreflect.training.refine import gathered_model
from torch_interreflect.training.sample import load_resources
from torch_interreflect.training.storage import atomic_write, json_bytes, write_sample

#: Seed of the test scenes (training runs use small seeds).
TEST_SEED = 424242
#: Scene kinds of the test set.
SCENES = ("v_groove", "w_shape", "cornell")
#: Probability that the illuminant, and each material's reflectance, comes from outside the training families.
P_OUTSIDE = 0.5
#: Illuminant families of :func:`torch_interreflect.spectral.illuminant_library` the training never draws.
OUTSIDE_FAMILIES = ("LED", "HP", "FL3.x", "measured lamps")
#: Mitsuba samples per pixel. On the first 40 images, the library's render of the same spectra is 1.84 % per pixel
#: from Mitsuba's at 2,048 spp (median; 4.8 % at 256 spp, over 200), and the refinement started from the true
#: illuminant ends at a median of 1.37° (2.34° on the 256-spp images): at 256 spp Mitsuba's noise was most of what
#: the refinement could not fit.
SPP = 2048

__all__ = [
    "OUTSIDE_FAMILIES",
    "SCENES",
    "SPP",
    "TEST_SEED",
    "library_image",
    "mitsuba_image",
    "render_test_set",
    "testset_config",
]


# ------------------------------------------------------------------------------------------------ draws
def _outside_illuminant(rng: np.random.Generator, wl: torch.Tensor, library: tuple) -> tuple[torch.Tensor, dict]:
    spectra, names, fams = library
    kind = int(rng.integers(3))
    if kind == 0:
        t = float(rng.uniform(2000.0, 2500.0) if rng.uniform() < 0.5 else rng.uniform(8000.0, 10000.0))
        spd = spectral.illuminant(f"blackbody:{t!r}", wl)
        return spd, {"kind": "blackbody (outside)", "name": f"blackbody:{t:.0f}"}
    if kind == 1:
        cct = float(rng.uniform(10000.0, 20000.0))
        return spectral.illuminant(cct, wl), {"kind": "daylight (outside)", "name": f"D{cct:.0f}K"}
    pick = [i for i, f in enumerate(fams) if f in OUTSIDE_FAMILIES]
    i = pick[int(rng.integers(len(pick)))]
    return spectra[i].to(wl), {"kind": fams[i], "name": names[i]}


def _smooth_reflectance(rng: np.random.Generator, wl: torch.Tensor) -> tuple[torch.Tensor, dict]:
    c = rng.normal(0.0, (3.0, 3.0, 1.5))
    x = (wl.double() - 550.0) / 150.0
    r = torch.sigmoid(c[0] * x**2 + c[1] * x + c[2]).clamp(0.02, 0.95)
    return r, {"source": "sigmoid polynomial (outside)", "coefficients": [round(float(v), 6) for v in c]}


# ------------------------------------------------------------------------------------------------ Mitsuba
def mitsuba_image(geometry: dict, reflectance: torch.Tensor, spd: torch.Tensor, wavelengths: torch.Tensor,
                  sensitivities: torch.Tensor, spp: int = SPP, seed: int = 0) -> np.ndarray:
    """Mitsuba's camera-RGB image ``[H, W, 3]`` (float64) of a gathered sample's geometry under ``spd``.

    Args:
        geometry: :func:`~torch_interreflect.training.load_geometry` of a gathered sample with a sky ambient.
        reflectance: One spectrum per material ``[M, L]``.
        spd: Illuminant ``[L]``.
        wavelengths: Grid ``[L]`` (nm, uniform).
        sensitivities: Camera ``[3, L]``; the bands are ``S_l`` on each bin, so a pixel is ``Σ_l S_l L_l Δλ``,
            the library's camera model.
    """
    mi = mr.load_mitsuba("llvm_ad_spectral")
    sh = geometry["shading"]
    if not sh["sky"]:
        raise ValueError("only a sky ambient has a path-traced counterpart")
    wl = wavelengths.double().numpy()
    corners = sh["corners"].double().numpy()
    tri = sh["is_triangle"].numpy().astype(bool)
    material = geometry["material"].numpy()
    centre, scale = mr.auto_frame(corners)
    p = (corners - centre) * scale
    refl = reflectance.double().numpy()
    s = spd.double().numpy()
    a = sh["ambient_weight"]
    d: dict = {"type": "scene",
               "sun": {"type": "directional", "direction": [float(v) for v in sh["sun"]],
                       "irradiance": mr.spectrum_dict((1.0 - a) * s, wl, step=True)},
               "sky": {"type": "constant", "radiance": mr.spectrum_dict(a * s / math.pi, wl, step=True)}}
    for m in np.unique(material):
        verts, faces, base = [], [], 0
        for f in np.flatnonzero(material == m):
            verts.append(p[f, : 3 if tri[f] else 4])
            faces += [[base, base + 1, base + 2]] + ([] if tri[f] else [[base, base + 2, base + 3]])
            base += len(verts[-1])
        v = np.concatenate(verts).astype(np.float32)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "diffuse",
                                      "reflectance": mr.spectrum_dict(refl[m], wl, step=True)})
        mesh = mi.Mesh(f"material_{m}", len(v), len(faces), props)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(v.ravel())
        params["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
        params.update()
        d[f"material_{m}"] = mesh
    v = sh["view"]
    eye = ((np.asarray(v["eye"]) - centre) * scale).tolist()
    target = ((np.asarray(v["target"]) - centre) * scale).tolist()
    film = {"type": "specfilm", "width": v["width"], "height": v["height"], "rfilter": {"type": "box"}}
    for k in range(3):
        film[f"band{k:02d}"] = mr.spectrum_dict(np.maximum(sensitivities[k].double().numpy(), 0.0), wl, step=True)
    d["sensor"] = {"type": "perspective", "fov": v["fov_deg"], "fov_axis": "y", "film": film,
                   "to_world": mi.ScalarTransform4f().look_at(origin=eye, target=target, up=list(v["up"])),
                   "sampler": {"type": "independent", "sample_count": spp}}
    d["integrator"] = {"type": "path", "max_depth": -1, "hide_emitters": True}
    scene = mi.load_dict(d)
    return np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)[..., :3]


def library_image(geometry: dict, reflectance: torch.Tensor, spd: torch.Tensor, camera) -> np.ndarray:
    """The library's final-gather image ``[H, W, 3]`` of the same geometry and spectra (the generator's model,
    rebuilt as :func:`~torch_interreflect.training.refine_illuminant` rebuilds it)."""
    op, direct = gathered_model(geometry)
    r = reflectance.double()[geometry["material"]]
    E = source_irradiance(geometry["form_factors"], r, geometry["light_factor"][:, None] * spd[None].double())
    return gathered_image(op, r, E, spd.double(), camera, direct=direct).permute(1, 2, 0).numpy()


# ------------------------------------------------------------------------------------------------ the set
def testset_config(count: int, size: int) -> GeneratorConfig:
    """The generator configuration the test scenes are drawn with (its images are replaced by Mitsuba's)."""
    return GeneratorConfig(count=count, seed=TEST_SEED, scenes=SCENES, size=(size, size), bounces=(None,))


def _sample(config: GeneratorConfig, index: int, spp: int, library: tuple) -> Sample | None:
    """Sample ``index`` of the test set, or ``None`` when its ambient light is not a sky."""
    s = render_sample(config, index)
    if s.metadata["light"]["ambient"] != "sky":
        return None
    res = load_resources(config)
    wl, cam = res["wl"], res["camera"]
    rng = np.random.default_rng([TEST_SEED, index, 1])
    meta, geo = s.metadata, dict(s.geometry)
    spd = torch.tensor(meta["illuminant"]["spd"], dtype=torch.float64)
    ill = {k: v for k, v in meta["illuminant"].items() if k not in ("spd", "rgb", "rgb_normalized")}
    if rng.uniform() < P_OUTSIDE:
        spd, drawn = _outside_illuminant(rng, wl, library)
        ill = {"wavelengths": ill["wavelengths"], **drawn}
        spd = spd / spd.mean()
    refl = torch.from_numpy(geo["reflectance"]).double()
    mats = [dict(m) for m in meta["materials"]]
    for k in range(refl.shape[0]):
        if rng.uniform() < P_OUTSIDE:
            refl[k], drawn = _smooth_reflectance(rng, wl)
            mats[k] = {"name": mats[k]["name"], **drawn}
        mats[k]["reflectance"] = [round(float(v), 6) for v in refl[k]]
    geo["reflectance"] = refl.numpy().astype(np.float32)
    loaded = load_geometry(geo)
    t = time.perf_counter()
    image = mitsuba_image(loaded, refl, spd, wl, cam.sensitivities, spp=spp, seed=index)
    seconds = time.perf_counter() - t
    ours = library_image(loaded, refl, spd, cam)
    cov = loaded["background"].numpy() < 1.0
    diff = float(np.linalg.norm((ours - image)[cov]) / max(np.linalg.norm(image[cov]), 1e-300))
    p99 = float(np.quantile(image, 0.99))
    exposure = 0.9 / p99 if p99 > 0 else 1.0
    white = cam(spd[None] / math.pi)[0]  # a white diffuser's camera RGB: the ground truth
    rgb = {"rgb": [float(v) for v in white], "rgb_normalized": [float(v) for v in white / white.norm()]}
    meta = {**meta, "exposure": exposure, "materials": mats,
            "illuminant": {**ill, "spd": [round(float(v), 8) for v in spd], **rgb},
            "renderer": {"name": "mitsuba", "version": mr.load_mitsuba("llvm_ad_spectral").__version__,
                         "variant": "llvm_ad_spectral", "spp": spp, "seed": index, "seconds": round(seconds, 3)},
            "ours_vs_mitsuba": round(diff, 5)}
    return Sample(index, {None: (image * exposure).astype(np.float32)}, meta, geo)


def render_test_set(out: str | Path, count: int = 200, size: int = 32, spp: int = SPP, *,
                    progress: bool = True) -> Path:
    """Render (or complete) the path-traced test set of ``count`` sky-lit samples in ``out``; return ``out``.

    Samples already in ``out`` are kept (the folder is resumable and grows with ``count``); ``dataset.json`` lists
    the indices scanned, so :class:`~torch_interreflect.training.GeneratedDataset` finds every complete sample.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / CONFIG_FILE
    stored = json.loads(cfg_path.read_text()) if cfg_path.is_file() else {}
    done = stored.get("indices", [])
    config = testset_config(max(done, default=-1) + 1, size)
    if stored and stored.get("spp", 256) != spp:
        raise ValueError(f"{out} holds images path-traced at {stored.get('spp', 256)} spp, not the {spp} asked "
                         "for; use another folder")
    if stored and not GeneratorConfig.from_json(stored["generator"]).same_samples(config):
        have = GeneratorConfig.from_json(stored["generator"])
        raise ValueError(f"{out} holds samples of another generator configuration ({have.size[0]}x{have.size[1]}, "
                         f"edge rays {have.edge_supersample}) than size={size} asks with this version (edge rays "
                         f"{config.edge_supersample}); use another folder")
    library = spectral.illuminant_library(load_resources(config)["wl"])
    index = max(done, default=-1) + 1
    bar = tqdm(total=count, initial=min(len(done), count), disable=not progress, desc="path-traced test set")
    while len(done) < count:
        s = _sample(config, index, spp, library)
        if s is not None:
            write_sample(out, s)
            done.append(index)
            bar.update()
        index += 1
        content = {"generator": dataclasses.replace(config, count=index).to_json(), "indices": done,
                   "library": "torch_interreflect", "renderer": "mitsuba", "spp": spp}
        atomic_write(cfg_path, json_bytes(content))
    bar.close()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--count", type=int, default=200)
    p.add_argument("--size", type=int, default=32)
    p.add_argument("--spp", type=int, default=SPP)
    p.add_argument("--out", default=None, help="default: out/cc-pathtraced-{size}-{spp}spp")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = render_test_set(args.out or f"out/cc-pathtraced-{args.size}-{args.spp}spp", args.count, args.size, args.spp)
    diffs = [json.loads(f.read_text())["ours_vs_mitsuba"] for f in sorted(out.glob("[0-9]*[0-9].json"))]
    print(f"{out}: {len(diffs)} samples; library vs Mitsuba, relative RMS over covered pixels: median "
          f"{np.median(diffs):.4f}, 90th percentile {np.quantile(diffs, 0.9):.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
