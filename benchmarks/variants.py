"""Many variants of one geometry: 100 reflectance × illuminant variants of each image scene, ours against Mitsuba 3.

The workload of a user who renders training data or fits materials: one geometry and one view, many materials and
light levels. Per scene of :mod:`benchmarks.images` (same views, same lights, grey, one wavelength):

- **ours**: contact split + form factors + light factor and the view's gather operator once, then every variant in
  one batched solve and one batched gather (``[N, F, 1]`` → ``[N, 1, H, W]``). Reported: the total, and what one
  more variant costs.
- **Mitsuba**: one render per variant (its scene parameters change in place, which we count as free). Its time per
  variant at our per-pixel error is measured on ``--check`` variants: each gets a converged reference (two renders
  of ``REF_SPP``, cached under ``benchmarks/references/images/``), our error against it (interior pixels, the
  reference's noise taken out), and Mitsuba's error at 64 spp, extrapolated with ``error ∝ spp^-½`` to our error.
  Mitsuba's time for N variants is N × the mean of those per-variant times.

A variant: grey reflectance per material drawn in [0.2, 0.9] and the light scaled by a factor in [0.5, 2]
(seeded). The light's scale does not change relative errors for either renderer; the reflectances do.

Run: ``python -m benchmarks.variants --quick`` (64 × 64, ~10 min on 2 cores with references to render) or without
``--quick`` (128 × 128). Writes ``benchmarks/results/variants.md`` (``variants_quick.md``).
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import torch

import torch_interreflect as ti
from benchmarks import images as im
from torch_interreflect.camera import View, gather_operator, gathered_radiance
from torch_interreflect.geometry import split_at_contacts


def variants(scene: ti.Scene, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Grey reflectance per facet ``[n, F, 1]`` (per material in [0.2, 0.9]) and light scales ``[n, 1]``."""
    g = torch.Generator().manual_seed(seed)
    m = scene.material if scene.material is not None else torch.zeros(scene.num_facets, dtype=torch.long)
    per_material = 0.2 + 0.7 * torch.rand(n, int(m.max()) + 1, generator=g, dtype=torch.float64)
    # its own stream, so variant k is the same whatever n
    scale = 0.5 + 1.5 * torch.rand(n, 1, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64)
    return per_material[:, m][..., None], scale


def ours(scene: ti.Scene, light, view: View, n: int) -> dict:
    """All ``n`` variants: times of the geometry, the gather operator and the batched variants; images ``[n, H, W]``."""
    t0 = time.perf_counter()
    split = split_at_contacts(scene)[0]
    K = ti.form_factors(split)
    g = ti.lights.light_geometry(split, K, light) if light != "sky" else ti.lights.sky(
        split, K, torch.ones(1, dtype=torch.float64))[:, 0]
    t_geometry = time.perf_counter() - t0
    t0 = time.perf_counter()
    op = gather_operator(split, view, light, supersample=im.SUPERSAMPLE, samples=im.SAMPLES, cache=False)
    t_op = time.perf_counter() - t0
    r, scale = variants(split, n)
    S = scale * (1.0 / math.pi if light == "sky" else 1.0)  # [n, 1]: sky radiance 1/π or sun irradiance 1, scaled
    t0 = time.perf_counter()
    E = ti.solve(K, r, g[None, :, None] * S[:, None, :])
    images = gathered_radiance(op, r, E, S)[:, 0]  # [n, H, W]
    t_variants = time.perf_counter() - t0
    return {"images": images.numpy(), "t_geometry": t_geometry, "t_op": t_op, "t_variants": t_variants,
            "facets": split.num_facets}


def check_variant(name: str, spec: dict, view: View, k: int, ref_spp: int, ours_image: np.ndarray,
                  interior: np.ndarray) -> dict:
    """Variant ``k`` against its own Mitsuba reference: our error and Mitsuba's time at it."""
    scene = spec["scene"]()
    r, scale = variants(scene, k + 1)
    m = im.MitsubaImage(scene, spec["light"], view, refl=r[k, :, 0].numpy())
    m.render(4, seed=7)  # compile
    rf = im.reference(f"{name}_variant{k}", m, view, ref_spp)
    ref = float(scale[k, 0]) * 0.5 * (rf["a"] + rf["b"])
    noise = im.rel_rmse(0.5 * (rf["a"] - rf["b"]) + 0.5 * (rf["a"] + rf["b"]), 0.5 * (rf["a"] + rf["b"]), interior)
    err = im.rel_rmse(ours_image, ref, interior)
    img, t = m.render(64, seed=77 + k)
    e64 = im.rel_rmse(float(scale[k, 0]) * img, ref, interior)
    e_clean = math.sqrt(max(e64**2 - noise**2, 1e-30))
    target = math.sqrt(max(err**2 - noise**2, (0.1 * noise) ** 2))
    return {"variant": k, "ours_err": err, "ref_noise": noise, "ours_err_out": math.sqrt(max(err**2 - noise**2, 0)),
            "mitsuba_64": (t, e64), "mitsuba_time_at_ours": t * (e_clean / target) ** 2}


def run_scene(name: str, spec: dict, size: int, n: int, checks: int, ref_spp: int) -> dict:
    scene = spec["scene"]()
    small = ti.scenes.v_groove(60.0, divisions=1, dtype=torch.float64)  # warm-up: imports, Embree, first calls
    ours(small, [0.0, 0.0, -1.0], View((0.1, -0.05, 0.08), (0.03, 0.03, 0.0), height=4, width=4), 2)
    view = View(**spec["view"], height=size, width=size)
    o = ours(scene, spec["light"], view, n)
    o1 = ours(scene, spec["light"], view, 1)  # what a single image costs, same path
    interior = im.interior_mask(scene, view)
    checked = [check_variant(name, spec, view, k, ref_spp, o["images"][k], interior) for k in range(checks)]
    mitsuba_each = float(np.mean([c["mitsuba_time_at_ours"] for c in checked]))
    ours_total = o["t_geometry"] + o["t_op"] + o["t_variants"]
    row = {"scene": name, "facets": o["facets"], "size": size, "n": n, "ours_total": ours_total,
           "ours_geometry": o["t_geometry"], "ours_op": o["t_op"], "ours_variants": o["t_variants"],
           "ours_one": o1["t_geometry"] + o1["t_op"] + o1["t_variants"], "checked": checked,
           "mitsuba_each": mitsuba_each, "mitsuba_total": n * mitsuba_each, "ratio": n * mitsuba_each / ours_total}
    print({k: v for k, v in row.items() if k != "checked"}, flush=True)
    return row


def write(rows: list[dict], quick: bool, ref_spp: int) -> None:
    path = im.RESULTS / ("variants_quick.md" if quick else "variants.md")
    load = os.getloadavg()[0]
    lines = [
        "# 100 variants of one geometry against Mitsuba 3",
        "",
        f"Generated by `benchmarks/variants.py` on {os.cpu_count()} CPUs (load average {load:.1f} at the end), torch "
        f"{torch.__version__}, Mitsuba {__import__('mitsuba').__version__} llvm_ad_mono. See the script's docstring "
        "for the set-up.",
        "",
        f"Per scene: {rows[0]['n']} variants (grey reflectance per material in [0.2, 0.9], light × [0.5, 2]), "
        f"{rows[0]['size']} × {rows[0]['size']} pixels. *ours*: geometry (contact split, form factors, light) + "
        "gather operator + all variants batched (solve and gather). *one more*: the batched part divided by the "
        f"variants. *checked*: our per-pixel error (interior pixels, reference noise out) on the first "
        f"{len(rows[0]['checked'])} variants against their own Mitsuba references ({2 * ref_spp} spp each), and "
        "Mitsuba's time per variant at that error (from 64 spp, `∝ spp^-½`).",
        "",
        "| scene | facets | ours: geometry + op + variants = total | one more | one image alone | checked errors "
        "(ours) | Mitsuba per variant at our error | Mitsuba, all variants | ratio |",
        "|---|---:|---|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        errs = " / ".join(f"{100 * c['ours_err_out']:.2f} %" for c in r["checked"])
        lines.append(
            f"| {r['scene']} | {r['facets']} | {r['ours_geometry']:.2f} + {r['ours_op']:.2f} + "
            f"{r['ours_variants']:.2f} = {r['ours_total']:.2f} s | {1000 * r['ours_variants'] / r['n']:.1f} ms | "
            f"{r['ours_one']:.2f} s | {errs} | {r['mitsuba_each']:.1f} s | {r['mitsuba_total']:.0f} s | "
            f"**{r['ratio']:.0f}×** |"
        )
    path.write_text("\n".join(lines) + "\n")
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="64 x 64 pixels (default 128 x 128)")
    p.add_argument("--variants", type=int, default=100, help="variants per scene (default 100)")
    p.add_argument("--check", type=int, default=3, help="variants checked against Mitsuba references (default 3)")
    p.add_argument("--ref-spp", type=int, default=None, help="samples per pixel of each of the two reference renders")
    p.add_argument("--only", nargs="*", help="scene names")
    a = p.parse_args(argv)
    size = 64 if a.quick else 128
    ref_spp = a.ref_spp or (4096 if a.quick else 8192)
    rows = [run_scene(n, s, size, a.variants, a.check, ref_spp) for n, s in im.scenes().items()
            if not a.only or n in a.only]
    write(rows, a.quick, ref_spp)


if __name__ == "__main__":
    main()
