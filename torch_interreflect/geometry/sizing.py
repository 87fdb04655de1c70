"""Subdivision to a size: every facet split until its pieces are no longer than a given length.

:meth:`Scene.subdivide` splits every facet ``k × k`` whatever its size, so a scene of large walls and small blocks
(the Cornell box, a room) gets either walls too coarse or blocks too fine. :func:`subdivide_to` picks the split of
each facet from its own edges instead: a quad ``a × b`` metres becomes ``⌈a / size⌉ × ⌈b / size⌉`` pieces (long thin
strips, such as the floor pieces :func:`~torch_interreflect.geometry.split_at_contacts` leaves, are cut across their
length only), a triangle with longest edge ``l`` becomes ``⌈l / size⌉²`` triangles. On the Cornell box under the sky
(quadratic basis) this reaches the same error as a uniform ``subdivide(k)`` with 3–5× fewer pieces
(``benchmarks/results/cornell.md``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import ValueRangeError
from .scene import Scene, split_quads

__all__ = ["pieces_per_side", "subdivide_to"]


def _check_size(size: float) -> float:
    if isinstance(size, bool) or not isinstance(size, (int, float)) or not math.isfinite(size) or size <= 0:
        raise ValueRangeError(f"size must be a positive finite length in metres; got {size!r}")
    return float(size)


def pieces_per_side(scene: Scene, size: float) -> tuple[Tensor, Tensor]:
    """How :func:`subdivide_to` splits each facet: ``(ku, kv)``, the pieces along the edges ``0→1`` and ``0→3``
    (``ku = kv`` for triangles).

    Args:
        scene: The scene.
        size: Longest edge of a piece, in metres (> 0).

    Returns:
        ``(ku, kv)``, int64 on the scene's device. Shape ``[F]`` each.
    """
    size = _check_size(size)
    c = scene.corners.detach()
    edge = (c.roll(-1, dims=1) - c).norm(dim=-1)  # [F, 4]: 0→1, 1→2, 2→3, 3→0 (a triangle's 2→3 is 0)
    along_u = torch.maximum(edge[:, 0], edge[:, 2])
    along_v = torch.maximum(edge[:, 1], edge[:, 3])
    ku = torch.ceil(along_u / size * (1 - 1e-9)).clamp_min(1).long()
    kv = torch.ceil(along_v / size * (1 - 1e-9)).clamp_min(1).long()
    tri = scene.is_triangle
    longest = edge.amax(1)
    kt = torch.ceil(longest / size * (1 - 1e-9)).clamp_min(1).long()
    return torch.where(tri, kt, ku), torch.where(tri, kt, kv)


def subdivide_to(scene: Scene, size: float) -> tuple[Scene, Tensor]:
    """Split every facet into pieces whose edges are at most ``size`` long (quads ``ku × kv`` by their own sides,
    triangles ``k²``; :func:`pieces_per_side`). Differentiable in the corners.

    Args:
        scene: The scene.
        size: Longest edge of a piece, in metres (> 0). A facet whose edges are within it stays whole.

    Returns:
        ``(fine, parent)`` as :meth:`Scene.subdivide` returns them: ``parent[j]`` is the facet of ``scene`` that
        piece ``j`` came from; a facet's pieces are contiguous, in the facets' order, and their areas sum to its
        area.

    Raises:
        ValueRangeError: ``size`` is not a positive finite number. TypeError: ``scene`` is not a :class:`Scene`.

    Shape:
        - parent: ``[F_fine]``, ``F_fine = Σ ku·kv``

    Example:
        >>> import torch_interreflect as ti
        >>> box = ti.scenes.cornell_box(divisions=1, light=False)
        >>> fine, parent = ti.geometry.subdivide_to(box, 0.3)
        >>> box.num_facets, fine.num_facets, int(parent[-1])
        (16, 48, 15)
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"subdivide_to expects a Scene; got {type(scene).__name__}")
    ku, kv = pieces_per_side(scene, size)
    c, tri = scene.corners, scene.is_triangle
    pieces: list[Tensor] = []
    owners: list[Tensor] = []
    is_tri: list[Tensor] = []
    keys = torch.stack([ku, kv, tri.long()], 1)
    for u, v, t in torch.unique(keys, dim=0).tolist():
        idx = torch.nonzero((keys == torch.tensor([u, v, t], device=keys.device)).all(1)).reshape(-1)
        if t:
            sub, _ = Scene.from_parts(c[idx], tri[idx], None, None).subdivide(u)
            pieces.append(sub.corners)
            n = u * u
        else:
            pieces.append(split_quads(c[idx], u, v).reshape(-1, 4, 3))
            n = u * v
        owners.append(idx.repeat_interleave(n))
        is_tri.append(torch.full((idx.numel() * n,), bool(t), dtype=torch.bool, device=c.device))
    owner = torch.cat(owners)
    order = torch.sort(owner, stable=True).indices  # the facets' order, each facet's pieces in their split order
    parent = owner[order]
    mat = scene.material[parent] if scene.material is not None else None
    fine = Scene.from_parts(torch.cat(pieces)[order], torch.cat(is_tri)[order], mat, scene.material_names)
    return fine, parent
