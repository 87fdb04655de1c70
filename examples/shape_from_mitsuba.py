"""Shape from interreflections against a path tracer: recover a V-groove's angle and a W fold's shape (and the
reflectance, jointly) from per-facet radiance that Mitsuba 3 rendered.

The observations ship with the repository (``benchmarks/references/*.npz``, converged Mitsuba 3 irradiance-meter
renders of every facet: ~3 million samples per facet, 0.03 % noise; see their ``.json`` sidecars): a 30° V-groove
under a low sun and the paper's W fold (valleys of 45°, inner plates 4 cm wide, the ridge occluding) under an
overhead sun, both grey with reflectance 0.9. The observation is the radiance ``r E / π`` of every facet.

The model is this library's, on the same mesh, with the shape parameters and the reflectance as tensors:
gradients reach them through the form factors (:func:`torch_interreflect.form_factors`, compiled adjoint), the
sun's cosines and the solver's adjoint. Fitted by L-BFGS on the relative squared error, with

- ``infinite``: the infinite-bounce model, and
- ``two-bounce``: ``E = E0 + F R E0``, the common approximation, and
- ``refined`` (V-groove): infinite bounces on the ~900 leaves that ``render(accuracy=1e-2)`` refines at the
  infinite fit (:meth:`~torch_interreflect.accuracy.Plan.for_geometry` moves them with the shape), fitted again.
  (The W fold needs ~10,000 leaves for 3e-3, about a minute per evaluation here, so it has no refined row.)

On the W fold the ridge occludes: the visible fractions and the sun's shadows are ray cast, and their gradient
comes from their moving shadow edges (``form_factors(visibility_grad_points=)``,
:func:`torch_interreflect.lights.sun_shadow_gradient`). Prints recovered against true values.

    python examples/shape_from_mitsuba.py
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

import torch_interreflect as ti

F64 = torch.float64
REFERENCES = Path(__file__).resolve().parents[1] / "benchmarks" / "references"


def observation(name: str) -> tuple[torch.Tensor, dict]:
    """Mitsuba's per-facet radiance ``[F]`` and the reference's description."""
    meta = json.loads((REFERENCES / f"{name}.json").read_text())
    E = torch.from_numpy(np.load(REFERENCES / f"{name}.npz")["irradiance"].astype(np.float64))
    return meta["reflectance"] * E / math.pi, meta


def groove(params: torch.Tensor, meta: dict) -> tuple[ti.Scene, torch.Tensor]:
    """The V-groove and its reflectance for ``params = (angle / 10°, logit r)``."""
    kw = meta["kwargs"]
    scene = ti.scenes.v_groove(10.0 * params[0], size=tuple(kw["size"]), divisions=kw["divisions"])
    return scene, torch.sigmoid(params[1])


def w_fold(params: torch.Tensor, meta: dict) -> tuple[ti.Scene, torch.Tensor]:
    """The W fold and its reflectance for ``params = (valley angle / 10°, inner width / cm, logit r)``."""
    scene = ti.scenes.w_shape(10.0 * params[0], inner=params[1] / 100.0, divisions=tuple(meta["kwargs"]["divisions"]))
    return scene, torch.sigmoid(params[2])


def radiance(scene: ti.Scene, r: torch.Tensor, meta: dict, bounces: int | None, refined=None) -> torch.Tensor:
    """Per-facet radiance ``[F]`` under the reference's sun (irradiance 1): solved on the facets, or on the leaves
    of ``refined`` (a :class:`torch_interreflect.accuracy.Plan`) moved onto ``scene``."""
    d = torch.tensor(meta["light"]["direction"], dtype=F64)
    rr = r.reshape(1, 1).expand(scene.num_facets, 1)
    if refined is not None:
        E = refined.for_geometry(scene).apply(rr, torch.ones(1, dtype=F64)).irradiance
    else:
        E0 = ti.lights.directional(scene, d, torch.ones(1, dtype=F64))  # [F, 1]
        E = ti.solve(ti.form_factors(scene), rr, E0, bounces=bounces)
    return (rr * E / math.pi)[:, 0]


def refinement(build, x: torch.Tensor, meta: dict, accuracy: float):
    """A plan of ``render(accuracy=)`` at the parameters ``x`` (leaves refined where the error is)."""
    scene, r = build(x.detach(), meta)
    d = torch.tensor(meta["light"]["direction"], dtype=F64)
    rr = r.reshape(1, 1).expand(scene.num_facets, 1)
    # the constant basis: its leaves follow the shape (Plan.for_geometry) and pass gradients to it
    return ti.accuracy.plan(scene, rr, d, torch.ones(1, dtype=F64), accuracy=accuracy,
                            wavelengths=torch.tensor([550.0], dtype=F64), basis="constant")


def fit(build, start: list[float], observed: torch.Tensor, meta: dict, bounces: int | None, steps: int,
        refined=None) -> dict:
    """Parameters that best explain ``observed`` with ``bounces`` (or on ``refined`` leaves), from ``start``."""

    def model(x: torch.Tensor) -> torch.Tensor:
        return radiance(*build(x, meta), meta, bounces, refined)

    x = torch.tensor(start, dtype=F64, requires_grad=True)
    opt = torch.optim.LBFGS([x], lr=1.0, max_iter=steps, tolerance_grad=1e-12, tolerance_change=1e-14,
                            line_search_fn="strong_wolfe")
    calls = [0]

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = ((model(x) / observed - 1.0) ** 2).mean()
        loss.backward()
        calls[0] += 1
        return loss

    t0 = time.perf_counter()
    opt.step(closure)
    with torch.no_grad():
        rms = float(((model(x) / observed - 1.0) ** 2).mean().sqrt())
    return {"x": x.detach(), "rms": rms, "evaluations": calls[0], "seconds": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--steps", type=int, default=40, help="L-BFGS iterations at most")
    p.add_argument("--accuracy", type=float, default=1e-2, help="the refined model's render(accuracy=)")
    args = p.parse_args(argv)
    results: dict[str, float] = {}
    logit = math.log(0.5 / 0.5)
    cases = [
        ("V-groove", "vgroove30_sun_r9", groove, [4.5, logit],
         lambda x: {"angle (°)": 10 * float(x[0]), "reflectance": float(torch.sigmoid(x[1]))},
         {"angle (°)": 30.0, "reflectance": 0.9}, True),
        ("W fold", "w_shape_sun_r9", w_fold, [6.0, 5.0, logit],
         lambda x: {"valley (°)": 10 * float(x[0]), "inner (cm)": float(x[1]),
                    "reflectance": float(torch.sigmoid(x[2]))},
         {"valley (°)": 45.0, "inner (cm)": 4.0, "reflectance": 0.9}, False),
    ]
    for title, name, build, start, read, truth, refine in cases:
        observed, meta = observation(name)
        fits: dict[str, dict] = {}
        print(f"{title}: {meta['num_facets']} facets, Mitsuba 3 ({meta['spp_total']:,} samples per facet); "
              f"start {read(torch.tensor(start, dtype=F64))}")
        print(f"  {'model':<11}" + "".join(f"{k:>14}" for k in truth) + f"{'rms residual':>14}{'evals':>7}{'s':>6}")
        print(f"  {'truth':<11}" + "".join(f"{v:>14.3f}" for v in truth.values()))
        models = (("infinite", None), ("two-bounce", 2)) + ((("refined", None),) if refine else ())
        for label, bounces in models:
            if label == "refined":  # infinite bounces on leaves refined to --accuracy at the infinite fit
                x = fits["infinite"]["x"]
                f = fit(build, x.tolist(), observed, meta, None, args.steps, refinement(build, x, meta, args.accuracy))
            else:
                f = fit(build, start, observed, meta, bounces, args.steps)
            fits[label] = f
            got = read(f["x"])
            print(f"  {label:<11}" + "".join(f"{v:>14.3f}" for v in got.values())
                  + f"{f['rms']:>14.2e}{f['evaluations']:>7d}{f['seconds']:>6.1f}")
            for k, v in got.items():
                results[f"{name}/{label}/{k}"] = v
            results[f"{name}/{label}/rms"] = f["rms"]
    return results


if __name__ == "__main__":
    main()
