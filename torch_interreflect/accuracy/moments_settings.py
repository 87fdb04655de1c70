"""Settings of the quadratic planner (:mod:`.moments_plan`): when the polynomial basis applies, the factors of its
error estimates, the moments' quadrature tolerance and CG's for a request, and the allowances reported for the
kernel and the solver."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..formfactors.compiled import loops
from ..geometry.contacts import split_at_contacts
from ..geometry.scene import Scene
from ..light_moments import light_is_rough
from ..lights import sun_direction
from .leaves import near_facets
from .refine import Problem

__all__ = [
    "PROBE_ACCURACY",
    "PROBE_REFLECTANCE",
    "Q_CONVERGED",
    "Q_DIVERGING",
    "Q_EST",
    "Q_HALVING",
    "Q_LINEAR",
    "Q_ROUGH",
    "constant_probe_pays",
    "kernel_part",
    "moment_quadrature_tol",
    "polynomial_allowed",
    "rough_estimate",
    "smooth_light",
    "solver_part",
    "solver_tolerance",
]

#: The estimate of a user facet's error: this times the difference between its degree-2 and degree-1 outputs.
Q_EST = 0.5

#: The estimate of a degree-1 output: this times its difference from the degree-0 one. Measured on the benchmark's
#: unoccluded scenes and the W shape (48 to 800 leaves), the degree-1 error is 0.05–0.15 of that difference (RMS).
#: Where it meets the request the planner stops at degree 1 (half the moments' work, a solve 8 × cheaper).
Q_LINEAR = 0.3


#: The estimate of a user facet's error where the light is rough (``halving``): this times the change of its output
#: when its leaves were last split in four (and at least this times its change when a neighbour's were): the error
#: falling as the leaves' size to the power 1.4 (Richardson's ``1 / (2^1.4 − 1)``), the order fitted on the Cornell
#: box under a sky at r = 0.2 (the accuracy benchmark's finer solutions). With the sky from the openings the ray-cast
#: parts no longer hide a shortfall: at 0.5 (order 1.6) the Cornell box at r = 0.2 and 1e-2 / 5e-3 was 0.40 % / 0.40 %
#: from Mitsuba, estimated 0.37 % / 0.37 %; at 0.65 0.40 % / 0.36 %, estimated 0.45 % / 0.39 %, in 1.3 s each, and
#: 0.084 % / 0.10 % at 2e-3 / 1e-3 (4.7 s / 11 s; 3.0 s / 4.1 s at 0.5). r = 0.9: 0.059–0.089 % at 1e-2 … 2e-3 in
#: 0.7–1.1 s either way; at 1e-3 it warns (estimated 0.109 %, actual 0.080 %, 8.4 s).
Q_HALVING = 0.65

#: The estimate of the first level where the light is rough (``halving``), before any split: this times the larger
#: change of a user facet's output between degrees 0 and 1 and between 1 and 2 on the same leaves (``|x1 − x0|``
#: bounds the degree-2 error where each degree at least halves it: ``e1 ≤ e0 / 2`` gives ``e2 ≤ e1 ≤ |x1 − x0|``). It is
#: taken only where the degrees converge (:data:`Q_CONVERGED`) and no sun's shadow edge crosses a leaf (the light's
#: own quadrature error is the same at every degree). The discretisation's part of the degree-2 error (the rays at 48²
#: sky directions and 12 visibility rays per side, against Mitsuba) was 0.07 / 0.24 of the larger change on the open
#: room under a sky (r = 0.9 / 0.2) and 0.08 / 0.28 on the Cornell box; against ``subdivide(3)`` of the pieces, 0.19 on
#: the Cornell box under its area light at r = 0.9 (at 0.2 and 0.5 its degrees do not converge: 0.67, 0.52), 0.09 /
#: 0.05 under uniform light (r = 0.5 / 0.9), 0.17 under a sky (r = 0.5). So 0.5 keeps a margin of 1.8 over the largest;
#: the rays' own error is measured apart (the replicas). With 1.0 the room took 1.14 s at 1e-2 (r = 0.9), its rays
#: grown; with 0.5, 0.71 s.
Q_ROUGH = 0.5

#: Most a user facet's a-priori estimate (:func:`rough_estimate`) takes of its larger change between degrees where its
#: own degrees do not converge (``|x2 − x1| ≥ |x1 − x0|``): on the wall hung across a floor, where they do not, the
#: degree-2 error was 4–12 times ``|x2 − x1|``.
Q_DIVERGING = 12.0

#: Largest ratio of the degrees' changes, ``rms|x2 − x1| / rms|x1 − x0|``, at which their difference is taken to
#: bound the error (:data:`Q_EST`, :data:`Q_ROUGH`): the estimates assume each degree cuts the error severalfold.
#: Measured on the accuracy benchmark's scenes at their first level: 0.06–0.23 under a sun, 0.12–0.18 in the room and
#: 0.08–0.15 in the Cornell box under a sky. Where a facet sees both faces of another whose plane crosses it (a wall
#: hung 5 cm above a floor, under a sun or uniform light: a kink in the interreflected light inside the floor's leaf)
#: it was 0.86–3.0, and the degree-2 error was 4–12 times ``Q_EST |x2 − x1|``; there the planner estimates by halving.
Q_CONVERGED = 0.5


#: Largest reflectance from which ``basis="auto"`` skips its first look on the constant basis. That look's estimate
#: grows with the reflectance like the interreflected light: on the four held-out-style scenes of the accuracy
#: benchmark (V-grooves at 30° and 45°, a box corner, a W fold; 48-200 facets, under a sun) it was 1.9-4.0e-3 at
#: r = 0.3, 5.6-12.5e-3 at r = 0.5, 9.2-20e-3 at r = 0.6 and 14-32e-3 at r = 0.7: from 0.7 it met none of the
#: benchmark's requests (1e-2 and below), and at r = 0.9 it never met one there. It cost about a third of those
#: renders (21 of 78 ms on the 30° groove at 2e-3, one thread).
PROBE_REFLECTANCE = 0.7
#: Loosest request at which bright scenes skip that look (the benchmark's loosest, where it was measured).
PROBE_ACCURACY = 1e-2


def moment_quadrature_tol(accuracy: float) -> float:
    """Per-entry quadrature tolerance of the moments for a request: a hundredth of it, in ``[1e-8, 1e-5]``. Tighter
    than the constant basis needs (its orders grow slowly: on the 200-facet 30° V-groove the moments take 0.062 s
    at 1e-4 and 0.088 s at 1e-6), since the quadratic basis's discretisation error is small enough for a 1e-4
    kernel to show (0.069 % against 0.044 % at 1e-5 and below)."""
    return min(1e-5, max(1e-8, 1e-2 * accuracy))


def kernel_part(pb: Problem) -> float:
    """The allowance reported for the kernel's error: its tolerance amplified by the interreflections,
    ``tol / (1 − r_max)`` (at most 20 ×; ``r_max`` the largest planning reflectance). A measured allowance, not a
    bound: far pairs are integrated to
    :data:`~torch_interreflect.formfactors.moments.FAR_TOL_FACTOR` times the tolerance, and on the 200-facet V-groove
    the output moves by 5e-6 between tolerances 1e-5 and 1e-8."""
    r_max = float(pb.r.max()) if pb.r.numel() else 0.0
    return pb.quadrature_tol / max(1.0 - r_max, 0.05)


def solver_part(pb: Problem) -> float:
    """The allowance reported for the solver: CG's tolerance (:func:`solver_tolerance`), since a polynomial plan
    solves by dense Cholesky or CG, whichever the cost model picks at each solve."""
    return solver_tolerance(pb.accuracy)


def polynomial_allowed(basis: str, scene: Scene, light: Any) -> bool:
    """Whether the polynomial basis may be used: ``basis="quadratic"``, or ``"auto"`` unless gradients must reach the
    geometry (corners or a light direction that require grad: the moments are constants of the geometry) or the
    compiled loops are off. Under ``"auto"`` :func:`~torch_interreflect.accuracy.plan` then also needs the light
    smooth over every piece (:func:`smooth_light`), where the estimate holds.

    Raises:
        ValueError: ``basis`` is not ``"auto"``, ``"constant"`` or ``"quadratic"``.
    """
    if basis not in ("auto", "constant", "quadratic"):
        raise ValueError(f"basis must be 'auto', 'constant' or 'quadratic'; got {basis!r}")
    if basis != "auto":
        return basis == "quadratic"
    light_grad = isinstance(light, Tensor) and light.requires_grad
    return not (scene.corners.requires_grad or light_grad or loops("moments") is None)


def constant_probe_pays(reflectance: Tensor, accuracy: float, scene: Scene | None = None) -> bool:
    """Whether ``basis="auto"`` first solves once on the constant basis (kept where its a-priori estimate already
    meets the request: dark scenes, 30 ms against 0.2 s for the 200-facet grooves at r = 0.2): not where the largest
    reflectance is :data:`PROBE_REFLECTANCE` or more and the request :data:`PROBE_ACCURACY` or tighter (the range
    measured; looser requests keep the look, which can meet them there). Compared in the reflectance's own dtype:
    0.7 in float32 is 0.69999999, below the threshold. Nor where two facets of ``scene`` nearly touch
    (:func:`~torch_interreflect.geometry.gaps.near_pairs` with :data:`~.leaves.NEAR_RATIO`): the light between them
    varies on the scale of their gap, which the estimate from the facets' corners does not see (a wall hung 5 cm
    above a floor, uniform light, r = 0.5: 0.33 % off, estimated 0.037 %).

    Args:
        reflectance: Reflectance per facet and wavelength (``[F, L]``).
        accuracy: The requested relative error.
        scene: The user's scene (not checked for near pairs when None).

    Returns:
        True where the look is taken.
    """
    bright = bool(reflectance.numel()) and float(reflectance.max()) >= PROBE_REFLECTANCE
    if bright and accuracy <= PROBE_ACCURACY:
        return False
    return scene is None or not near_facets(scene)[0].numel()


def smooth_light(scene: Scene, light: Any, pieces: Scene | None = None) -> bool:
    """No rough light over any piece of the scene split at contacts
    (:func:`~torch_interreflect.light_moments.light_is_rough`: a sun's shadow edge, a sky or area light through
    blockable pairs), and no contact in a scene with blockable pairs: where something stands on something among
    occluders (the Cornell box's blocks), the interreflected light has the penumbrae that make a sky rough, and the
    estimate failed there under uniform light too (accuracy 1e-3: estimated 0.14 % against 0.38 % at 1,208
    leaves). The W fold (occluders, no contact) keeps the polynomial basis: 0.036 % from Mitsuba at 1e-3 with an
    estimate of 0.094 %. ``pieces``: the scene already split at contacts (split here when None). The blockable
    pairs are looked for only where there are contacts."""
    pieces = split_at_contacts(scene)[0] if pieces is None else pieces
    is_sun = sun_direction(light, scene.num_facets) is not None  # on the user's facets, not the pieces' count
    if light_is_rough(pieces, light, direction=is_sun):
        return False
    contacts = pieces.num_facets != scene.num_facets
    # a sky is rough exactly where a third facet can block a pair
    return not (contacts and light_is_rough(pieces, "sky"))


def solver_tolerance(accuracy: float) -> float:
    """CG's tolerance on the quadratic basis (the dense solve is direct): far below the request."""
    return max(1e-10, 1e-3 * accuracy)


def rough_estimate(d10: Tensor, d21: Tensor) -> Tensor:
    """The a-priori estimate of a first level where the light is rough, per user facet: :data:`Q_ROUGH` times its
    larger change between degrees ``m = max(d10, d21)`` where its own degrees converge (``q = d21 / d10 ≤``
    :data:`Q_CONVERGED`), else the geometric tail ``m q / (1 − q)``, at most :data:`Q_DIVERGING` ``m``. The
    scene-wide check (``rms d21 ≤ Q_CONVERGED rms d10``) is the caller's. On the open room under a sky (r = 0.2) two of
    its 114 facets had ``q`` of 0.54 and 0.64 and degree-2 errors of 0.90 % and 0.42 % against ``Q_ROUGH m`` of 0.66 %
    and 0.59 %; the tail gives 1.5 % and 2.1 %.

    Args:
        d10: Relative change of each user facet's output from degree 0 to 1 ``[F]``.
        d21: The same from degree 1 to 2 ``[F]``.

    Returns:
        The estimate per user facet ``[F]`` (float64).

    Shape:
        - d10, d21, output: ``[F]``
    """
    d10, d21 = d10.double(), d21.double()
    m = torch.maximum(d10, d21)
    q = d21 / d10.clamp_min(torch.finfo(torch.float64).tiny)
    tail = (q / (1 - q).clamp_min(1 / Q_DIVERGING)).clamp_max(Q_DIVERGING)  # q ≥ 1: Q_DIVERGING
    return m * torch.where(q <= Q_CONVERGED, torch.full_like(q, Q_ROUGH), tail)
