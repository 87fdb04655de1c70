"""Planning on the quadratic basis: how :func:`~torch_interreflect.accuracy.render` reaches a requested accuracy when
irradiance is a polynomial of degree 2 inside every leaf (``basis="quadratic"``, the default where it applies).

The scene is split at its contact lines (as for the constant basis); every piece is a leaf. Each step computes the
moments of the leaves (:func:`~torch_interreflect.formfactors.moment_form_factors`) and the light's
(:func:`~torch_interreflect.light_moments.light_moments`), solves on the quadratic basis and on its linear part
(the leading block of the same moments: the basis is hierarchical), and estimates the error of every user facet's
output as :data:`Q_EST` times the difference of the two. Measured on the accuracy benchmark's unoccluded scenes
(V-grooves at 30° and 45°, a box corner; 48 to 800 leaves), the degree-2 error is 0.17–0.22 of the degree-1 error
and 0.21–0.28 of their difference (RMS; 90 % of the facets under 0.54 of it), so ``Q_EST = 0.5`` leaves a margin of
about 2. Where the RMS estimate is above the discretisation's share, the user facets that carry the excess have all
their leaves split in four (:func:`~torch_interreflect.accuracy.leaves.select`), and the step repeats.

The estimate needs the light to be smooth over every leaf. Where a sun's shadow edge crosses a leaf, or a sky or
an area light reaches it through pairs that a third facet can block (penumbrae), a polynomial converges slowly,
the degree-2 output is hardly better than the degree-1 one and their difference no longer bounds the error (the
Cornell box under a sky, 50 leaves: 1.28 % from Mitsuba against 1.77 % for degree 1, a difference of 0.59 %; under
a sun at 800 leaves: 0.33 % from a 4 × finer solution against an estimate of 0.033 %; both measured while building
this, not in a committed benchmark). Contacts among occluders do the same to the interreflected light (the Cornell
box under uniform light at 1e-3: estimated 0.14 %, actual 0.38 %). On such scenes
(:func:`~.moments_settings.smooth_light` false, or a rough leaf found by the light's own shadow points) the planner
estimates by *halving* instead: the first level is solved, every leaf is split in four and solved again, and a user
facet's estimate is :data:`Q_HALVING` times the change of its output when its leaves were last split; the facets
carrying the excess are split again. No split where the first level's a-priori estimate
(:func:`~.moments_settings.rough_estimate`) holds and meets the share (the open room under a sky, see the README).
A first level whose degrees do not converge (:data:`~.moments_settings.Q_CONVERGED`) is planned by halving too.
When halving, facets that nearly touch (a gap under :data:`~.leaves.NEAR_RATIO` of a leaf's diameter) are split
together, and their estimate is inflated while their leaves are larger than that (:func:`~.leaves.unresolved_near`).

Rays (pairs that a third facet could block, and the sky's open part on their leaves where a facet's back may be in
view) are sampled. At the last step both are drawn again at the same counts with other seeds (replicas,
:func:`~torch_interreflect.formfactors.moments.resample_visibility` and
:func:`~torch_interreflect.light_moments.sky_rays`); the answer is the mean of the two replicas, and the change
of the output that each replica makes, over √2 (:data:`REPLICA_MARGIN`), is its part of the error
(``parts["light"]``, the two added; half the change of two replicas is the RMS error of their mean, and the rest is
a margin on so noisy a measure). It is not lowered by refinement. While it keeps the total above the
request, each count grows by the factor that brings its part down at the least cost (the costs modelled from counts
of pairs and rays, not timed, so that a render is the same bit for bit from run to run), and the replicas are drawn
again at the new counts.

Where the openings can be told and the rows are not exact, the sky's open part comes from them (``sky_rays``).
Under a sky, where a leaf's open part is counted from escaping rays, the same rays also give it as one minus the
moments' row sums (:func:`~torch_interreflect.light_moments.sky_estimates`), and every solve weighs the two per leaf
(:func:`~torch_interreflect.solver.solve_moments_sky`): the weight cancels the visibility rays' error where the
surroundings are as bright as the sky. Only where the largest reflectance can make them so (:data:`WEIGH_REFLECTANCE`;
:func:`_weighed`). The Cornell box at r = 0.9 and 5e-3: 1.7 s and 0.051 % from Mitsuba (212 leaves, the rays at
their first counts), against 8.8 s and 0.14 % (236 leaves, the rays grown to 12 per side and 26² directions).

Where the light is smooth, the first level that meets the discretisation's share also measures the ray-cast parts
(one replica each at the first counts). If they do not fit in what the share leaves of the request, the share is
lowered to what they leave (:data:`RAY_FIRST_SHARE` at least) and refinement goes on instead of the rays growing:
splitting the few leaves that carry a smooth error costs less than more rays on every occluded pair (the W shape
under a sun at 1e-3: 0.52 s against 0.92 s). Where the lowered share cannot be reached (the leaf or step caps),
the rays grow as before; where the share is not lowered, the replicas serve the ray-cast parts' first measure.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .._deprecation import moved_attribute
from ..formfactors.moments import MomentFormFactors, mean_moments, moment_form_factors, resample_visibility
from ..geometry.contacts import split_at_contacts
from ..geometry.scene import Scene
from ..light_moments import SkyRays, light_moments, sky_estimates, sky_rays
from ..lights import sun_direction
from ..solver.moments import solve_moments
from ..solver.sky import solve_moments_sky
from .leaves import Leaves, near_facets, relative_change, rms, select, split, to_user, unresolved_near
from .moments_settings import Q_CONVERGED, Q_EST, Q_HALVING, Q_LINEAR, kernel_part, rough_estimate, solver_part
from .ray_counts import (
    MAX_SKY_SAMPLES,
    MAX_VISIBILITY_SAMPLES,
    RAY_MARGIN,
    VISIBILITY_SAMPLES,
    first_sky_samples,
    grown,
    more_samples,
    sky_cost,
    sky_points,
    visibility_cost,
)
from .refine import Problem
from .report import AccuracyReport

#: Names that moved to :mod:`.moments_settings` (this release): they still resolve here, with a warning.
_MOVED = {name: "torch_interreflect.accuracy.moments_settings" for name in (
    "kernel_part", "moment_quadrature_tol", "polynomial_allowed", "smooth_light", "solver_part", "solver_tolerance")}


def __getattr__(name: str) -> Any:
    return moved_attribute(__name__, name, _MOVED)


__all__ = ["DEGREE", "HALVING_SHARE", "RAY_FIRST_SHARE", "REPLICA_MARGIN", "WEIGH_REFLECTANCE", "MomentRefinement",
           "leaf_light", "moment_report", "refine_moments"]

#: Degree of the basis the planner solves on.
DEGREE = 2

#: Largest reflectance from which the sky's two estimates are weighed (:func:`_weighed`).
WEIGH_REFLECTANCE = 1 / 3

#: Share of the request left to the discretisation where the light is rough (``halving``): the rest goes to the
#: ray-cast parts, which are large there (the Cornell box and the room at 5e-3: 24 s and 68 s with 0.7, against
#: 27 s and 114 s, both short of the request, with the 0.9 of smooth scenes; measured with ``Q_HALVING = 0.6``).
HALVING_SHARE = 0.7

#: Least share of the request the discretisation is held to when the ray-cast parts, measured at their first counts
#: on a level that met its share, do not fit beside it (smooth light only): the share is lowered to what they leave
#: (with :data:`RAY_MARGIN`) and refinement goes on instead of the rays growing, while that leaves at least this.
#: The W shape under a sun (r = 0.9) at 1e-3: 0.92 s growing the rays from 3 to 12 per side (162 leaves, 0.047 % from
#: Mitsuba), 0.52 s with the share lowered (228 leaves, 0.064 %). Where the light is rough it was mixed (the Cornell
#: box under a sky: 0.56–2.7× the time), so it is not done there.
RAY_FIRST_SHARE = 0.3

#: A ray-cast part is the change of the output that its replica makes, divided by this. Half the change is the RMS
#: error of the mean of the two replicas; one pair of replicas measures it noisily (the sky's part on the Cornell
#: box, 12 pairs: 0.4–2.5 times the error, pooled 0.85–0.97), and √2 keeps the margin that the single check before
#: the replicas had (its change was √2 times the error of the answer it checked).
REPLICA_MARGIN = math.sqrt(2.0)


@dataclass
class MomentRefinement:
    """The outcome of :func:`refine_moments`.

    Attributes:
        leaves: The solved leaves. K: Their moments. g: The light's moments ``[n, nb]``.
        est: Estimated discretisation error per user facet ``[F]``; ``ray``: the measured ray-cast part ``[F]``.
        iterations: Refinement steps; ``reason``: why refinement stopped short (``""`` when it met its share;
            ``"rough"``: handed back at the first level, whose degrees do not converge, to be planned by halving).
        history: Per step: leaves, estimate, seconds. rough: User facets whose leaves see a rough light ``[F]``.
        rows: Under a sky, the other estimate of its light ``[n, nb]`` where the two differ (``None`` elsewhere).
        h: The last solve's leaf averages of the gain ``[..., n, L]`` (for the plan's reflectance; ``Plan.apply``
            reuses them).
    """

    leaves: Leaves
    K: MomentFormFactors
    g: Tensor
    est: Tensor
    ray: Tensor
    iterations: int = 0
    reason: str = ""
    history: list[dict[str, float]] = field(default_factory=list)
    rough: Tensor | None = None
    rows: Tensor | None = None
    h: Tensor | None = None


def leaf_light(light: Any, user: Tensor, num_user: int) -> Any:
    """The light on the leaves: a per-user-facet factor or mask ``[F]`` follows each leaf's user facet."""
    if isinstance(light, Tensor) and light.ndim == 1 and light.numel() == num_user != 3:
        return light.to(user.device)[user]
    return light


def _outputs(pb: Problem, leaves: Leaves, h: Tensor) -> Tensor:
    """What the target is measured on, per user facet ``[..., F, C]``: the gain (irradiance over the illuminant)
    per wavelength, or camera RGB."""
    refl = pb.r[..., leaves.user, :]
    if pb.camera is not None:
        return to_user(pb.rgb_of(h, torch.arange(pb.grid.numel()), refl), leaves, pb.F)
    return to_user(h, leaves, pb.F)


@dataclass
class _Level:
    """One level: the moments it computed (``full``, degree 2) and those of the degree it settles on (``K``, with the
    light's moments ``g [n, nb]``), the per-user-facet output ``x`` at that degree, its estimate ``est [F]``,
    which user facets hold a leaf where the light is rough (a shadow edge crosses it, a sky or area light reaches it
    through blockable pairs), and under a sky its ray-cast part ``sky`` and, where the sky's open part is counted
    from escaping rays, its other estimate ``rows [n, nb]`` (:func:`~torch_interreflect.light_moments.sky_estimates`;
    the outputs weigh the two, :func:`~torch_interreflect.solver.solve_moments_sky`). ``light``: the light's moments
    of every degree and its rough leaves where they do not depend on the moments (a sun or a uniform light), for
    another level on the same leaves (:func:`_level`). ``h``: the solve's leaf averages of the gain ``[..., n, L]``."""

    full: MomentFormFactors
    K: MomentFormFactors
    g: Tensor
    x: Tensor
    est: Tensor
    rough: Tensor
    sky: SkyRays | None = None
    rows: Tensor | None = None
    light: tuple[Tensor, Tensor] | None = None
    h: Tensor | None = None

    @property
    def degree(self) -> int:
        return self.K.degree


def _level(pb: Problem, leaves: Leaves, share: float, seed: int = 0, sky_samples: int | None = None,
           visibility: int = VISIBILITY_SAMPLES, like: MomentFormFactors | None = None,
           degree: int | None = None, moments: MomentFormFactors | None = None,
           previous: MomentFormFactors | None = None, sky: SkyRays | None = None,
           light: tuple[Tensor, Tensor] | None = None, rough_first: bool = False) -> _Level:
    """Moments and light on ``leaves``; the outputs of degree 1 and 0, and of degree 2 unless the degree-1 estimate
    ``Q_LINEAR |x1 − x0|`` is within ``share``. ``like``: moments of these leaves whose unoccluded pairs are reused
    (only the occluded pairs' rays are drawn again,
    :func:`~torch_interreflect.formfactors.moments.resample_visibility`). ``degree``: only that degree's output (no
    estimate: a check of the rays). ``moments``: these leaves' moments, taken as they are (a check of the sky's
    directions alone). ``previous``: the moments of the leaves before their last split, made with the same settings:
    the pairs of two leaves kept by the split (``leaves.kept``) take their sums from there. ``sky``: the sky's
    ray-cast part already cast on these leaves (cast with ``sky_samples`` otherwise: :func:`_sky_start` when None).
    ``light``: ``_Level.light`` of a level on these leaves, taken instead of computing the light again.
    ``rough_first``: halving's first level: degree 2, estimated a priori (``rough_estimate``; ``inf`` where the
    degrees do not converge or a sun's shadow edge crosses a leaf). Else a first level (no ``previous``, ``like``,
    ``moments``) whose degrees do not converge (``Q_CONVERGED``) marks every user facet rough (planned by halving)."""
    t = time.perf_counter()
    if moments is not None:
        K = moments
    elif like is not None:
        K = resample_visibility(like, seed=seed, visibility_samples=visibility)
    else:
        reuse = None if previous is None or leaves.kept is None else (previous, leaves.kept)
        K = moment_form_factors(leaves.scene, DEGREE, quadrature_tol=pb.quadrature_tol, seed=seed,
                                visibility_samples=visibility, reuse=reuse)
    pb.seconds["form_factors"] += time.perf_counter() - t
    t = time.perf_counter()
    is_sun = sun_direction(pb.light, pb.F) is not None  # decided on the user's facets, not the leaves' count
    if sky is None and _is_sky(pb):
        sky_samples = _sky_start(pb) if sky_samples is None else sky_samples
        sky = sky_rays(leaves.scene, K, samples=sky_samples, points=sky_points(sky_samples), rows=_weighed(pb),
                       openings=True)
    if light is None:
        g, rough_leaf = light_moments(leaves.scene, K, leaf_light(pb.light, leaves.user, pb.F), rough=True,
                                      direction=is_sun, sky=sky)  # type: ignore[misc]
        g = g.to(device=pb.r.device, dtype=pb.r.dtype)  # light_moments works in float64 on the CPU
    else:
        g, rough_leaf = light
    # a sun's or a uniform light's moments need the leaves' basis alone, not the moments' rows
    keep = (g, rough_leaf) if is_sun or (isinstance(pb.light, str) and pb.light == "uniform") else None
    rows = None
    if sky is not None and sky.escape_back is not None and sky.escape_ids.numel():
        rows = sky_estimates(leaves.scene, K, sky=sky)[1].to(device=pb.r.device, dtype=pb.r.dtype)
    rough = torch.zeros(pb.F, dtype=torch.bool)
    rough[leaves.user.cpu()[rough_leaf]] = True
    pb.seconds["light"] += time.perf_counter() - t
    t = time.perf_counter()
    refl = pb.r[..., leaves.user, :]
    L = refl.shape[-1]

    def output(d: int) -> tuple[MomentFormFactors, Tensor, Tensor]:
        Kd = K.truncate(d)
        n = Kd.size
        if rows is None:
            h = solve_moments(Kd, refl, g[:, :n, None].expand(-1, -1, L), tol=pb.plan_tol)
        else:  # unit sky radiance per wavelength: the weights are ratios of radiances
            h = solve_moments_sky(Kd, refl, g[:, :n], rows[:, :n], refl.new_ones(L), tol=pb.plan_tol)
        return Kd, _outputs(pb, leaves, h[..., 0, :]), h[..., 0, :]

    def level(out: tuple[MomentFormFactors, Tensor, Tensor], est: Tensor) -> _Level:
        Kd, x, h = out
        n = Kd.size
        return _Level(K, Kd, g[:, :n], x, est, rough, sky, None if rows is None else rows[:, :n], keep, h)

    try:
        if degree is not None:
            return level(output(degree), torch.zeros(pb.F, dtype=torch.float64))
        out1 = output(1)
        x1, x0 = out1[1], output(0)[1]
        d10 = relative_change(x1, x0)
        linear = not rough_first and rms(Q_LINEAR * d10) <= share  # the linear basis meets the share
        first = all(v is None for v in (previous, like, moments))  # where the degrees' convergence is checked
        if linear and not first:
            return level(out1, Q_LINEAR * d10)
        out2 = output(2)
        x2 = out2[1]
        d21 = relative_change(x2, x1)
        converged = rms(d21) <= Q_CONVERGED * rms(d10)
        if rough_first:  # the first level of halving: its a-priori estimate, unknown (inf) where it does not hold
            est = rough_estimate(d10, d21)
            # a sun's shadow edge across a leaf: its error is in the light's moments, the same at every degree
            held = converged and not (is_sun and bool(rough_leaf.any()))
            return level(out2, est if held else torch.full_like(est, math.inf))
        if first and not converged:  # plan by halving
            rough.fill_(True)
        if linear:
            return level(out1, Q_LINEAR * d10)
        return level(out2, Q_EST * relative_change(x1, x2))
    finally:
        pb.seconds["solve"] += time.perf_counter() - t


def _is_sky(pb: Problem) -> bool:
    return isinstance(pb.light, str) and pb.light == "sky"


def _weighed(pb: Problem) -> bool:
    """Whether the sky's two estimates are weighed (``_Level.rows``): where the surroundings can be bright enough to
    matter. The weight is the radiance a facet sees over the sky's, at most ``r / (1 − r)`` (``r`` the largest
    reflectance); below :data:`WEIGH_REFLECTANCE` (a weight of at most 1/2) the escape count alone is kept. On the
    accuracy benchmark's sky-lit scenes at r = 0.2 (the Cornell box and the room at 1e-2 and 5e-3, one run each)
    weighing moved the error from Mitsuba by −7 % to +25 % and the time by −8 % to +49 %; at r = 0.9 it took the
    Cornell box at 5e-3 from 8.8 s (0.14 % from Mitsuba) to 1.7 s (0.051 %)."""
    return _is_sky(pb) and bool(pb.r.numel()) and float(pb.r.max()) >= WEIGH_REFLECTANCE


def _sky_start(pb: Problem) -> int:
    """The sky's directions per axis at first (:func:`~.ray_counts.first_sky_samples`)."""
    return first_sky_samples(pb.accuracy, _weighed(pb))


def refine_moments(pb: Problem, *, max_unknowns: int, max_iterations: int, show: bool,
                   t_start: float, halving: bool = False,
                   contact_split: tuple[Scene, Tensor] | None = None) -> MomentRefinement:
    """Refine until the estimated discretisation error is within its share of the request (module docstring).

    Args:
        pb: The planning problem (as :func:`~torch_interreflect.accuracy.plan` builds it).
        max_unknowns: Most leaves × basis functions (6 per leaf) solved.
        max_iterations: Most refinement steps.
        show: Show a progress bar.
        t_start: Start of the planning (for the history's seconds).
        halving: Estimate from the change of each user facet's output when its leaves are split
            (:data:`Q_HALVING`), not from the degrees' difference: where the light is rough
            (:func:`~.moments_settings.smooth_light`). Every user facet is split at least once, unless the first
            level's a-priori estimate already meets the share (:func:`_level`'s ``rough_first``).
        contact_split: ``split_at_contacts(pb.scene)`` already computed (the pieces, the first leaves, and their user
            facets); computed here when None.
    """
    pieces, piece_user = split_at_contacts(pb.scene) if contact_split is None else contact_split
    leaves = Leaves(pieces, piece_user.to(pb.scene.device))
    share = pb.accuracy * (pb.budget["discretisation"] + pb.budget.get("sparsification", 0.0))
    if halving:
        share = pb.accuracy * HALVING_SHARE
    share = min(share, pb.accuracy - kernel_part(pb) - solver_part(pb))
    met = share  # the share as first set: a lowered one that cannot be reached falls back to more rays
    max_leaves = max(pieces.num_facets, max_unknowns // 6)
    history: list[dict[str, float]] = []
    reason, it = "", 0
    bar = tqdm(total=max_iterations + 1, desc="render (quadratic basis)", disable=not show, leave=False)
    # halving: a user facet's error is unknown (inf) until its leaves are split, unless the a-priori estimate holds
    est = torch.full((pb.F,), math.inf, dtype=torch.float64)
    lv = _level(pb, leaves, share, rough_first=True) if halving else None
    near, raw = near_facets(pb.scene) if halving else None, est  # raw: before unresolved_near's factor (once each)
    if lv is not None and near is not None and rms(lv.est) <= share:  # the a-priori estimate meets the share
        raw = lv.est.cpu()
        est = unresolved_near(raw, leaves, near)
    previous: MomentFormFactors | None = None
    first: _Replicas | None = None  # the ray-cast parts at their first counts, measured once (smooth light)
    while True:
        if lv is None or not halving:
            lv = _level(pb, leaves, share, previous=previous)
            est = lv.est
            if bool(lv.rough.any()):  # the caller plans again by halving (plan._plan_quadratic)
                bar.close()
                return MomentRefinement(leaves, lv.K, lv.g, est.cpu(), torch.zeros(pb.F, dtype=torch.float64), it,
                                        "rough", history, lv.rough, lv.rows)
        disc = rms(est)
        history.append({"leaves": float(leaves.scene.num_facets), "estimated": disc,
                        "seconds": time.perf_counter() - t_start})
        bar.update(1)
        if disc <= share and not halving and first is None and _occluded(lv):
            first = _replicas(pb, leaves, lv, share, VISIBILITY_SAMPLES, _sky_start(pb))
            room = pb.accuracy - kernel_part(pb) - solver_part(pb) - RAY_MARGIN * rms(first.parts[0] + first.parts[1])
            if disc > room >= RAY_FIRST_SHARE * pb.accuracy:  # the rays would have to grow: refine instead
                share = room
                history[-1]["share"] = share
        if disc <= share:
            break
        if it >= max_iterations:
            reason = "" if disc <= met else f"max_iterations ({max_iterations})"
            break
        sel = select(leaves, est, share, max_leaves, near)  # with the facets that nearly touch those picked
        if sel is None:
            reason = "" if disc <= met else (
                f"max_facets ({max_unknowns} unknowns: {max_leaves} leaves of 6 basis functions)")
            break
        touched = torch.zeros(pb.F, dtype=torch.bool)
        touched[leaves.user[sel].cpu()] = True
        leaves = split(leaves, sel)
        previous = lv.full
        it += 1
        if halving:
            before = lv.x
            lv = _level(pb, leaves, share, degree=DEGREE, previous=previous)
            change = Q_HALVING * relative_change(lv.x, before).cpu()  # F values: kept on the CPU
            raw = torch.where(touched, change, torch.maximum(raw, change))  # a neighbour's split moves it too
            est = unresolved_near(raw, leaves, near)  # type: ignore[arg-type]
    bar.close()
    if first is not None and first.level is not lv:
        first = None  # measured on a level since refined
    lv, ray, est = _ray_parts(pb, leaves, lv, est, share, halving, history, t_start, first)
    return MomentRefinement(leaves, lv.K, lv.g, est.cpu(), ray.cpu(), it, reason, history,
                            None if halving else lv.rough, lv.rows, lv.h)


def _occluded(lv: _Level) -> bool:
    return bool(lv.full.info["occluded_facets"].any())


@dataclass
class _Replicas:
    """Replicas of the ray-cast parts on one level (``level``): the visibility's moments ``K`` and the sky's rays
    ``sky`` drawn with another seed, the parts they measure per user facet (visibility, sky) and their modelled
    costs."""

    level: _Level
    K: MomentFormFactors
    sky: SkyRays | None
    parts: list[Tensor]
    cost: list[float]


def _replicas(pb: Problem, leaves: Leaves, lv: _Level, share: float, vis: int, sky: int, seed: int = 1) -> _Replicas:
    """The visibility's rays (``vis`` per side) and the sky's (``sky`` directions per axis) drawn again with ``seed``
    on ``lv``; each part is the change of the output that its replica makes, over :data:`REPLICA_MARGIN`."""
    zero = torch.zeros(pb.F, dtype=torch.float64)
    parts, cost = [zero, zero.clone()], [0.0, 0.0]
    K_b = resample_visibility(lv.full, seed=seed, visibility_samples=vis)
    x_b = _level(pb, leaves, share, degree=lv.degree, moments=K_b, sky=lv.sky, light=lv.light).x
    cost[0] = visibility_cost(K_b)
    parts[0] = relative_change(x_b, lv.x).cpu() / REPLICA_MARGIN
    sky_b = None
    if lv.sky is not None and (lv.sky.escape_ids.numel() or lv.sky.back_ids.numel()):
        sky_b = sky_rays(leaves.scene, lv.full, samples=sky, points=sky_points(sky), seed=seed, rows=_weighed(pb),
                         openings=True)
        x_b = _level(pb, leaves, share, degree=lv.degree, moments=lv.full, sky=sky_b, light=lv.light).x
        cost[1] = sky_cost(sky_b, sky)
        parts[1] = relative_change(x_b, lv.x).cpu() / REPLICA_MARGIN
    return _Replicas(lv, K_b, sky_b, parts, cost)


def _ray_parts(pb: Problem, leaves: Leaves, lv: _Level, est: Tensor, share: float, halving: bool,
               history: list[dict[str, float]], t_start: float,
               first: _Replicas | None = None) -> tuple[_Level, Tensor, Tensor]:
    """The ray-cast parts at the last level, measured apart by replicas: the visibility's rays, and the sky's points
    and directions, drawn again at the same counts with other seeds; the result is the mean of both replicas. A
    part is the change its replica makes over √2 (:data:`REPLICA_MARGIN`). While they keep the total above the
    request, each count grows (:func:`~.ray_counts.more_samples`) and the replicas are drawn again. Returns the level
    of the mean, the ray-cast part per user facet ``[F]`` and the discretisation estimate ``est [F]`` (that of the last
    level solved unless ``halving``); appends each growth to ``history``. ``first``: the replicas at the first counts
    already drawn on this level."""
    ray = torch.zeros(pb.F, dtype=torch.float64)
    vis, sky = VISIBILITY_SAMPLES, _sky_start(pb)
    replica = 0
    while _occluded(lv):
        replica += 1
        rep = first if replica == 1 and first is not None else _replicas(pb, leaves, lv, share, vis, sky, replica)
        parts, cost, K_b, sky_b = rep.parts, rep.cost, rep.K, rep.sky
        ray = parts[0] + parts[1]
        left = pb.accuracy - rms(est) - kernel_part(pb) - solver_part(pb)
        # done when the parts fit; nothing to gain when every count is at its most, or when the discretisation
        # alone is above the request
        done = rms(ray) <= left or (vis >= MAX_VISIBILITY_SAMPLES and sky >= MAX_SKY_SAMPLES) or left <= 0
        if not done:
            more_vis, more_sky = more_samples(rms(parts[0]), rms(parts[1]), cost[0], cost[1], left / RAY_MARGIN)
            new_vis = grown(vis, more_vis, MAX_VISIBILITY_SAMPLES)
            # the sky's part falls as one over its rays per axis (points × directions): each count per axis grows by
            # the square root (kept even)
            new_sky = grown(sky, math.sqrt(more_sky), MAX_SKY_SAMPLES)
            new_sky += new_sky % 2
            done = (new_vis, new_sky) == (vis, sky)
        if done:
            sky_mean = lv.sky.mean(sky_b) if lv.sky is not None and sky_b is not None else lv.sky
            return (_level(pb, leaves, share, degree=lv.degree, moments=mean_moments(lv.full, K_b), sky=sky_mean,
                           light=lv.light),
                    ray, est)
        same_vis, same_sky = new_vis == vis, new_sky == sky
        vis, sky = new_vis, new_sky
        lv = _level(pb, leaves, share, sky_samples=sky, visibility=vis, like=None if same_vis else lv.full,
                    moments=lv.full if same_vis else None, degree=DEGREE if halving else None,
                    sky=lv.sky if same_sky else None, light=lv.light)
        est = est if halving else lv.est
        history.append({"leaves": float(leaves.scene.num_facets), "estimated": rms(est),
                        "seconds": time.perf_counter() - t_start, "visibility_samples": float(vis),
                        "sky_samples": float(sky)})
    return lv, ray, est


def moment_report(pb: Problem, st: MomentRefinement, method: str, solver_tol: float, t_start: float) -> AccuracyReport:
    """The :class:`AccuracyReport` of a plan on the quadratic basis: the discretisation estimate, the ray-cast part
    measured at the last step, and the quadrature tolerance as the kernel's bound (the dense solve is direct; CG
    stops at ``solver_tol``)."""
    solver = 0.0 if method == "dense" else solver_part(pb)
    parts = {"discretisation": rms(st.est), "form_factors": kernel_part(pb),
             "sparsification": 0.0, "solver": solver, "wavelengths": 0.0, "light": rms(st.ray)}
    total = sum(parts.values())
    per_facet = st.est + st.ray + (total - parts["discretisation"] - parts["light"])
    pb.seconds["total"] = time.perf_counter() - t_start
    F = pb.F
    return AccuracyReport(
        requested=pb.accuracy, estimated=total, estimated_max=float(per_facet.max()) if F else 0.0,
        per_facet=per_facet, parts=parts, reached=total <= pb.accuracy, leaves=st.leaves.scene.num_facets,
        leaves_per_facet=torch.bincount(st.leaves.user.cpu(), minlength=F), iterations=st.iterations,
        quadrature_tol=pb.quadrature_tol, sparsified=False, dropped=0.0, dropped_row_mass=0.0, method=method,
        bounces=None, solver_tol=solver_tol, wavelengths=pb.grid, wavelength_error=0.0, seconds=pb.seconds,
        history=st.history, extrapolated=False, degree=st.K.degree,
    )
