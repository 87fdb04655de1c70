"""Moments reused across a refinement: which facets of a refined scene are unchanged facets of an earlier one, and
the sums of the pairs of two such facets copied from the earlier moments (:func:`~.moments.moment_form_factors`'s
``reuse``), so that a refinement step integrates only the pairs that changed."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..geometry.scene import Scene

__all__ = ["reuse_map", "reused_sums"]


def reuse_map(sc: Scene, reuse: tuple[Any, Tensor], settings: dict[str, Any]) -> np.ndarray:
    """Each facet's index among the previous moments' facets (``-1``: new), once ``reuse`` is checked.

    Args:
        sc: The refined scene (float64, CPU).
        reuse: ``(previous, kept)``: moments straight from :func:`~.moments.moment_form_factors` (a
            :class:`~.moments.MomentFormFactors`, not imported here: that module imports this one) and the indices
            ``kept [m]`` of their facets that are ``sc``'s first ``m`` facets, unchanged.
        settings: The settings of the moments to make (``previous`` must have been made with the same).

    Returns:
        ``[F]`` int64 (numpy).

    Raises:
        ValueError: ``previous`` holds no sums or was made with other settings, ``kept`` does not index it or
            names facets that are not ``sc``'s first facets, or ``sc``'s other facets do not cover the previous
            ones' other facets (their total area or bounding box differs: not a refinement).
    """
    previous, kept = reuse
    if "_sums" not in getattr(previous, "info", {}):
        raise ValueError("reuse needs moments straight from moment_form_factors (they keep their pairs' sums); got "
                         f"{type(previous).__name__} without them")
    if previous.info.get("settings") != settings:
        raise ValueError(f"reuse needs moments made with the same settings {settings}; got "
                         f"{previous.info.get('settings')}")
    kept = torch.as_tensor(kept).reshape(-1).to(torch.int64).cpu()
    old_sc = previous.info["_sums"][0]
    if kept.numel() > sc.num_facets or (kept.numel() and (int(kept.min()) < 0 or int(kept.max()) >= old_sc.num_facets)):
        raise ValueError(f"reuse's kept must index the previous moments' {old_sc.num_facets} facets, at most one per "
                         f"facet of this scene ({sc.num_facets}); got {kept.numel()} indices in "
                         f"[{int(kept.min()) if kept.numel() else 0}, {int(kept.max()) if kept.numel() else 0}]")
    m = kept.numel()
    if not torch.equal(sc.corners[:m], old_sc.corners[kept]):
        raise ValueError("reuse's kept facets must be this scene's first facets, unchanged; their corners differ")
    # the other facets must cover the same surfaces as the previous ones (a refinement of them): the kept pairs'
    # rays were cast against those; checked by their total area and bounding box
    rest = torch.ones(old_sc.num_facets, dtype=torch.bool)
    rest[kept] = False
    a_new, a_old = float(sc.areas[m:].sum()), float(old_sc.areas[rest].sum())
    box_new, box_old = _box(sc.corners[m:]), _box(old_sc.corners[rest])
    size = float((sc.corners.reshape(-1, 3).amax(0) - sc.corners.reshape(-1, 3).amin(0)).norm())
    if abs(a_new - a_old) > 1e-9 * max(a_old, 1e-300) or float((box_new - box_old).abs().max()) > 1e-9 * size:
        raise ValueError("reuse needs a refinement of the previous scene: its facets other than the kept ones must "
                         f"cover the same surfaces; got an area of {a_new:.9g} m² against {a_old:.9g} m², bounding "
                         f"boxes {box_new.tolist()} against {box_old.tolist()}")
    old_of = np.full(sc.num_facets, -1, dtype=np.int64)
    old_of[: kept.numel()] = kept.numpy()
    return old_of


def _box(corners: Tensor) -> Tensor:
    """Bounding box ``[2, 3]`` of facets' corners ``[n, 4, 3]`` (zeros when there are none)."""
    if corners.shape[0] == 0:
        return torch.zeros(2, 3, dtype=corners.dtype)
    pts = corners.reshape(-1, 3)
    return torch.stack([pts.amin(0), pts.amax(0)])


def reused_sums(setup: dict[str, Any], old: tuple[dict[str, Any], np.ndarray], old_of: np.ndarray,
                acc: np.ndarray) -> np.ndarray:
    """Copy into ``acc [P, nb, nb]`` the monomial sums of the pairs whose two facets were a pair of the previous
    moments ``old = (setup, acc)`` and need rays there as here (transposed where domain and target swapped), and the
    occluded ones' exact unoccluded sums into ``setup["exact"]``; the pairs left to integrate.

    Args:
        setup: The new pairs (``dom``, ``tgt``, ``need``; :func:`~.moments.moment_form_factors`' set-up).
        old: The previous set-up and sums.
        old_of: Each new facet's previous index, ``-1`` if new (:func:`reuse_map`).
        acc: The new pairs' sums, filled in place.

    Returns:
        Indices of the pairs still to integrate ``[P']`` (int64, numpy).
    """
    old_setup, old_acc = old
    dom, tgt = setup["dom"].numpy(), setup["tgt"].numpy()
    od, ot = old_of[dom], old_of[tgt]
    cand = np.nonzero((od >= 0) & (ot >= 0))[0]
    odom, otgt = old_setup["dom"].numpy(), old_setup["tgt"].numpy()
    todo = np.ones(dom.size, dtype=bool)
    if cand.size and odom.size:
        n = int(max(odom.max(), otgt.max())) + 1  # old facet indices: a key per unordered pair
        okey = np.minimum(odom, otgt) * n + np.maximum(odom, otgt)
        order = np.argsort(okey)
        sorted_key = okey[order]
        key = np.minimum(od[cand], ot[cand]) * n + np.maximum(od[cand], ot[cand])
        pos = np.minimum(np.searchsorted(sorted_key, key), order.size - 1)
        found = sorted_key[pos] == key
        p, q = cand[found], order[pos[found]]
        same = setup["need"].numpy()[p] == old_setup["need"].numpy()[q]
        p, q = p[same], q[same]
        turned = odom[q] != od[p]  # domain and target swapped: the monomial sums transposed
        acc[p] = np.where(turned[:, None, None], old_acc[q].transpose(0, 2, 1), old_acc[q])
        todo[p] = False
        occ = setup["need"].numpy()[p]  # occluded pairs: their exact unoccluded sums too
        if occ.any():
            po, qo, to = p[occ], q[occ], turned[occ]
            old_exact = old_setup["exact"][old_setup["need_rank"][qo]]
            setup["exact"][setup["need_rank"][po]] = np.where(to[:, None, None], old_exact.transpose(0, 2, 1),
                                                              old_exact)
    return np.nonzero(todo)[0].astype(np.int64)
