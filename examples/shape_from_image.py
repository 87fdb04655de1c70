"""Shape from one path-traced image: recover a V-groove's opening angle and its reflectance from a 64 × 64 picture
that Mitsuba 3 rendered, silhouettes and shadows included.

The observation ships with the repository (``examples/data/vgroove40_sun_image64.npz`` and its ``.json``):
a grey V-groove (reflectance 0.8, opening 40°, 10 × 10 facets per plate) under a low sun that lets one plate shade
the other, seen from above the groove's open side, rendered by Mitsuba 3's path tracer (``path``, unbounded depth,
box pixel filter, 2 × 1,024 samples per pixel). Re-render it with ``--render`` (needs the bench extra).

The model renders the same view with this library: form factors, sun, solve, and the per-pixel final gather
(:func:`torch_interreflect.camera.render_view`). The scene is built from the angle tensor, so the image passes
gradients to it through the solved light, the per-pixel kernel and the edges in the image: the groove's outline
against the background, the hinge and the shadow's edge (:mod:`torch_interreflect.camera.image_grad`). Fitted by
L-BFGS on the mean squared pixel error, from 60° and 0.5, with

- ``infinite``: the infinite-bounce model;
- ``two-bounce``: the image gathers the direct light once (``E = E0 + F R E0`` at the pixels);
- ``outline``: the angle alone from the groove's outline (the observed pixels that are not background against the
  share of each pixel the model covers): only the edge terms carry this gradient, and ``outline, no edge terms``
  shows that without them the fit does not move.

    python examples/shape_from_image.py
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torch_interreflect as ti
from torch_interreflect.camera import View, gather_operator, gathered_radiance, render_view, source_irradiance
from torch_interreflect.camera.image_grad import image_gradient

F64 = torch.float64
DATA = Path(__file__).resolve().parent / "data"
NAME = "vgroove40_sun_image64"
TRUTH = {"angle": 40.0, "reflectance": 0.8, "divisions": 10}
SUN = [-0.3, 0.25, -0.55]  # the way the light travels: low over the open side, one plate shades the other
VIEW = dict(eye=(0.17, -0.035, 0.09), target=(0.025, 0.045, 0.015), fov_deg=37.0)


def render_observation(size: int, spp: int) -> None:
    """Render the observation with Mitsuba 3 (two renders of ``spp``) and write it with its sidecar."""
    sys.path.insert(0, str(DATA.parents[1]))  # the repository root: the benchmarks' Mitsuba helpers
    from benchmarks.images import MitsubaImage

    view = View(**VIEW, height=size, width=size)
    scene = ti.scenes.v_groove(TRUTH["angle"], divisions=TRUTH["divisions"], dtype=F64)
    m = MitsubaImage(scene, SUN, view, np.full(scene.num_facets, TRUTH["reflectance"]))
    a, ta = m.render(spp, seed=1001)
    b, tb = m.render(spp, seed=2002)
    np.savez_compressed(DATA / f"{NAME}.npz", image=((a + b) / 2).astype(np.float32),
                        noise=(np.abs(a - b) / 2).astype(np.float32))
    meta = {"truth": TRUTH, "sun": {"direction": SUN, "irradiance": 1.0}, "view": {**VIEW, "height": size,
            "width": size}, "mitsuba": {"integrator": "path", "max_depth": -1, "spp": 2 * spp,
                                        "seconds": ta + tb, "variant": m.mi.variant()}}
    (DATA / f"{NAME}.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"wrote {DATA / NAME}.npz ({ta + tb:.1f} s of Mitsuba)")


def model_image(x: torch.Tensor, view: View, bounces: int | None) -> torch.Tensor:
    """The radiance image ``[H, W]`` for ``x = (logit(angle / 180°), logit r)`` under the sun (irradiance 1)."""
    scene = ti.scenes.v_groove(180.0 * torch.sigmoid(x[0]), divisions=TRUTH["divisions"])
    r = torch.sigmoid(x[1]).reshape(1, 1).expand(scene.num_facets, 1)
    d = torch.tensor(SUN, dtype=F64)
    K = ti.form_factors(scene)
    E0 = ti.lights.directional(scene, d, torch.ones(1, dtype=F64))
    E = source_irradiance(K, r, E0, bounces)  # what the gather gathers from: the full solution or E0 (two-bounce)
    return render_view(scene, r, E, torch.ones(1, dtype=F64), None, view, d)[0]


def silhouette(x: torch.Tensor, view: View, edges: bool) -> torch.Tensor:
    """The share of each pixel that the groove covers ``[H, W]`` (flat shading of value 1): only the edge terms
    carry its gradient (``edges=False`` drops them)."""
    scene = ti.scenes.v_groove(180.0 * torch.sigmoid(x[0]), divisions=TRUTH["divisions"])
    op = gather_operator(scene, view, shading="flat")
    grad = image_gradient(op, scene, shading="flat") if edges else None
    ones = torch.ones(scene.num_facets, 1, dtype=F64)
    img = gathered_radiance(op, ones, math.pi * ones, shading="flat", gradient=grad)[0]
    return img if edges else img + 0.0 * x[0]  # no edge terms: the coverage is a constant of the angle


def fit(model, observed: torch.Tensor, steps: int) -> dict:
    """L-BFGS on the mean squared pixel error (relative to the observation's mean square), from 60° / 0.5."""
    x = torch.tensor([math.log(60.0 / 120.0), 0.0], dtype=F64, requires_grad=True)
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=steps, tolerance_grad=1e-12, tolerance_change=1e-14,
                            line_search_fn="strong_wolfe")
    scale = observed.square().mean()
    calls = [0]

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = (model(x) - observed).square().mean() / scale
        loss.backward()
        calls[0] += 1
        return loss

    t0 = time.perf_counter()
    opt.step(closure)
    with torch.no_grad():
        img = model(x)
    return {"angle": 180 * float(torch.sigmoid(x[0].detach())), "reflectance": float(torch.sigmoid(x[1].detach())),
            "image": img.detach(), "rms": float(((img - observed).square().mean() / scale).sqrt()),
            "evaluations": calls[0], "seconds": time.perf_counter() - t0}


def figure(observed: torch.Tensor, fits: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 1 + len(fits), figsize=(3 * (1 + len(fits)), 3.2))
    vmax = float(observed.max())
    axes[0].imshow(observed.numpy(), cmap="gray", vmin=0, vmax=vmax)
    axes[0].set_title("Mitsuba (observed)")
    for ax, (name, f) in zip(axes[1:], fits.items(), strict=True):
        ax.imshow(f["image"].numpy(), cmap="gray", vmin=0, vmax=vmax)
        shape = f"{f['angle']:.2f}°" + ("" if name.startswith("outline") else f", r {f['reflectance']:.3f}")
        ax.set_title(f"{name}: {shape}", fontsize=9)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--steps", type=int, default=15, help="L-BFGS iterations at most")
    p.add_argument("--out", type=Path, default=Path("out/shape_from_image"))
    p.add_argument("--render", action="store_true", help="re-render the observation with Mitsuba 3 first")
    p.add_argument("--spp", type=int, default=1024, help="with --render: samples per pixel of each of two renders")
    args = p.parse_args(argv)
    if args.render:
        render_observation(64, args.spp)
    meta = json.loads((DATA / f"{NAME}.json").read_text())
    observed = torch.from_numpy(np.load(DATA / f"{NAME}.npz")["image"].astype(np.float64))
    view = View(**{k: tuple(v) if isinstance(v, list) else v for k, v in meta["view"].items()})
    mask = (observed > 0).to(F64)  # the groove's outline in the picture
    fits = {"infinite": fit(lambda x: model_image(x, view, None), observed, args.steps),
            "two-bounce": fit(lambda x: model_image(x, view, 2), observed, args.steps),
            "outline": fit(lambda x: silhouette(x, view, True), mask, args.steps),
            "outline, no edge terms": fit(lambda x: silhouette(x, view, False), mask, args.steps)}
    results: dict[str, float] = {}
    spp = meta["mitsuba"]["spp"]
    print(f"truth: {TRUTH['angle']:.1f}°, reflectance {TRUTH['reflectance']:.3f} (Mitsuba, {spp} samples per pixel)")
    for name, f in fits.items():
        refl = "" if name.startswith("outline") else f", reflectance {f['reflectance']:.3f}"
        print(f"  {name:>22}: {f['angle']:6.2f}°{refl}, rms {f['rms']:.4f} "
              f"({f['evaluations']} evaluations, {f['seconds']:.1f} s)")
        results.update({f"{name}/angle": f["angle"], f"{name}/reflectance": f["reflectance"], f"{name}/rms": f["rms"]})
    args.out.mkdir(parents=True, exist_ok=True)
    figure(observed, fits, args.out / "fit.png")
    print(f"wrote {args.out / 'fit.png'}")
    return results


if __name__ == "__main__":
    main()
