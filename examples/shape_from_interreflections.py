"""Shape from interreflections: recover a V-groove's opening angle and its reflectance from one observation.

The oldest use of interreflection in vision (Nayar, Ikeuchi & Kanade 1991): in a concave shape the light that
bounces between the facets depends on the shape, so the shading of a uniformly lit groove (no shading cue from the
light's direction) tells its angle, jointly with its albedo.

Ground truth: a grey V-groove (angle 50°, reflectance 0.6) under uniform light, rendered with infinitely many
bounces on a mesh ``--refine`` times finer than the model's and area-averaged onto the model's facets (per-facet
radiance, the "image"). The model is the same groove at the coarse mesh, with the angle and the reflectance as
parameters; gradients reach the angle through the form factors (:func:`torch_interreflect.form_factors` keeps the
graph of the corners of ``ti.scenes.v_groove(angle)`` for a tensor ``angle``) and the solver's adjoint. Both are
fitted by L-BFGS on the relative squared error, with

- ``infinite``: the infinite-bounce model (the one that generated the data, up to the mesh), and
- ``two-bounce``: ``E = E0 + F R E0``, the common approximation.

Prints recovered against true values and writes fit.png (observed and fitted radiance across the groove).

    python examples/shape_from_interreflections.py --out out/examples/shape_from_interreflections
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

import torch_interreflect as ti

F64 = torch.float64
TRUE_ANGLE = 50.0
TRUE_REFLECTANCE = 0.6


def radiance(angle: torch.Tensor, reflectance: torch.Tensor, divisions: tuple[int, int], bounces: int | None,
             refine: int = 1) -> torch.Tensor:
    """Per-facet radiance ``[F]`` of a grey groove under uniform light (``E0 = 1``), averaged back from a mesh
    ``refine`` times finer when ``refine > 1``."""
    coarse = ti.scenes.v_groove(angle, divisions=divisions)
    scene, parent = coarse.subdivide(refine)
    n = scene.num_facets
    r = reflectance.reshape(1, 1).expand(n, 1)
    E = ti.solve(ti.form_factors(scene), r, torch.ones(n, 1, dtype=F64), bounces=bounces)
    L = r * E / math.pi
    if refine > 1:
        L = coarse.average_to_parent(L, parent, scene)
    return L[:, 0]


def fit(observed: torch.Tensor, divisions: tuple[int, int], bounces: int | None, steps: int) -> dict[str, float]:
    """Angle (degrees) and reflectance that best explain ``observed`` under the model with ``bounces``."""
    # start from a wrong guess: 70°, reflectance 0.4 (parameters: angle in units of 10°, logit of the reflectance)
    a = torch.tensor(7.0, dtype=F64, requires_grad=True)
    z = torch.tensor(math.log(0.4 / 0.6), dtype=F64, requires_grad=True)
    opt = torch.optim.LBFGS([a, z], lr=1.0, max_iter=steps, tolerance_grad=1e-12, tolerance_change=1e-14,
                            line_search_fn="strong_wolfe")
    calls = [0]

    def closure() -> torch.Tensor:
        opt.zero_grad()
        model = radiance(10.0 * a, torch.sigmoid(z), divisions, bounces)
        loss = ((model / observed - 1.0) ** 2).mean()
        loss.backward()
        calls[0] += 1
        return loss

    t0 = time.perf_counter()
    opt.step(closure)
    with torch.no_grad():
        model = radiance(10.0 * a, torch.sigmoid(z), divisions, bounces)
        rms = float(((model / observed - 1.0) ** 2).mean().sqrt())
    return {"angle": float(10.0 * a.detach()), "reflectance": float(torch.sigmoid(z.detach())), "rms": rms,
            "evaluations": calls[0], "seconds": time.perf_counter() - t0, "model": model}


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("out/examples/shape_from_interreflections"))
    p.add_argument("--divisions", type=int, default=6, help="model facets across each plate (and along)")
    p.add_argument("--refine", type=int, default=3, help="the observation's mesh is this many times finer")
    p.add_argument("--steps", type=int, default=30, help="L-BFGS iterations at most")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    divisions = (args.divisions, args.divisions)
    t0 = time.perf_counter()
    truth = (torch.tensor(TRUE_ANGLE, dtype=F64), torch.tensor(TRUE_REFLECTANCE, dtype=F64))
    with torch.no_grad():
        observed = radiance(*truth, divisions, None, refine=args.refine)
    fits = {name: fit(observed, divisions, bounces, args.steps) for name, bounces in (("infinite", None),
                                                                                        ("two-bounce", 2))}
    print(f"observation: V-groove {TRUE_ANGLE:.1f}°, reflectance {TRUE_REFLECTANCE:.3f}, infinite bounces, "
          f"{2 * args.divisions ** 2 * args.refine ** 2} facets averaged onto {2 * args.divisions ** 2}")
    print(f"{'model':<12} {'angle (°)':>10} {'reflectance':>12} {'rms rel. residual':>18} {'evaluations':>12} "
          f"{'seconds':>8}")
    print(f"{'truth':<12} {TRUE_ANGLE:>10.3f} {TRUE_REFLECTANCE:>12.4f}")
    for name, f in fits.items():
        print(f"{name:<12} {f['angle']:>10.3f} {f['reflectance']:>12.4f} {f['rms']:>18.2e} {f['evaluations']:>12d} "
              f"{f['seconds']:>8.1f}")
    _plot(args.out / "fit.png", observed, fits, args.divisions)
    print(f"wrote {args.out / 'fit.png'} ({time.perf_counter() - t0:.1f} s)")
    results: dict[str, float] = {}
    for name, f in fits.items():
        key = "infinite" if name == "infinite" else "two_bounce"
        results[f"{key}_angle"] = f["angle"]
        results[f"{key}_reflectance"] = f["reflectance"]
        results[f"{key}_rms"] = f["rms"]
    return results


def _plot(path: Path, observed: torch.Tensor, fits: dict, n: int) -> None:
    """Radiance across the groove (mean over the rows along the hinge), observed and fitted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def across(L: torch.Tensor) -> torch.Tensor:
        # facet p * n * n + c * n + r: plate p, column c (0 at the hinge), row r; plate A from its outer edge in
        cols = L.reshape(2, n, n).mean(-1)
        return torch.cat([cols[0].flip(0), cols[1]])

    fig, ax = plt.subplots(figsize=(6, 3.5))
    x = torch.arange(2 * n) - n + 0.5
    ax.plot(x, across(observed), "ko", label="observed")
    for name, f in fits.items():
        ax.plot(x, across(f["model"]), "-", label=f"{name}: {f['angle']:.1f}°, r = {f['reflectance']:.3f}")
    ax.set_xlabel("facet column (0 = hinge)")
    ax.set_ylabel("radiance (W·sr⁻¹·m⁻²)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
