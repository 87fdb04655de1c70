"""The refinement loop of :func:`~torch_interreflect.accuracy.plan`: solve, estimate, split, until the estimated
discretisation error meets its share.

The error of a user facet is estimated from the change of its average between two refinements,
``|x_k − x_{k−1}| · q/(1 − q)`` with ``q`` the observed ratio of successive changes (0.5, first order, until two
changes are known; clamped to ``[Q_MIN, Q_MAX]``). Facets whose form factors rest on ray-cast visibility always get
the slowest ratio, :data:`Q_MAX`.

After a refinement the returned averages are extrapolated (Richardson): ``x̂ = x + c (x − x_back)`` with ``x_back``
the solution on every user facet one split back (its leaves before its own last split; the previous level when every
facet split before was split again, else one more solve of that mesh) and ``c = q/(1 − q)``. Here ``q`` is one
ratio for the scene, the RMS of the last changes over the RMS of the ones before (on the facets with an earlier
change; :data:`Q_EXTRAPOLATE` until one is measured), clamped to ``[Q_MIN, Q_EXTRAPOLATE]``: per-facet ratios are too
noisy to extrapolate with. ``c = 0`` on facets with ray-cast visibility (they converge unevenly) and on facets never
split. Against the previous level instead of each facet's own split back, the facets that the last step left alone
lost their extrapolation: on the 30° V-groove at 1e-3 the error rose from 0.041 % to 0.117 % over one refinement.

``c ≤ 2/3`` (``Q_EXTRAPOLATE = 0.4``), the middle of ``c ∈ [1/3, 1]`` for convergence orders 2 to 1 (``q ∈ [1/4,
1/2]``). Measured after one refinement (error of the extrapolated values against the accuracy benchmark's finer
solution, RMS over the extrapolated facets, over the RMS change), on the 30° and 45° V-grooves, the box corner and
the W shape in sun at r = 0.9: 0.25 / 0.19 / 0.20 / 0.22 with ``c = 2/3``, against 0.42 / 0.42 / 0.52 / 0.42 with
``c = 1`` (the cap before).

The estimate of an extrapolated facet is at least how far ``c`` can be from the facet's own, times its change:
``|x_k − x_{k−1}| · (c(max(1/2, q_f)) − c)`` (:func:`_bracket`; ``q_f`` its measured ratio, 1/2 at its first split;
the fast end, second order, ``c = 1/3``, is never farther since ``c ≤ 2/3``), a third of the change at ``c = 2/3``.
At its first split that is all (no change of ``x̂`` is known yet); at the next ones the change of ``x̂``,
``|x̂_k − x̂_{k−1}| · q_f/(1 − q_f)``, is taken when it is larger. Without the bracket (``c ≤ 2/3`` and the change of
``x̂`` alone) the 30° V-groove at 1e-3 stopped at 0.101 % estimated at 0.083 %; with the change of the plain values
at the first split and ``c ≤ 1`` (the rule before) the first refinement never met 1e-2 there.

Known weakness: the extrapolation uses ``x − x_back``, and in later steps, where the other facets sit one split back
in the back mesh, that difference is several times the facet's own change ``|x_k − x_{k−1}|`` that the estimate
multiplies. Single facets can then be far above their estimate (the 30° V-groove at 1e-3: 0.18 % against 0.023 %)
while the RMS estimate stays above the RMS error. Multiplying ``x − x_back`` instead made the estimates grow with
refinement and stall it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..camera.sensor import Camera
from ..formfactors.operator import FormFactors
from ..geometry.contacts import split_at_contacts
from ..geometry.scene import Scene, area_average
from ..solver.api import solve
from . import apriori
from .kernel import leaf_kernel
from .leaves import Leaves, back_leaves, light_check, light_factor, relative_change, rms, select, split, to_user
from .wavelengths import interp_matrix, nested_subsets

__all__ = ["AMPLIFICATION", "Q_EXTRAPOLATE", "Q_MAX", "Q_MIN", "STALL", "Level", "Problem", "Refinement", "refine"]

#: Range of the convergence ratio ``q`` (successive changes of a facet's value when its level doubles) used in the
#: estimate ``change · q / (1 − q)``: first order gives 0.5, second order 0.25; slower convergence up to 0.8 is
#: believed, faster than 1/3 is not.
Q_MIN, Q_MAX = 1 / 3, 0.8

#: The ratio ``q`` taken for facets whose form factors rest on ray-cast visibility (their own measured ratio is
#: noisy): their estimate is ``q/(1 − q) = 4 ×`` their last change. Lower values were measured and not kept: with
#: 0.6 the accuracy benchmark's open room at 1e-2 took 3.6-4 s instead of 19-47 s and the W shape at 1e-3 46 s
#: instead of 82-100 s, all requests still met, but the Cornell box at r = 0.2 under 240 facets estimated 4.4 %
#: against an actual 7.2 % (10.4 % with 0.8), and 0.7 still 6.5 %: that scene's error comes from a neighbour's
#: discretisation, which the per-facet changes do not see.
Q_SAMPLED = Q_MAX

#: The largest ratio ``q`` used in the extrapolation ``x + q/(1 − q) · change``, and the one used before any is
#: measured: ``c = 2/3``, the middle of ``c ∈ [1/3, 1]`` for orders 2 to 1 (the estimate carries the rest).
Q_EXTRAPOLATE = 0.4

#: How many times the extrapolated output ``(1 + c) x_k − c x_{k−1}`` can carry one level's error from the other
#: sources (``1 + 2c`` at the largest ``c``): their tolerances are divided by it.
AMPLIFICATION = 1 + 2 * Q_EXTRAPOLATE / (1 - Q_EXTRAPOLATE)


#: Refinement stops (and warns) when two refinements lowered the estimated discretisation error by less than
#: this factor: the error is then not falling with the facet size (the Cornell box's visibility), and going on
#: would spend minutes without reaching the target.
STALL = 0.8


@dataclass
class Problem:
    """What the planner works on (all detached) and the time it spends per stage.

    Attributes:
        scene: The user's scene (``F`` facets). grid: Wavelengths ``[L]``. S: Illuminant ``[..., L]``.
        r: Reflectance ``[..., F, L]``. camera: For RGB targets, else ``None``. light: As :func:`render` takes it.
        accuracy: The request; ``budget`` its share per source; ``quadrature_tol`` the form-factor tolerance;
        ``plan_tol`` the solver tolerance while planning; ``extrapolate`` whether outputs are extrapolated.
    """

    scene: Scene
    grid: Tensor
    S: Tensor
    r: Tensor
    camera: Camera | None
    light: Any
    accuracy: float
    budget: dict[str, float]
    quadrature_tol: float
    plan_tol: float
    extrapolate: bool = True
    seconds: dict[str, float] = field(default_factory=lambda: {"form_factors": 0.0, "light": 0.0, "solve": 0.0})

    @property
    def F(self) -> int:
        return self.scene.num_facets

    def rgb_of(self, h_nodes: Tensor, nodes: Tensor, refl: Tensor) -> Tensor:
        """Camera RGB ``[..., n, C]`` from the gain ``h`` on ``nodes`` (``E = S · interp(h)``)."""
        L = self.grid.numel()
        h = h_nodes @ interp_matrix(self.grid[nodes], self.grid) if nodes.numel() < L else h_nodes
        return self.camera(refl * (self.S[..., None, :] * h) / math.pi)  # type: ignore[misc]

    def solve_gain(self, K: FormFactors, refl: Tensor, g: Tensor) -> Tensor:
        """Gain ``h`` with ``(I − F R) h = g`` per column, to the planning tolerance."""
        t = time.perf_counter()
        h = solve(K, refl, g[:, None].expand(-1, refl.shape[-1]), tol=self.plan_tol)
        self.seconds["solve"] += time.perf_counter() - t
        return h


@dataclass
class Level:
    """A solved level kept for the extrapolation: its leaves, their form factors and light factor ``[n]``."""

    leaves: Leaves
    K: FormFactors
    g: Tensor


@dataclass
class Refinement:
    """State of the refinement loop; after :func:`refine`, the last level solved.

    Attributes:
        leaves: The current leaves. K, g, h: their form factors, light factor ``[n]`` and gain ``[..., n, L']``.
        nodes: Indices of the wavelengths solved ``[L']``; ``wavelength_error`` the RGB error of that subset.
        est: Estimated discretisation error per user facet ``[F]`` (float64, CPU; inf until measured).
        sampled: User facets whose rows rest on ray-cast visibility ``[F]``.
        light_error: Relative error per user facet of the ray-cast part of the light ``[F]`` (measured on the
            user's facets, before any refinement: it does not fall with refinement).
        history: Per level: leaves, estimate, seconds. iterations: Refinement steps. reason: Why it stopped
            short of the target ("" when it did not).
        previous: The level before the current one (``None`` before the first split). ``back``: each user facet
            one split back (its leaves before its own last split, :func:`~.leaves.back_leaves`); ``coarse``: that
            mesh solved (``None`` before the first refinement), ``coarse_user`` its outputs on the user facets;
            ``split_before [F]``: user facets split in an earlier step; ``reuse_previous``: whether ``back`` is the
            previous level (every facet split before was split again), which is then not solved again; ``coef``
            the extrapolation coefficient ``c`` per user facet ``[F]`` (float64, CPU), from ``ratio`` (the last
            measured convergence ratio, clamped; :data:`Q_EXTRAPOLATE` before one is measured); ``hat`` the
            extrapolated outputs on the user facets ``[..., F, C]``.
    """

    leaves: Leaves
    nodes: Tensor
    est: Tensor
    prev_delta: Tensor
    touched: Tensor
    sampled: Tensor
    wavelength_error: float = 0.0
    light_error: Tensor | None = None
    prev_user: Tensor | None = None
    K: FormFactors | None = None
    g: Tensor | None = None
    h: Tensor | None = None
    history: list[dict[str, float]] = field(default_factory=list)
    iterations: int = 0
    reason: str = ""
    coarse: Level | None = None
    previous: Level | None = None
    coef: Tensor | None = None
    hat: Tensor | None = None
    back: Leaves | None = None
    split_before: Tensor | None = None
    reuse_previous: bool = True
    coarse_user: Tensor | None = None
    ratio: float = Q_EXTRAPOLATE


def _start(pb: Problem) -> Refinement:
    F, dev = pb.F, pb.scene.device
    # first leaves: the user's facets, split where another facet stands on them (a hidden part under a block
    # would otherwise share its facet's light)
    pieces, user = split_at_contacts(pb.scene)
    return Refinement(
        leaves=Leaves(pieces, user),
        nodes=torch.arange(pb.grid.numel(), device=dev),
        est=torch.full((F,), math.inf, dtype=torch.float64),
        prev_delta=torch.full((F,), math.nan, dtype=torch.float64),
        touched=torch.zeros(F, dtype=torch.bool),
        sampled=torch.zeros(F, dtype=torch.bool),
    )


def _kernel_and_light(
    pb: Problem, leaves: Leaves, previous: FormFactors | None = None, kept: Tensor | None = None,
    previous_g: Tensor | None = None,
) -> tuple[FormFactors, Tensor]:
    """Form factors and light factor ``[n]`` of ``leaves`` (reusing ``previous`` and ``previous_g`` for the ``kept``
    ones), timed."""
    t = time.perf_counter()
    K = leaf_kernel(leaves.scene, pb.quadrature_tol, previous, kept)
    pb.seconds["form_factors"] += time.perf_counter() - t
    t = time.perf_counter()
    reuse = previous_g[kept.to(previous_g.device)] if previous_g is not None and kept is not None else None
    g = light_factor(pb.light, leaves.scene, K, leaves.user, pb.F, reuse)
    pb.seconds["light"] += time.perf_counter() - t
    return K, g


def _user_values(pb: Problem, nodes: Tensor, leaves: Leaves, h: Tensor) -> Tensor:
    """The output (irradiance or RGB) on the user's facets ``[..., F, C]`` from the gain ``h`` on ``leaves``."""
    refl = pb.r[..., leaves.user, :]
    vals = pb.rgb_of(h, nodes, refl) if pb.camera is not None else h * pb.S[..., None, nodes]
    return to_user(vals, leaves, pb.F)


def _choose_wavelengths(pb: Problem, st: Refinement, refl_leaf: Tensor) -> Tensor:
    """Solve on the full grid once and keep the coarsest nested subset within the wavelength share; returns the
    gain on that subset."""
    dev = pb.grid.device
    h_full = pb.solve_gain(st.K, refl_leaf, st.g)  # type: ignore[arg-type]
    rgb_full = pb.rgb_of(h_full, st.nodes, refl_leaf)
    for sub in nested_subsets(pb.grid.numel()):
        sub = sub.to(dev)
        err = rms(relative_change(pb.rgb_of(h_full[..., sub], sub, refl_leaf), rgb_full))
        if err <= pb.budget["wavelengths"] * pb.accuracy or sub.numel() == pb.grid.numel():
            st.nodes, st.wavelength_error = sub, err
            break
    return h_full[..., st.nodes]  # the full-grid solve already holds the subset


def _light_error(pb: Problem, st: Refinement, refl_leaf: Tensor) -> Tensor:
    """Relative change per user facet ``[F]`` of the gain when the ray-cast part of the light is cast again
    (zeros for lights without one)."""
    other = light_check(pb.light, st.leaves.scene, st.K)  # type: ignore[arg-type]
    if other is None:
        return torch.zeros(pb.F, dtype=torch.float64)
    h_other = pb.solve_gain(st.K, refl_leaf[..., st.nodes], other)  # type: ignore[arg-type]
    mine = to_user(st.h, st.leaves, pb.F)  # type: ignore[arg-type]
    return relative_change(to_user(h_other, st.leaves, pb.F), mine).cpu()


@torch.no_grad()
def _solve_level(pb: Problem, st: Refinement, probe: bool = False) -> Tensor:
    """Solve the current leaves; returns the output (irradiance or RGB) on the user's facets ``[..., F, C]``."""
    st.K, st.g = _kernel_and_light(pb, st.leaves, st.K, st.leaves.kept, st.g)
    occ = st.K.info.get("occluded_facets")
    if occ is not None and bool(occ.any()):  # user facets whose rows rest on ray-cast visibility
        st.sampled[st.leaves.user.cpu()[occ.cpu()]] = True
    refl_leaf = pb.r[..., st.leaves.user, :]
    if st.iterations == 0 and pb.camera is not None:
        st.h = _choose_wavelengths(pb, st, refl_leaf)
    else:
        st.h = pb.solve_gain(st.K, refl_leaf[..., st.nodes], st.g)  # type: ignore[arg-type]
    if st.iterations == 0:  # the user's facets (split at contacts): the a-priori estimate of their error
        t = time.perf_counter()
        r_nodes = refl_leaf[..., st.nodes]
        est = apriori.estimate(st.leaves.scene, st.K, r_nodes, st.g, st.h, pb.light)  # type: ignore[arg-type]
        st.est = _leaf_estimate_to_user(est, st)
        pb.seconds["estimate"] = time.perf_counter() - t
    if st.light_error is None:  # level 0 (the user's facets, split at contacts): the ray-cast light's error; a probe
        # checks it only where the a-priori estimate leaves the request in reach (the report leaves a part that is not
        # finite out of its sum: checked then)
        disc = rms(st.est)
        out_of_reach = probe and math.isfinite(disc) and disc > pb.accuracy
        st.light_error = torch.zeros(pb.F, dtype=torch.float64) if out_of_reach else _light_error(pb, st, refl_leaf)
    return _user_values(pb, st.nodes, st.leaves, st.h)  # type: ignore[arg-type]


@torch.no_grad()
def _solve_back(pb: Problem, st: Refinement, prev_user: Tensor) -> None:
    """Solve each user facet one split back (``st.back``; the previous level when it is that) for the
    extrapolation: ``st.coarse`` and ``st.coarse_user``."""
    if st.reuse_previous:
        st.coarse, st.coarse_user = st.previous, prev_user
        return
    back = st.back
    K, g = _kernel_and_light(pb, back)  # type: ignore[arg-type]
    h = pb.solve_gain(K, pb.r[..., back.user, :][..., st.nodes], g)  # type: ignore[union-attr]
    st.coarse, st.coarse_user = Level(back, K, g), _user_values(pb, st.nodes, back, h)  # type: ignore[arg-type]
    st.previous = None  # not the coarse level: its kernel can go


def _leaf_estimate_to_user(est: Tensor, st: Refinement) -> Tensor:
    """Relative error estimates of the first leaves ``[n]`` onto the user facets ``[F]``, weighted by each leaf's
    share of its user facet's power (a leaf hidden under a block has none; split at contacts, a user facet has
    several first leaves)."""
    user = st.leaves.user.cpu()
    num_user = int(st.est.shape[0])
    if user.numel() == num_user:
        return est
    h = st.h.detach().abs().to(torch.float64).cpu()  # type: ignore[union-attr]
    power = h.movedim(-2, 0).reshape(h.shape[-2], -1).mean(1) * st.leaves.scene.areas.detach().double().cpu()
    est = torch.where(power > 0, est.nan_to_num(0.0, posinf=0.0), torch.zeros_like(est))
    return area_average(est[:, None], user, power, num_user)[:, 0].nan_to_num(0.0)  # no power at all: 0


def _update_estimate(st: Refinement, user_vals: Tensor, extrapolate: bool) -> None:
    """After a refinement: the extrapolation coefficients and values, and the estimates of the facets refined last:
    ``change · q / (1 − q)`` (of the extrapolated values when there were some); on an extrapolated facet its change
    times :func:`_bracket` at its first split, the larger of the two at the next ones. The others keep theirs (or
    the change)."""
    if st.prev_user is None:
        return
    delta = relative_change(st.prev_user, user_vals).cpu()
    q = (delta / st.prev_delta).nan_to_num(0.5).clamp(Q_MIN, Q_MAX)
    q = torch.where(st.sampled, torch.full_like(q, Q_SAMPLED), q)  # sampled visibility converges slowly
    # facets with ray-cast visibility are not extrapolated: on the W shape that made their estimate erratic
    # (0.22 % -> 0.25 % over one refinement) and doubled the leaves at 2e-3
    t = st.touched & ~st.sampled & extrapolate
    measured = _global_ratio(delta, st.prev_delta, t)
    if measured is not None:  # else the last measured ratio stands (a step that split only new or sampled facets)
        st.ratio = min(max(measured, Q_MIN), Q_EXTRAPOLATE)
    qe = st.ratio
    # every facet split so far is extrapolated against itself one split back (st.coarse_user)
    coef = torch.where(_extrapolated(st) & extrapolate, torch.full_like(q, qe / (1 - qe)), torch.zeros_like(q))
    hat = user_vals  # nothing extrapolated (coef is 0) until a back level is solved
    if st.coarse_user is not None:
        hat = user_vals + coef.to(user_vals)[:, None] * (user_vals - st.coarse_user)
    change = delta if st.hat is None else relative_change(st.hat, hat).cpu()
    est = change * q / (1 - q)
    if st.coarse_user is not None:  # extrapolated: at least how far c can be from its facet's own (bracket), and
        # at its first split only that (no change of x̂ is known yet)
        first = st.touched & ~(st.split_before if st.split_before is not None else torch.zeros_like(st.touched))
        own = delta * _bracket(coef, q)  # q is 0.5 at a facet's first split (no earlier change)
        est = torch.where(coef > 0, torch.where(first, own, torch.maximum(est, own)), est)
    st.est = torch.where(st.touched, est, torch.maximum(st.est, change))
    st.prev_delta = torch.where(st.touched, delta, st.prev_delta)
    st.coef, st.hat = coef, hat


def _bracket(coef: Tensor, q: Tensor) -> Tensor:
    """How far an extrapolated value ``x + c (x − x_back)`` can be from the limit, in units of ``x − x_back``, when the
    facet converges at first order or faster, or at its own slower measured ratio ``q``: ``c(max(1/2, q)) − c`` with
    ``c(q) = q/(1 − q)`` (the fast end, second order, ``c = 1/3``, is never farther: ``c ≤ 2/3``). The caller
    multiplies it by the facet's change since the previous level (see the module doc's known weakness)."""
    slow = q.clamp_min(0.5)
    return (slow / (1 - slow) - coef).clamp_min(0.0)


def _global_ratio(delta: Tensor, prev: Tensor, touched: Tensor) -> float | None:
    """RMS of the last changes over the RMS of the ones before, on the ``touched`` facets that have an earlier change
    (``None`` when there are none, or the earlier changes are all 0)."""
    both = touched & prev.isfinite()
    if not bool(both.any()):
        return None
    num, den = float(delta[both].square().mean()), float(prev[both].square().mean())
    return math.sqrt(num / den) if den > 0 else None


def _extrapolated(st: Refinement) -> Tensor:
    """User facets ``[F]`` whose output is extrapolated: split at some step, and without ray-cast visibility."""
    was_split = st.touched | st.split_before if st.split_before is not None else st.touched
    return was_split & ~st.sampled


def _disc_target(pb: Problem, st: Refinement) -> float:
    """The discretisation's share of the request, less the measured error of the ray-cast light (the sky's open part)
    when that is under a quarter of the share: refinement does not lower that error, so the rest of the share goes to
    the discretisation and the total can meet the request. Above, the share stands (lowering it would spend
    refinement without meeting the request; the report warns). On the Cornell box (r = 0.9) at 1e-2, the sky's
    0.19 % against the share 0.8 %: estimate 0.83 % at 11,168 leaves, no warning (with the share alone 1.11 % at
    11,012 leaves, and a warning). At half the share instead of a quarter, 5e-3 spent 126 s instead of 84 s for the
    same warning."""
    share = pb.budget["discretisation"] * pb.accuracy
    light = rms(st.light_error) if st.light_error is not None else 0.0
    return share - light if light < 0.25 * share else share


def _stop_reason(pb: Problem, st: Refinement, disc: float, max_iterations: int) -> str | None:
    """``""`` when the target is met, a reason when refinement has to stop short of it, ``None`` to go on."""
    if disc <= _disc_target(pb, st):
        return ""
    if st.iterations >= max_iterations:
        return f"max_iterations={max_iterations}"
    if len(st.history) >= 3 and disc > STALL * st.history[-3]["estimate"]:
        return (
            f"a stalled estimate ({st.history[-3]['estimate']:.3g} -> {disc:.3g} over the last two refinements; "
            "the scene converges too slowly under refinement for this target)"
        )
    return None


def _split_step(pb: Problem, st: Refinement, user_vals: Tensor, max_facets: int) -> bool:
    """Split the leaves of the user facets carrying the excess error; ``False`` when none fits ``max_facets``."""
    sel = select(st.leaves, st.est, _disc_target(pb, st), max_facets)
    if sel is None:
        return False
    touched = torch.zeros(pb.F, dtype=torch.bool)
    touched[st.leaves.user[sel].cpu()] = True
    st.split_before = st.touched if st.split_before is None else st.split_before | st.touched
    st.touched = touched
    st.prev_user = user_vals
    # kept for the extrapolation only (the older ones go now; they are replaced after the next solve)
    st.previous = Level(st.leaves, st.K, st.g) if pb.extrapolate else None  # type: ignore[arg-type]
    st.coarse = st.coarse_user = None
    if pb.extrapolate:
        st.reuse_previous = not bool((st.split_before & ~touched).any())
        st.back = back_leaves(st.back, st.leaves, touched)
    st.leaves = split(st.leaves, sel)
    st.iterations += 1
    return True


def refine(pb: Problem, *, max_facets: int, max_iterations: int, show: bool, t_start: float,
           probe: bool = False) -> Refinement:
    """Refine until the estimated discretisation error meets its share, or a limit stops it (``reason``).

    ``probe``: a first look that is kept only if it reaches the request (``basis="auto"`` on the constant basis,
    ``max_iterations=0``): the ray-cast light's check (:func:`~.leaves.light_check`, a second cast of the sky's rays)
    is skipped where the a-priori estimate alone is above the request, and its part is then left at 0. On the Cornell
    box under a sky (50 pieces) that check was 0.20 s of the probe's 0.31 s; on the open room (194 pieces) 0.5 s of
    0.9 s, where the a-priori estimates (7.7–50 %) are above every request of the accuracy benchmark."""
    st = _start(pb)
    bar = tqdm(total=max_iterations + 1, desc="render", unit="step", leave=False, disable=None if show else True)
    while True:
        user_vals = _solve_level(pb, st, probe)
        if pb.extrapolate and st.prev_user is not None and bool(_extrapolated(st).any()):
            _solve_back(pb, st, st.prev_user)
        _update_estimate(st, user_vals, pb.extrapolate)
        disc = rms(st.est)
        st.history.append(
            {"leaves": st.leaves.scene.num_facets, "estimate": disc, "seconds": time.perf_counter() - t_start}
        )
        bar.set_postfix(facets=st.leaves.scene.num_facets, estimate=f"{disc:.2g}")
        bar.update(1)
        reason = _stop_reason(pb, st, disc, max_iterations)
        if reason is not None:
            st.reason = reason
            break
        if not _split_step(pb, st, user_vals, max_facets):
            st.reason = f"max_facets={max_facets}"
            break
    bar.close()
    return st
