"""How many rays the quadratic planner casts (:mod:`.moments_plan`): the first and the largest counts of the
visibility's rays and of the sky's directions, the modelled cost of a replica cast at given counts, and the growth of
the counts that brings the measured ray-cast parts within what the request leaves, at the least modelled cost."""

from __future__ import annotations

import math

from ..formfactors.moments import MomentFormFactors
from ..light_moments import SkyRays

__all__ = [
    "FIRST_HIT_FACTOR",
    "LOOSE_SKY_ACCURACY",
    "LOOSE_SKY_SAMPLES",
    "MAX_SKY_SAMPLES",
    "MAX_VISIBILITY_SAMPLES",
    "RAY_MARGIN",
    "SKY_RAY_SECONDS",
    "SKY_SAMPLES",
    "VISIBILITY_PAIR_SECONDS",
    "VISIBILITY_RAY_SECONDS",
    "VISIBILITY_SAMPLES",
    "first_sky_samples",
    "grown",
    "more_samples",
    "sky_cost",
    "sky_points",
    "visibility_cost",
]

#: Directions per axis of the sky's ray-cast part at first, from half as many points per axis on each leaf
#: (:func:`sky_points`). Points and directions grow together: on the Cornell box's 50 pieces (independent replicas,
#: RMS per piece) 8 points × 16 directions gave 1.42 %, 16 × 32 0.41 % against 0.69 % for 8 × 64 (the same rays:
#: the points set a floor when only the directions grow). Odd counts did worse (11 × 11: 2.7 %; 12 × 12: 1.1 %).
SKY_SAMPLES = 16

#: Directions per axis at first instead, where the sky's two estimates are weighed and the request is at least
#: :data:`LOOSE_SKY_ACCURACY` (:func:`first_sky_samples`): a sixteenth of the rays. At r = 0.9 and 1e-2 (one run each,
#: render on one thread, against Mitsuba's reference) the Cornell box took 0.58 s for 0.27 % (estimated 0.89 %)
#: against 1.07 s for 0.062 %, the open room 5.6 s for 0.11 % against 8.0 s for 0.044 %. At 5e-3 the room gained as
#: much (5.3 s against 8.0 s) but on the Cornell box the rays' noise entered the halving estimate (0.72 % at 200
#: leaves against 0.38 %), so it refined to 236 leaves and grew the directions to 14: 1.47 s for 0.27 % against
#: 1.43 s for 0.056 %. Lower (the Cornell box at 2e-3: 55 s against 9.2 s) and with the escape count alone (dark
#: scenes: 3.4-57 s against 1.2-17 s) the noise of so few rays made the planner refine or grow the rays more.
LOOSE_SKY_SAMPLES, LOOSE_SKY_ACCURACY = 8, 1e-2

#: Most directions per axis of the sky's ray-cast part (16 points per axis then: 16² × 32² ≈ 262,000 rays per leaf,
#: the 8² × 64² of the directions-only growth this replaced).
MAX_SKY_SAMPLES = 32

#: Margin on the sample counts chosen from the measured ray-cast parts (each falls as one over its count per axis).
RAY_MARGIN = 1.2

#: Visibility rays per side of the target from each outer point of an occluded pair, at first and at most: while
#: the measured ray-cast parts keep the total above the request, the rays and the sky's directions grow, each by the
#: factor that brings its part down at the least cost (:func:`more_samples`).
VISIBILITY_SAMPLES, MAX_VISIBILITY_SAMPLES = 3, 12

#: Modelled seconds of a visibility replica per occluded pair (its outer points; the exact sums are kept) and per
#: ray, and of the sky's replica per ray: the growth of the ray counts weighs the two parts by these, not by timing
#: them, so that a render is the same from run to run. Fitted on one thread to the replicas (their solve included) of
#: the Cornell box (r = 0.9 and 0.2, 200–380 leaves, 3,734–18,300 occluded pairs, 0.65–6.5 M visibility and
#: 2.9–34 M sky rays) and the W shape (162 leaves, 1,984 pairs, 0.16–2.6 M rays): the model is within 15 % of each
#: measured time (0.06–4.8 s). Only their ratios matter.
VISIBILITY_PAIR_SECONDS, VISIBILITY_RAY_SECONDS, SKY_RAY_SECONDS = 1e-5, 1.9e-7, 1.5e-7


def visibility_cost(moments: MomentFormFactors) -> float:
    """Modelled seconds of a visibility replica (``moments`` the resampled form factors: their
    ``info["occluded_pairs"]`` and ``info["rays"]``). A count of work, the same on every run
    (:data:`VISIBILITY_PAIR_SECONDS`)."""
    info = moments.info
    return VISIBILITY_PAIR_SECONDS * int(info["occluded_pairs"]) + VISIBILITY_RAY_SECONDS * int(info["rays"])


#: Cost of a first-hit ray over an escape (occlusion) ray: the escape leaves of a replica cast with ``rows=True``
#: (the sky's two estimates weighed) take first-hit rays. Measured on one thread, 50 pieces of the Cornell box, 16²
#: directions from 8² points: 89–90 ms against 49–51 ms.
FIRST_HIT_FACTOR = 1.8


def sky_cost(sky: SkyRays, samples: int) -> float:
    """Modelled seconds of the sky's replica ``sky`` cast at ``samples`` directions per axis (and :func:`sky_points`
    points per axis) on each of its leaves (:data:`SKY_RAY_SECONDS`; its escape leaves :data:`FIRST_HIT_FACTOR` times
    that where they were cast with ``rows=True``). From the scene's openings (``sky.opening_rays``), the rays those
    cast, as the square of ``samples``."""
    if sky.opening_rays is not None:
        return SKY_RAY_SECONDS * sky.opening_rays * samples**2
    escape = sky.escape_ids.numel() * (FIRST_HIT_FACTOR if sky.escape_back is not None else 1.0)
    return SKY_RAY_SECONDS * (escape + sky.back_ids.numel()) * samples**2 * sky_points(samples) ** 2


def first_sky_samples(accuracy: float, weighed: bool) -> int:
    """Directions per axis of the sky's first cast for a request: :data:`LOOSE_SKY_SAMPLES` where the two estimates
    are ``weighed`` and ``accuracy ≥ LOOSE_SKY_ACCURACY``, else :data:`SKY_SAMPLES`.

    Args:
        accuracy: The requested relative error. weighed: Whether the sky's two estimates are weighed.

    Returns:
        Directions per axis (points per axis: :func:`sky_points`).
    """
    return LOOSE_SKY_SAMPLES if weighed and accuracy >= LOOSE_SKY_ACCURACY else SKY_SAMPLES


def sky_points(samples: int) -> int:
    """Points per axis on each leaf for ``samples`` sky directions per axis (:data:`SKY_SAMPLES`)."""
    return max(1, samples // 2)


def more_samples(vis_part: float, sky_part: float, vis_cost: float, sky_cost: float,
                 left: float) -> tuple[float, float]:
    """Factors on the visibility rays per side and on the sky's rays per point and axis (its points per axis times
    its directions per axis) that bring the two measured ray-cast parts (each falling as one over its factor) within
    ``left`` at the least cost (each cost growing as its factor squared): ``f ∝ (part / cost)^(1/3)``, neither below
    1; infinite where one part alone exceeds ``left`` (``left > 0``)."""
    a = (vis_part / max(vis_cost, 1e-9)) ** (1 / 3)
    b = (sky_part / max(sky_cost, 1e-9)) ** (1 / 3)
    c = ((vis_part / a if a > 0 else 0.0) + (sky_part / b if b > 0 else 0.0)) / left
    fv, fs = max(1.0, c * a), max(1.0, c * b)
    if fv == 1.0 and sky_part > 0:  # one part needs no more samples: the other takes all that is left
        fs = sky_part / (left - vis_part) if left > vis_part else math.inf
    elif fs == 1.0 and vis_part > 0:
        fv = vis_part / (left - sky_part) if left > sky_part else math.inf
    return fv, fs


def grown(count: int, factor: float, most: int) -> int:
    """``count`` times ``factor``, rounded up, within ``[count, most]`` (``most`` for an infinite factor)."""
    return most if not math.isfinite(factor) else min(most, max(count, math.ceil(count * factor)))
