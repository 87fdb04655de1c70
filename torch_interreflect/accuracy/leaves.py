"""The leaves of adaptive refinement: which user facet each leaf belongs to, splitting, selection, averaging back.

Every user facet starts as one leaf; :func:`select` picks the user facets that carry the excess estimated error
and :func:`split` splits all their leaves in four. Values on the leaves are area-averaged back onto the user's
facets (:func:`to_user`), so outputs keep the user's layout and total power.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from .. import lights
from ..formfactors.operator import FormFactors
from ..geometry.gaps import near_pairs
from ..geometry.scene import Scene, area_average
from ..lights import light_geometry

__all__ = [
    "NEAR_INFLATION",
    "NEAR_RATIO",
    "SKY_SAMPLES",
    "UNRESOLVED_RATIO",
    "Leaves",
    "back_leaves",
    "light_check",
    "light_factor",
    "near_facets",
    "near_partners",
    "relative_change",
    "rms",
    "select",
    "split",
    "subset",
    "to_user",
    "unresolved_near",
]


@dataclass
class Leaves:
    """A refined scene and the user facet of each of its facets (leaves).

    Attributes:
        scene: The refined scene (``n`` leaves).
        user: User facet of each leaf. Shape ``[n]``.
        kept: After :func:`split`: the indices, among the previous leaves, of the first ``len(kept)`` leaves
            (unchanged by the split; their form factors can be reused). Shape ``[m]``.
    """

    scene: Scene
    user: Tensor
    kept: Tensor | None = None


def subset(scene: Scene, idx: Tensor) -> Scene:
    """The facets ``idx`` of ``scene`` (corners, kind and material) as a scene."""
    mat = scene.material[idx] if scene.material is not None else None
    return Scene.from_parts(scene.corners[idx], scene.is_triangle[idx], mat, scene.material_names)


def _joined(a: Scene, b: Scene) -> Scene:
    """The facets of ``a`` then those of ``b``, two parts of one scene (same material names)."""
    mat = None
    if a.material is not None and b.material is not None:
        mat = torch.cat([a.material, b.material])
    return Scene.from_parts(torch.cat([a.corners, b.corners]), torch.cat([a.is_triangle, b.is_triangle]), mat,
                            a.material_names)


def split(leaves: Leaves, sel: Tensor) -> Leaves:
    """Split the selected leaves ``sel [n]`` in four (kept leaves first, then the children)."""
    idx_keep = torch.nonzero(~sel).reshape(-1)
    idx_sel = torch.nonzero(sel).reshape(-1)
    fine, par = subset(leaves.scene, idx_sel).subdivide(2)
    scene = _joined(subset(leaves.scene, idx_keep), fine)
    return Leaves(scene, leaves.user[torch.cat([idx_keep, idx_sel[par]])], idx_keep)


def back_leaves(back: Leaves | None, leaves: Leaves, touched: Tensor) -> Leaves:
    """Each user facet one split back, before ``leaves`` are split on the ``touched [F]`` user facets: their
    current leaves for those, and their leaves in ``back`` (the same before this split) for the others. ``None``
    for ``back``: before the first split (every facet's current leaves)."""
    if back is None:
        return Leaves(leaves.scene, leaves.user)
    dev = leaves.user.device
    a = torch.nonzero(touched.to(dev)[leaves.user]).reshape(-1)
    b = torch.nonzero(~touched.to(back.user.device)[back.user]).reshape(-1)
    scene = _joined(subset(leaves.scene, a), subset(back.scene, b.to(back.scene.device)))
    return Leaves(scene, torch.cat([leaves.user[a], back.user[b].to(dev)]))


def to_user(values: Tensor, leaves: Leaves, num_user: int) -> Tensor:
    """Area-weighted average of leaf values ``[..., n, C]`` onto the user facets ``[..., F, C]``."""
    return area_average(values, leaves.user, leaves.scene.areas, num_user)


def relative_change(a: Tensor, b: Tensor) -> Tensor:
    """Per-facet relative difference ``[F]``: largest over the columns of ``|a − b| / |b|`` (facets on dim −2;
    computed in float64, so a column that is zero everywhere gives 0, not NaN, in float32 too)."""
    a, b = a.double(), b.double()
    d = (a - b).abs()
    scale = b.abs()
    floor = 1e-12 * scale.amax(dim=-2, keepdim=True).clamp_min(1e-300)
    r = d / torch.maximum(scale, floor)
    r = r.movedim(-2, 0).reshape(r.shape[-2], -1)
    return r.amax(dim=1) if r.shape[1] else r.new_zeros(r.shape[0])


def rms(x: Tensor) -> float:
    """Root mean square of ``x`` (0 when empty)."""
    return float(x.detach().square().mean().sqrt()) if x.numel() else 0.0


#: Directions per axis of the ray-cast parts of the sky (:func:`torch_interreflect.lights.sky`), and the smaller
#: count :func:`light_check` compares with.
SKY_SAMPLES, SKY_CHECK_SAMPLES = 16, 24


def light_factor(light: Any, scene: Scene, K: FormFactors, user: Tensor, num_user: int,
                 kept_g: Tensor | None = None) -> Tensor:
    """Geometric factor ``g [n]`` of the light on the leaves: ``E0 = g ⊗ spectrum``.

    ``kept_g``: the factors ``[m]`` of the first ``m`` leaves, kept unchanged from a previous step (:func:`split`).
    Under the sky, those whose value is a count of escaping rays (leaves with occluded pairs) keep it: it depends
    on the leaf and the scene alone, and casting again would draw other rays (and change the value by its noise).
    """
    if isinstance(light, str) and light == "sky":
        one = torch.ones(1, dtype=scene.dtype, device=scene.device)
        occ = K.info.get("occluded_facets")
        if kept_g is None or occ is None or not bool(occ[: kept_g.numel()].any()):
            return lights.sky(scene, K, one, sky_samples=SKY_SAMPLES)[:, 0]
        keep = torch.zeros(scene.num_facets, dtype=torch.bool)
        keep[: kept_g.numel()] = occ[: kept_g.numel()].cpu()
        fresh = torch.nonzero(~keep).reshape(-1)
        g = torch.empty(scene.num_facets, dtype=scene.dtype, device=scene.device)
        g[keep.to(g.device)] = kept_g.to(g)[keep[: kept_g.numel()].to(g.device)]
        g[fresh.to(g.device)] = lights.sky(scene, K, one, sky_samples=SKY_SAMPLES, facets=fresh)[:, 0]
        return g
    if isinstance(light, Tensor) and light.ndim == 1 and light.shape[0] == num_user and num_user != 3:
        if light.dtype == torch.bool:
            return light_geometry(scene, K, light.to(scene.device)[user])
        return light.to(device=scene.device, dtype=scene.dtype)[user]  # a factor per user facet: per leaf
    return light_geometry(scene, K, light)


def light_check(light: Any, scene: Scene, K: FormFactors) -> Tensor | None:
    """The light factor ``[n]`` cast again with :data:`SKY_CHECK_SAMPLES` directions per axis, for a light with
    ray-cast parts (the sky); ``None`` for the others (deterministic: their error is discretisation).

    The sky's open part on facets with occluded pairs and its back-face coverage are Monte Carlo estimates whose
    error does not fall with refinement (each leaf gets the same rays); the difference between the two estimates
    measures it.
    """
    if not (isinstance(light, str) and light == "sky"):
        return None
    one = torch.ones(1, dtype=scene.dtype, device=scene.device)
    return lights.sky(scene, K, one, sky_samples=SKY_CHECK_SAMPLES)[:, 0]


def _chosen(est: Tensor, target: float) -> list[int]:
    """User facets carrying the excess error: largest estimates first, until the others alone meet ``target``
    (every not-yet-measured facet when some are)."""
    if bool(torch.isinf(est).any()):
        return torch.nonzero(torch.isinf(est)).reshape(-1).tolist()
    order = torch.argsort(est, descending=True).tolist()
    sq = est.square()
    total = float(sq.sum())
    limit = 0.8 * target * target * est.numel()
    chosen: list[int] = []
    for i in order:  # the fewest facets without which the rest meets the target
        if total <= limit and chosen:
            break
        chosen.append(i)
        total -= float(sq[i])
    return chosen


def _fit(candidates: list[int], count: Tensor, room: int) -> tuple[list[int], int]:
    """The candidate user facets whose leaves fit in ``room`` more leaves, in order (a split adds three leaves per
    leaf; ``count [F]``: leaves per user facet), and the room left."""
    picked = []
    for i in candidates:
        if 3 * int(count[i]) <= room:
            picked.append(i)
            room -= 3 * int(count[i])
    return picked, room


def select(leaves: Leaves, est: Tensor, target: float, max_facets: int,
           near: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor | None:
    """Leaves to split ``[n]``: every leaf of the user facets that carry the excess error, as many as
    ``max_facets`` allows (``None`` when no facet fits); with ``near`` (:func:`near_facets`), then those of the
    facets that nearly touch them (:func:`near_partners`), as many as the room left allows."""
    user = leaves.user.cpu()
    count = torch.bincount(user, minlength=est.numel())
    picked, room = _fit(_chosen(est, target), count, max_facets - leaves.scene.num_facets)
    if not picked:
        return None
    pick = torch.zeros(est.numel(), dtype=torch.bool)
    pick[picked] = True
    if near is not None:
        pick[_fit(near_partners(leaves, pick, near), count, room)[0]] = True
    return pick[user].to(leaves.user.device)


#: A user facet is split with a selected one whose gap to it is below this fraction of its own leaves' diameter
#: (:func:`near_partners`).
NEAR_RATIO = 0.1

#: A user facet's estimate is inflated (:data:`NEAR_INFLATION`) while its gap to a facet it nearly touches is below
#: this fraction of its leaves' diameter (:func:`unresolved_near`).
UNRESOLVED_RATIO = 0.1

#: What :func:`unresolved_near` multiplies such a facet's estimate by.
NEAR_INFLATION = 4.0


def near_partners(leaves: Leaves, picked: Tensor, near: tuple[Tensor, Tensor, Tensor]) -> list[int]:
    """The user facets ``j`` not ``picked`` (bool ``[F]``) near a picked one ``i``: the pairs ``near = (i, j, gap)``
    (:func:`near_facets`, both orders) whose gap is below :data:`NEAR_RATIO` times the diameter of ``j``'s leaves.

    Where two facets nearly touch, the error of one's output comes from the other's leaves (a floor under a wall
    hung 5 cm above it, uniform light, r = 0.9, 1e-3: the floor 0.42 % off on 16 leaves while the wall stayed at 4,
    estimated 0.02 %): splitting them together puts that error into the change that estimates it.

    Args:
        leaves: The leaves. picked: The user facets picked to split, bool ``[F]``.
        near: ``(i, j, gap)`` user-facet pairs, both orders.

    Returns:
        The partners' indices, ascending.
    """
    i, j, gap = near
    if not i.numel():
        return []
    partner = torch.zeros(picked.numel(), dtype=torch.bool)
    partner[j[picked[i] & ~picked[j] & (gap < NEAR_RATIO * _leaf_sizes(leaves, picked.numel())[j])]] = True
    return torch.nonzero(partner).reshape(-1).tolist()


def near_facets(scene: Scene) -> tuple[Tensor, Tensor, Tensor]:
    """The user facets that nearly touch: :func:`~torch_interreflect.geometry.gaps.near_pairs` with
    :data:`NEAR_RATIO`."""
    return near_pairs(scene, NEAR_RATIO)


def _leaf_sizes(leaves: Leaves, num_user: int) -> Tensor:
    """The largest diameter of each user facet's leaves ``[F]`` (m, float64, CPU)."""
    return torch.zeros(num_user, dtype=torch.float64).scatter_reduce_(
        0, leaves.user.cpu(), leaves.scene.diameters.detach().cpu().to(torch.float64), "amax")


def unresolved_near(est: Tensor, leaves: Leaves, near: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """``est [F]`` times :data:`NEAR_INFLATION` on every user facet whose leaves are more than
    ``1 / UNRESOLVED_RATIO`` times as large as its gap to a facet it nearly touches (``near``: :func:`near_facets`,
    both orders): the light between the two varies on the scale of the gap, and a change between two levels of
    leaves much larger than that understates the error (the same wall under a sun that lights the floor alone,
    r = 0.9, 1e-2: the wall 1.9 % off on 4 leaves, estimated 0.94 % from its change since 1 leaf; with the factor 4,
    256 leaves, 0.085 % off, estimated 0.023 %, the scene's RMS 0.060 % against 0.12 %). Splitting such facets until
    their leaves are that small (an unknown estimate) also met every request of the wall at x = 0.2, 0.3, 0.35 (uniform
    light and the sun, r = 0.5 and 0.9, 1e-2 and 1e-3), but split the wall to 256 leaves in every case (0.25–0.36 s
    where the factor takes 4–64 leaves and 0.04–0.09 s under uniform light at 1e-2).

    Args:
        est: Estimated error per user facet, without this factor ``[F]``.
        leaves: The leaves. near: ``(i, j, gap)`` user-facet pairs, both orders (:func:`near_facets`).

    Returns:
        The estimate with the factor where it applies ``[F]`` (a copy).
    """
    _, j, gap = near
    if not j.numel():
        return est
    out = est.clone()
    sizes = _leaf_sizes(leaves, est.numel())
    out[j[gap < UNRESOLVED_RATIO * sizes[j]].to(out.device)] *= NEAR_INFLATION
    return out
