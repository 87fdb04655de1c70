"""Translated copies among the moments' pairs: two pairs whose facets are the same quads shifted by one vector (a
uniform subdivision is full of them: a groove's hinge pairs repeat along the hinge, a wall's pieces along the floor)
have the same unoccluded sums, since each facet's monomials are taken in its own frame about its own centroid. The
moments integrate one pair of each class and copy its sums to the others (:func:`~.moments.moment_form_factors`);
the occluded pairs keep their own rays. Measured (CHANGELOG, 2026-12-05 evening): on the accuracy benchmark's
uniform scenes most pairs are copies (a 6 × 6 groove: 900 of 1,296), on the Cornell box cut to a size few (107 of
5,015 at 0.2 m).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..geometry._polygon import scene_size
from .compiled import launch

__all__ = ["translated_copies"]


def translated_copies(kern: Any, setup: dict[str, Any], todo: np.ndarray) -> np.ndarray:
    """For each pair of ``todo`` the pair whose sums it takes: the first of ``todo`` (in its order) that is a
    translated copy of it (its own index where there is none).

    Args:
        kern: The moments' compiled loops (:mod:`._numba_moments`).
        setup: The pairs of :func:`~.moments.moment_form_factors` (its ``pairs``, ``fine``, ``corners``, ``scene``,
            ``triangle`` and ``tie``). Corners relative to their domain's first corner are rounded to steps of
            ``tie`` times the scene's size (:func:`.pairs.copy_tie`, the rounding between translated copies, which
            moves their sums by about as little); pairs whose steps agree are copies. Rounding to steps, two copies
            that straddle a step's edge are missed (each is then integrated); pairs less than a step apart may be
            taken as copies.
        todo: Pair indices ``[n]`` (int64).

    Returns:
        Pair indices ``[n]`` (int64); ``rep[t] == todo[t]`` for the pairs that are integrated.
    """
    if todo.size < 2:
        return todo.copy()
    dom, tgt, kind, rule, shift = setup["pairs"]
    corners = setup["corners"]
    quantum = float(setup["tie"]) * max(scene_size(setup["scene"]), 1e-300)
    args = (dom, tgt, kind, rule, shift, setup["fine"], corners, setup["triangle"], quantum)
    keys = np.empty(todo.size, dtype=np.uint64)
    launch(kern.pair_hashes, todo, *args, keys)
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    rep = todo[first][inverse.reshape(-1)]
    same = np.empty(todo.size, dtype=np.bool_)
    launch(kern.same_pairs, todo, rep, *args, same)
    rep[~same] = todo[~same]  # a hash collision: integrated on its own
    return rep
