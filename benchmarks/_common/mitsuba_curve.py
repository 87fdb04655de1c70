"""Mitsuba 3's time against error on a reference scene, timed in the calling run: the peer at its best for the
benchmarks that set our time against Mitsuba's (the batched irradiance-meter estimator, warm kernels, both of its
samplers, the cheaper one at each error).

Each point renders the reference's scene at ``spp`` samples per facet (:meth:`MitsubaReference.render_warm`,
three seeds, the median time and the RMS of the three errors) and adds the scene build once (a new geometry is
built once; the faster of the samplers' builds, since the first also pays Mitsuba's start-up). Errors are per-facet
relative RMS against the cached converged reference, its noise taken out in quadrature.
``benchmarks.speed_vs_error.time_at_error`` reads the ``(error, seconds)`` pairs at an error (log-log between
points, ``t ∝ e⁻²`` below the smallest error, on the curve's Pareto front: the cheaper sampler there).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from . import mitsuba as mr
from .report import debias, rel_errors

__all__ = ["SAMPLERS", "mitsuba_curve"]

#: Mitsuba's samplers tried at every sample count; the curve keeps the cheaper at each error.
SAMPLERS = ("independent", "multijitter")


def mitsuba_curve(ref: dict, spps: Sequence[int], samplers: Sequence[str] = SAMPLERS,
                  seeds: Sequence[int] = (11, 12, 13)) -> list[dict]:
    """Points ``{"sampler", "spp", "error", "seconds"}`` of Mitsuba on a cached reference (``error`` debiased,
    ``seconds`` = scene build + median warm render)."""
    spec = ref["settings"]
    scene = mr.build_scene(spec)
    noise = float(spec["rel_noise_rms"])
    built, build = {}, math.inf
    for sampler in samplers:
        t0 = time.perf_counter()
        built[sampler] = mr.MitsubaReference(scene, spec["reflectance"], mr.make_light(spec["light"]),
                                             sampler=sampler, origin=spec.get("mitsuba_origin"))
        build = min(build, time.perf_counter() - t0)  # the first build also pays Mitsuba's start-up
    out = []
    for sampler, m in built.items():
        m.render(16, seed=1)  # compiles the kernels (cached on disk afterwards)
        for spp in spps:
            errs, secs = [], []
            for seed in seeds:
                res = m.render_warm(spp, seed=seed)
                errs.append(rel_errors(res.irradiance, ref["irradiance"])[0])
                secs.append(res.seconds)
            raw = float(np.sqrt(np.mean(np.square(errs))))
            out.append({"sampler": sampler, "spp": int(spp), "error": debias(raw, noise), "raw": raw,
                        "seconds": build + float(np.median(secs))})
    return out
