"""How noisy the ray-cast visibility of the moments is: a bound on the variance of each facet's row sum
``Σ_j F(i → j)`` (internal to the sky's moments, :mod:`torch_interreflect.light_moments`).

An occluded pair's moments are its exact unoccluded sums less a blocked part estimated from ``visibility_samples²``
jittered rays per outer point (:func:`~.moments.moment_form_factors`). Counted as ``n`` independent samples of a
blocked fraction ``β`` of the pair's exact form factor, that estimate has variance ``(A F_exact)² β (1 − β) / n``;
stratification only lowers it. The pairs are independent, so a facet's row sum has the sum of its pairs' variances.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .compiled import launch, loops
from .moments import MomentFormFactors

__all__ = ["row_variance"]


def row_variance(moments: MomentFormFactors) -> Tensor | None:
    """A binomial bound on the variance of each facet's row sum ``Σ_j F(i → j)`` of ``moments`` (straight from
    :func:`~.moments.moment_form_factors`, :func:`~.moments.resample_visibility` or :func:`~.moments.mean_moments`:
    the mean of two replicas counts the rays of both). ``0`` on facets without a ray-cast pair.

    Returns:
        ``[F]`` float64 on the CPU (dimensionless²), or ``None`` when ``moments`` do not hold their pairs' sums.
    """
    sums = moments.info.get("_sums")
    kern = loops("moments")
    if sums is None or kern is None:
        return None
    sc, setup, acc = sums
    out = np.zeros(sc.num_facets)
    sel = np.nonzero(setup["need"].numpy())[0].astype(np.int64)
    if sel.size == 0:
        return torch.from_numpy(out)
    counts = np.zeros(sel.size, dtype=np.int64)
    launch(kern.count_rays, sel, *setup["pairs"], *setup["rules"], setup["corners"], setup["normals"], setup["buf"],
           counts)
    ns = int(moments.info["visibility_samples"])
    replicas = max(1.0, float(moments.info["rays"]) / max(1, int(counts.sum()) * ns * ns))  # 2 for a mean
    exact = setup["exact"][setup["need_rank"][sel], 0, 0]
    blocked = exact - acc[sel, 0, 0]
    beta = np.clip(blocked / np.where(exact > 0, exact, 1.0), 0.0, 1.0)
    var = exact * exact * beta * (1.0 - beta) / np.maximum(counts * ns * ns * replicas, 1.0)
    areas = sc.areas.numpy()
    dom, tgt = setup["dom"].numpy()[sel], setup["tgt"].numpy()[sel]
    np.add.at(out, dom, var / areas[dom] ** 2)
    np.add.at(out, tgt, var / areas[tgt] ** 2)
    return torch.from_numpy(out)
