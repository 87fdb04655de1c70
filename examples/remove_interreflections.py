"""Remove interreflections from images of a V-groove and of the W shape (known geometry and light).

Each scene is lit by a directional D50 light (with cast shadows) shining into it and observed with infinitely many
bounces by the Nikon 5100. The direct-only (one-bounce) image is estimated three ways (torch_interreflect.inverse):

- ``spectral``: from spectral radiance, ``B1 = B · E0 / (E0 + F B)`` — exact;
- ``channel``: the same formula per camera channel from RGB — an approximation for broad-band channels;
- ``basis``: reflectances recovered from RGB in the Mallett & Yuksel (2019) basis, then ``camera(R E0 / π)``.

Prints the relative RMS difference to the true direct-only RGB (the observed image itself for comparison) and
writes, per scene, observed.png, direct_true.png, direct_channel.png and direct_basis.png.

    python examples/remove_interreflections.py --out out/examples/remove_interreflections
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

import torch_interreflect as ti
from torch_interreflect.camera import project, to_srgb, white_balance
from torch_interreflect.inverse import remove_interreflections
from torch_interreflect.layers import RGBToSpectrum
from torch_interreflect.solver import radiance, solve


def _save(path: Path, image: torch.Tensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(path, image[0].permute(1, 2, 0).clamp(0, 1).numpy())


def _scenes(fine: bool) -> list[tuple[str, ti.Scene, list[str], tuple[float, ...], tuple[float, ...]]]:
    n = 10 if fine else 4
    groove = ti.scenes.v_groove(45.0, divisions=n, dtype=torch.float64)
    w = ti.scenes.w_shape(divisions=(n, 2 * n, n) if fine else (3, 6, 3), dtype=torch.float64)
    return [
        # (name, scene, ColorChecker patch per plate, viewing direction, light direction of travel)
        ("v_groove", groove, ["yellow", "neutral 8"], (0.92, -0.5, 0.38), (-0.8, 0.2, -0.6)),
        ("w_shape", w, ["red", "neutral 8", "neutral 8", "blue"], (0.0, -0.4, 1.0), (0.25, 0.15, -1.0)),
    ]


def rel_rms(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).pow(2).mean().sqrt() / b.pow(2).mean().sqrt())


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("out/examples/remove_interreflections"))
    p.add_argument("--coarse", action="store_true", help="fewer facets (for a quick run)")
    p.add_argument("--size", type=int, default=128)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    wl = ti.spectral.wavelengths(dtype=torch.float64)
    cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
    d50 = ti.spectral.illuminant("D50", wl)
    white = cam(d50[None] / math.pi)[0]
    results: dict[str, float] = {}
    print("relative RMS difference to the true direct-only camera RGB (per facet)")
    print(f"| {'scene':<9} | {'facets':>6} | {'observed':>8} | {'spectral':>8} | {'channel':>8} | {'basis':>8} |")
    print("|-----------|--------|----------|----------|----------|----------|")
    for name, scene, patches, view, light in _scenes(not args.coarse):
        out = args.out / name
        out.mkdir(parents=True, exist_ok=True)
        ff = ti.form_factors(scene)
        r = torch.stack([ti.spectral.reflectance(pn, wl) for pn in patches])[scene.material]
        E0 = ti.lights.directional(scene, torch.tensor(light), d50)
        L = radiance(solve(ff, r, E0, tol=1e-10), r)
        obs = cam(L)
        truth = cam(radiance(E0, r))
        est = {
            "spectral": cam(remove_interreflections(ff, L, E0)),
            "channel": remove_interreflections(ff, obs, E0, camera=cam),
            "basis": remove_interreflections(ff, obs, E0, camera=cam, basis=RGBToSpectrum(wl)),
        }
        errs = {"observed": rel_rms(obs, truth), **{k: rel_rms(v, truth) for k, v in est.items()}}
        for k, v in errs.items():
            results[f"{name}_{k}"] = v
        print(f"| {name:<9} | {scene.num_facets:>6} | {errs['observed']:8.4f} | {errs['spectral']:8.1e} | "
              f"{errs['channel']:8.4f} | {errs['basis']:8.4f} |")
        target = (scene.centroids * scene.areas[:, None]).sum(0) / scene.areas.sum()
        view_dir = torch.tensor(view, dtype=torch.float64)
        eye = target + 0.22 * view_dir / view_dir.norm()
        proj = project(scene, (eye, target), args.size, args.size, fov_deg=40.0, supersample=2)
        exposure = 1.0 / float(white_balance(proj(obs), white).max())
        for label, rgb in (("observed", obs), ("direct_true", truth), ("direct_channel", est["channel"]),
                           ("direct_basis", est["basis"])):
            _save(out / f"{label}.png", to_srgb(white_balance(proj(rgb), white), exposure=exposure))
    elapsed = time.perf_counter() - t0
    results["seconds"] = elapsed
    print(f"wrote PNGs under {args.out} in {elapsed:.1f} s")
    return results


if __name__ == "__main__":
    main()
