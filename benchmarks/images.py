"""Images pixel by pixel against Mitsuba 3: final gather (``shading="gather"``) and flat shading vs a path tracer.

For each scene (V-groove, box corner, W fold, Cornell box, an open-top room) and one view, this library renders
a grey (mono, one wavelength) radiance image with :func:`torch_interreflect.camera.gather_operator` +
:func:`~torch_interreflect.camera.gathered_radiance` from the facet solve, both gathered and flat, and Mitsuba 3
renders the same scene with a ``perspective`` sensor of the same intrinsics (vertical fov, principal point at the
centre, box pixel filter), the ``path`` integrator (``max_depth=-1``, emitters hidden from the camera) and the same
light (``directional`` sun or ``constant`` sky). Scenes go to Mitsuba centred and scaled to max |coordinate| 100
(its ray offsets lose light near acute edges at 10 cm scale; see ``mitsuba_ref.py``); radiance does not change.

The reference is two independent Mitsuba renders of ``REF_SPP`` samples per pixel each (cached under
``benchmarks/references/images/``); their difference gives the reference's own per-pixel noise. Errors are
per-pixel relative RMSE over *interior* pixels (every ray through the pixel's corners, edges and sub-pixel centres
hits the front of facets in one plane: no silhouettes, no creases) and, apart, over the other covered pixels
(*edges*: silhouettes and creases). Mitsuba's time at our error is read off renders at 4, 16, 64 spp
(``error ∝ spp^-½``, reference noise taken out in quadrature).

Run: ``python benchmarks/images.py --quick`` (64 × 64, ~5 min on 2 busy cores) or without ``--quick``
(128 × 128). Writes ``benchmarks/results/images.md`` (``images_quick.md``) and ``images.png``.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

import torch_interreflect as ti
from benchmarks._common import HERE
from benchmarks._common import mitsuba as mr
from torch_interreflect.camera import View, gather_operator, gathered_radiance
from torch_interreflect.geometry import split_at_contacts
from torch_interreflect.geometry.raycast import RayCaster

REF_DIR = HERE / "references" / "images"
RESULTS = HERE / "results"
SUPERSAMPLE = 3
SAMPLES = 4


def _open_room() -> ti.Scene:
    room = ti.scenes.room(divisions=2, lamp=False, dtype=torch.float64)
    keep = room.material != room.material_names.index("ceiling")
    return ti.Scene.from_parts(room.corners[keep], room.is_triangle[keep], room.material[keep], room.material_names)


def scenes() -> dict[str, dict]:
    """name → scene, light (ours, Mitsuba), view (without size)."""
    half = math.radians(22.5)
    sun_vg = [-math.cos(half), 0.0, -math.sin(half)]
    diag = [-1 / math.sqrt(3)] * 3
    return {
        "vgroove45_sun": dict(scene=lambda: ti.scenes.v_groove(45.0, size=(0.09, 0.06), divisions=10,
                                                               dtype=torch.float64),
                              light=sun_vg, view=dict(eye=(0.12, -0.02, 0.10), target=(0.02, 0.045, 0.01),
                                                      fov_deg=45.0)),
        "box_corner_sun": dict(scene=lambda: ti.scenes.box_corner(1.0, 4, dtype=torch.float64), light=diag,
                               view=dict(eye=(2.2, 1.8, 1.6), target=(0.3, 0.3, 0.2), fov_deg=45.0)),
        "w_shape_sun": dict(scene=lambda: ti.scenes.w_shape(45.0, divisions=(5, 10, 5), dtype=torch.float64),
                            light=[0.0, 0.0, -1.0], view=dict(eye=(0.015, -0.08, 0.16), target=(0.015, 0.05, 0.02),
                                                              fov_deg=50.0)),
        "cornell_sky": dict(scene=lambda: ti.scenes.cornell_box(4, light=False, dtype=torch.float64), light="sky",
                            view=dict(eye=(0.278, 0.273, -0.8), target=(0.278, 0.273, 0.3), up=(0.0, 1.0, 0.0),
                                      fov_deg=40.0)),
        "room_open_sky": dict(scene=_open_room, light="sky",
                              view=dict(eye=(0.3, 0.3, 2.3), target=(2.2, 2.8, 0.6), fov_deg=60.0)),
    }


def reflectance(scene: ti.Scene) -> torch.Tensor:
    """Grey per material: 0.3, 0.55, 0.8 in turn. ``[F, 1]``."""
    m = scene.material if scene.material is not None else torch.zeros(scene.num_facets, dtype=torch.long)
    return (0.3 + 0.25 * (m % 3)).to(torch.float64)[:, None]


# ------------------------------------------------------------------------------------------------ ours
def ours(scene: ti.Scene, light, view: View) -> dict:
    t0 = time.perf_counter()
    scene = split_at_contacts(scene)[0]  # a block on a floor: the hidden part must not share the floor's light
    K = ti.form_factors(scene)
    g = ti.lights.light_geometry(scene, K, light) if light != "sky" else ti.lights.sky(
        scene, K, torch.ones(1, dtype=torch.float64))[:, 0]
    r = reflectance(scene)
    # the light's spectrum: sun irradiance 1 W/m², or sky radiance 1/π (an open upward plane gets 1), as in Mitsuba
    S = torch.full((1,), 1.0 / math.pi if light == "sky" else 1.0, dtype=torch.float64)
    E = ti.solve(K, r, g[:, None] * S)
    t_solve = time.perf_counter() - t0
    t0 = time.perf_counter()
    op = gather_operator(scene, view, light, supersample=SUPERSAMPLE, samples=SAMPLES, cache=False)
    t_kernel = time.perf_counter() - t0
    t0 = time.perf_counter()
    img = gathered_radiance(op, r, E, S)[0].numpy()
    t_img = time.perf_counter() - t0
    t0 = time.perf_counter()
    flat_op = gather_operator(scene, view, light, supersample=SUPERSAMPLE, shading="flat", cache=False)
    flat = gathered_radiance(flat_op, r, E, shading="flat")[0].numpy()
    t_flat = time.perf_counter() - t0
    return {"gather": img, "flat": flat, "t_solve": t_solve, "t_kernel": t_kernel, "t_image": t_img,
            "t_flat": t_flat, "facets": scene.num_facets, "fragments": op.num_fragments, "rays": op.info["rays"],
            "coverage": op.coverage.to_dense().sum(1).reshape(view.height, view.width).numpy()}


def interior_mask(scene: ti.Scene, view: View, s: int = SUPERSAMPLE) -> np.ndarray:
    """Pixels whose rays through corners, edge midpoints and sub-pixel centres all hit front faces of one plane."""
    sc = scene.to(torch.float64)
    size = float((sc.corners.reshape(-1, 3).amax(0) - sc.corners.reshape(-1, 3).amin(0)).norm())
    key = torch.round(torch.cat([sc.normals, (sc.normals * sc.centroids).sum(-1, keepdim=True) / size], 1) * 1e5)
    plane = torch.unique(key, dim=0, return_inverse=True)[1]
    offs = torch.linspace(-0.5, 0.5, 2 * s + 1, dtype=torch.float64)
    h, w = view.height, view.width
    us = (torch.arange(w, dtype=torch.float64)[:, None] + offs).reshape(-1)
    vs = (torch.arange(h, dtype=torch.float64)[:, None] + offs).reshape(-1)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")
    pin = view.pinhole()
    pts = pin.unproject(torch.stack([uu, vv], -1).reshape(1, -1, 2), torch.ones(1, uu.numel(), 1,
                                                                                dtype=torch.float64))[0]
    eye = torch.tensor(view.eye, dtype=torch.float64)
    d = pts - eye
    hit = torch.from_numpy(RayCaster(sc).first_hit(np.broadcast_to(eye.numpy(), d.shape), d.numpy()))
    front = (hit >= 0) & ((sc.normals[hit.clamp_min(0)] * d).sum(-1) < 0)
    pid = torch.where(front, plane[hit.clamp_min(0)], torch.full_like(hit, -1)).reshape(h, 2 * s + 1, w, 2 * s + 1)
    pid = pid.permute(0, 2, 1, 3).reshape(h, w, -1)
    return ((pid == pid[..., :1]).all(-1) & (pid[..., 0] >= 0)).numpy()


# ------------------------------------------------------------------------------------------------ Mitsuba
class MitsubaImage:
    def __init__(self, scene: ti.Scene, light, view: View, refl: np.ndarray | None = None) -> None:
        """``refl``: grey reflectance per facet ``[F]`` (default :func:`reflectance`)."""
        ml = mr.Sky(1.0 / math.pi) if light == "sky" else mr.Directional(tuple(light), 1.0)
        t0 = time.perf_counter()
        refl = reflectance(scene)[:, 0].numpy() if refl is None else np.asarray(refl, dtype=np.float64)
        self.ref = mr.MitsubaReference(scene, refl, ml)
        mi = self.mi = self.ref.mi
        eye = (np.asarray(view.eye) - self.ref.centre) * self.ref.scale
        tgt = (np.asarray(view.target) - self.ref.centre) * self.ref.scale
        self.sensor = mi.load_dict({
            "type": "perspective", "fov": view.fov_deg, "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=tgt.tolist(), up=list(view.up)),
            "film": {"type": "hdrfilm", "width": view.width, "height": view.height, "rfilter": {"type": "box"},
                     "pixel_format": "luminance"},
            "sampler": {"type": "independent", "sample_count": 4},
        })
        self.integrator = mi.load_dict({"type": "path", "max_depth": -1, "hide_emitters": True})
        self.build_seconds = time.perf_counter() - t0

    def render(self, spp: int, seed: int) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        img = np.array(self.mi.render(self.ref.scene, sensor=self.sensor, integrator=self.integrator, spp=spp,
                                      seed=seed), dtype=np.float64)[..., 0]
        return img, time.perf_counter() - t0


def reference(name: str, m: MitsubaImage, view: View, spp: int) -> dict:
    """Two renders of ``spp`` (seeds 1001, 2002), cached as ``references/images/{name}_{H}x{W}_{spp}.npz``."""
    path = REF_DIR / f"{name}_{view.height}x{view.width}_{spp}.npz"
    if path.exists():
        z = np.load(path)
        return {k: z[k] for k in z.files}
    a, ta = m.render(spp, seed=1001)
    b, tb = m.render(spp, seed=2002)
    REF_DIR.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, a=a, b=b, seconds=np.array(ta + tb))
    return {"a": a, "b": b, "seconds": np.array(ta + tb)}


def rel_rmse(x: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    ok = mask & (ref > 1e-6 * ref.max())
    return float(np.sqrt(np.mean(((x[ok] - ref[ok]) / ref[ok]) ** 2))) if ok.any() else float("nan")


def run_scene(name: str, spec: dict, size: int, ref_spp: int) -> dict:
    scene = spec["scene"]()
    small = ti.scenes.v_groove(60.0, divisions=1, dtype=torch.float64)  # warm-up: imports, Embree, first calls
    ours(small, [0.0, 0.0, -1.0], View((0.1, -0.05, 0.08), (0.03, 0.03, 0.0), height=4, width=4))
    view = View(**spec["view"], height=size, width=size)
    o = ours(scene, spec["light"], view)
    m = MitsubaImage(scene, spec["light"], view)
    m.render(4, seed=7)  # compile the kernels
    rf = reference(name, m, view, ref_spp)
    ref = 0.5 * (rf["a"] + rf["b"])
    interior = interior_mask(scene, view)
    edges = (o["coverage"] > 0) & ~interior
    noise = rel_rmse(0.5 * (rf["a"] - rf["b"]) + ref, ref, interior)  # per-pixel std. error of the mean of two
    row = {"scene": name, "facets": o["facets"], "size": size, "interior_px": int(interior.sum()),
           "edge_px": int(edges.sum()), "ref_spp": 2 * ref_spp, "ref_noise": noise, "ours": o, "ref": ref}
    level = float(np.median(ref[interior])) if interior.any() else float(ref.max())
    for k in ("gather", "flat"):
        row[f"{k}_err"] = rel_rmse(o[k], ref, interior)
        # edge pixels are partly covered (relative errors blow up where coverage is small): error / typical level
        row[f"{k}_edge_err"] = float(np.sqrt(np.mean(((o[k] - ref)[edges] / level) ** 2))) if edges.any() else 0.0
    # Mitsuba's error and time against spp; time at our gathered error (noise of the reference out)
    curve = []
    for i, spp in enumerate((4, 16, 64)):
        img, t = m.render(spp, seed=31 + i)
        curve.append((spp, t, rel_rmse(img, ref, interior)))
    row["mitsuba_curve"] = curve
    spp, t, e = curve[-1]
    e_clean = math.sqrt(max(e**2 - noise**2, 1e-30))
    target = math.sqrt(max(row["gather_err"] ** 2 - noise**2, (0.1 * noise) ** 2))
    row["mitsuba_spp_at_ours"] = spp * (e_clean / target) ** 2
    row["mitsuba_time_at_ours"] = t * (e_clean / target) ** 2
    row["mitsuba_build"] = m.build_seconds
    print({k: v for k, v in row.items() if k not in ("ours", "ref")}, flush=True)
    return row


def _out(r: dict, k: str) -> float:
    """Error with the reference's noise taken out in quadrature."""
    return math.sqrt(max(r[f"{k}_err"] ** 2 - r["ref_noise"] ** 2, 0.0))


def write(rows: list[dict], quick: bool) -> None:
    tag = "_quick" if quick else ""
    md = [
        "# Images against Mitsuba 3, pixel by pixel",
        "",
        f"Generated by `benchmarks/images.py{' --quick' if quick else ''}` on {os.cpu_count()} CPUs (shared; load "
        f"average {os.getloadavg()[0]:.1f} at the end), torch {torch.__version__}, Mitsuba "
        f"{__import__('mitsuba').__version__} llvm_ad_mono. See the script's docstring for the set-up.",
        "",
        f"Grey reflectance per material (0.3 / 0.55 / 0.8 in turn), one wavelength; {SUPERSAMPLE}×{SUPERSAMPLE} "
        f"sub-pixel rays, {SAMPLES}×{SAMPLES} visibility rays per blockable (point, facet) pair. Errors: per-pixel "
        "relative RMSE against the Mitsuba reference (its own per-pixel noise in the *ref. noise* column, included in "
        "the errors). *interior*: pixels whose rays all hit one plane's front; *edges*: the other covered pixels "
        "(silhouettes, creases), their RMSE relative to the median interior radiance (3×3 sub-pixel coverage "
        "against Mitsuba's exact box filter). Ours: *solve* = form factors + light + solve of the facets; "
        "*gather op* = rays, point kernel, visibility (once per scene, view and light); *image* = one image from a "
        "solved `E` (what a new reflectance or illuminant costs, besides the solve). Mitsuba at equal error: read "
        "off its error at 4/16/64 spp (`∝ spp^-½`, reference noise out in quadrature).",
        "",
        "| scene | facets | px (interior / edges) | ref. spp (noise) | gather: interior (noise out) | edges | "
        "flat: interior (noise out) | edges | ours: solve + gather op + image | Mitsuba at gather's error | "
        "Mitsuba 64 spp (error) |",
        "|---|---:|---|---|---:|---:|---:|---:|---|---|---|",
    ]
    for r in rows:
        o = r["ours"]
        _, t64, e64 = r["mitsuba_curve"][-1]
        md.append(
            f"| {r['scene']} | {r['facets']} | {r['size']}² ({r['interior_px']} / {r['edge_px']}) | {r['ref_spp']} "
            f"({100 * r['ref_noise']:.2f} %) | {100 * r['gather_err']:.2f} % (**{100 * _out(r, 'gather'):.2f} %**) | "
            f"{100 * r['gather_edge_err']:.2f} % | {100 * r['flat_err']:.2f} % ({100 * _out(r, 'flat'):.2f} %) | "
            f"{100 * r['flat_edge_err']:.2f} % | {o['t_solve']:.2f} + "
            f"{o['t_kernel']:.2f} + {o['t_image'] * 1e3:.0f} ms = {o['t_solve'] + o['t_kernel'] + o['t_image']:.2f} s "
            f"| {r['mitsuba_time_at_ours']:.2f} s ({r['mitsuba_spp_at_ours']:.0f} spp) | {t64:.2f} s "
            f"({100 * e64:.2f} %) |"
        )
    md += ["", f"![ours (gather), ours (flat), Mitsuba, relative difference](images{tag}.png)", ""]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"images{tag}.md").write_text("\n".join(md) + "\n")
    figure(rows, RESULTS / f"images{tag}.png")
    print("\n".join(md))


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 4, figsize=(12, 3 * len(rows)), squeeze=False)
    for i, r in enumerate(rows):
        ref, g, f = r["ref"], r["ours"]["gather"], r["ours"]["flat"]
        vmax = float(np.percentile(ref, 99.5)) or 1.0
        for j, (img, title) in enumerate(((g, "ours, gather"), (f, "ours, flat"), (ref, "Mitsuba"))):
            axes[i, j].imshow(np.clip(img / vmax, 0, 1) ** (1 / 2.2), cmap="gray", vmin=0, vmax=1)
            axes[i, j].set_title(f"{r['scene']}: {title}" if j == 0 else title, fontsize=9)
        diff = np.where(ref > 0, (g - ref) / np.maximum(ref, 1e-12), 0.0)
        im = axes[i, 3].imshow(diff, cmap="RdBu_r", vmin=-0.05, vmax=0.05)
        axes[i, 3].set_title(f"(gather − Mitsuba) / Mitsuba, ±5 %\ninterior RMSE {100 * r['gather_err']:.2f} %",
                             fontsize=9)
        fig.colorbar(im, ax=axes[i, 3], fraction=0.046)
        for a in axes[i]:
            a.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="64 × 64 (default 128 × 128)")
    p.add_argument("--only", nargs="*", default=None)
    p.add_argument("--ref-spp", type=int, default=None, help="samples per pixel of each of the two reference renders")
    a = p.parse_args(argv)
    size = 64 if a.quick else 128
    ref_spp = a.ref_spp or (4096 if a.quick else 8192)
    rows = [run_scene(n, s, size, ref_spp) for n, s in scenes().items() if not a.only or n in a.only]
    write(rows, a.quick)


if __name__ == "__main__":
    main()
