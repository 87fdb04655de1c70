"""The least work of a render on the quadratic basis: one solve of degree 2 on the scene's pieces, no planning.

``ti.render(..., accuracy=a)`` on a sun-lit scene splits the scene at contacts, computes the pieces' moments at the
quadrature tolerance of the request (:func:`~torch_interreflect.accuracy.moments_settings.moment_quadrature_tol`)
and the sun's moments, and solves; its estimate needs the same solve at degree 1 beside it, and a request it does
not meet there needs more leaves and rays. :func:`one_solve_seconds` times the first of these alone: no plan on this
basis and kernel can be faster, so Mitsuba's time at the requested error over it bounds the ratio any planner could
show (the accuracy benchmark's table of it).
"""

from __future__ import annotations

import time

import torch

from torch_interreflect.accuracy.moments_settings import moment_quadrature_tol
from torch_interreflect.formfactors import moment_form_factors
from torch_interreflect.geometry import split_at_contacts
from torch_interreflect.light_moments import light_moments
from torch_interreflect.solver.moments import solve_moments

__all__ = ["one_solve", "one_solve_seconds"]


def one_solve(p: dict, accuracy: float) -> torch.Tensor:
    """Degree-2 coefficients on the pieces of ``p["scene"]`` under its sun (``p`` as
    :func:`benchmarks.accuracy.problem` makes it), at the moments' quadrature tolerance for ``accuracy``.

    Shape: ``[pieces, 6, 1]``.
    """
    pieces = split_at_contacts(p["scene"])[0]
    G = moment_form_factors(pieces, 2, quadrature_tol=moment_quadrature_tol(accuracy))
    g = light_moments(pieces, G, p["light"], direction=True)
    refl = torch.full((pieces.num_facets,), float(p["r"]), dtype=pieces.dtype)
    return solve_moments(G, refl, g[:, :, None] * p["illuminant"])


def one_solve_seconds(p: dict, accuracy: float, repeats: int = 3) -> float:
    """The best wall time (s) of :func:`one_solve` over ``repeats`` warm calls (one call before them warms the
    compiled kernels); ``nan`` where the light is not a sun (a direction tensor)."""
    if not isinstance(p["light"], torch.Tensor):
        return float("nan")
    one_solve(p, accuracy)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        one_solve(p, accuracy)
        best = min(best, time.perf_counter() - t0)
    return best
