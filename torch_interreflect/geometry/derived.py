"""Values derived from a scene's corners (areas, normals, centroids, a ray caster), computed once while the corners
are unchanged.

A render reads the same derived quantities many times: on the 56-piece Cornell box the moments, the sky's rays and
the solve computed the centroids 10 times, the normals 9 times and built Embree's scene twice per call.
:class:`DerivedCache` keeps each value beside the tensor it came from and hands it out again while that tensor is
the same object at the same version (:attr:`torch.Tensor._version` counts in-place writes through the tensor and its
views: ``corners[...] *= 2`` or ``corners.add_(…)`` under :func:`torch.no_grad` is seen). Nothing is kept where a
stale or shared value could change a result:

- corners that require grad (each read builds its own graph, as autograd needs; an optimiser's parameters);
- inference tensors, or inside :func:`torch.inference_mode` (such a value could not be saved for backward later);
- a kept tensor that was itself written in place since (its version is checked on every hit).

Writes that bypass the version counter are not seen: through ``corners.data`` (a new counter) or through a numpy view
of the corners (``corners.numpy()``). After such a write, :meth:`DerivedCache.clear` (``Scene.clear_derived``)
forgets the kept values. Kept tensors are shared by every reader: treat them as read-only.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, TypeVar

import torch
from torch import Tensor

__all__ = ["DerivedCache", "cacheable"]

T = TypeVar("T")


def cacheable(source: Tensor) -> bool:
    """Whether values derived from ``source`` may be kept (see the module docstring)."""
    if source.requires_grad or torch.is_inference_mode_enabled():
        return False
    try:
        return not source.is_inference()
    except RuntimeError:  # pragma: no cover - wrapped tensors (functorch) say nothing: do not keep
        return False


def _version(value: Any) -> int | None:
    """The version of a kept tensor (None for other values, which are not written in place)."""
    return value._version if isinstance(value, Tensor) else None


class DerivedCache:
    """Values derived from one tensor, by key, kept while that tensor is unchanged.

    Example:
        >>> import torch
        >>> from torch_interreflect.geometry.derived import DerivedCache
        >>> corners, cache, calls = torch.zeros(2, 4, 3), DerivedCache(), []
        >>> make = lambda: calls.append(1) or corners.sum(1)
        >>> a = cache.get(corners, "sum", make); b = cache.get(corners, "sum", make)
        >>> len(calls), a is b
        (1, True)
        >>> corners += 1.0   # an in-place write: computed again
        >>> float(cache.get(corners, "sum", make)[0, 0]), len(calls)
        (4.0, 2)
    """

    __slots__ = ("_entries",)

    def __init__(self) -> None:
        self._entries: dict[Hashable, tuple[Tensor, int, Any, int | None]] = {}

    def get(self, source: Tensor, key: Hashable, make: Callable[[], T]) -> T:
        """``make()``, or the value it gave before for ``key`` while ``source`` is unchanged (module docstring).

        Args:
            source: The tensor the value is derived from.
            key: Which value (one per key and source).
            make: Computes the value.

        Returns:
            The value (the kept one, or ``make()``'s).
        """
        if not cacheable(source):
            return make()
        version = source._version
        hit = self._entries.get(key)
        if hit is not None and hit[0] is source and hit[1] == version and _version(hit[2]) == hit[3]:
            return hit[2]
        value = make()
        self._entries[key] = (source, version, value, _version(value))
        return value

    def clear(self) -> None:
        """Forget every kept value."""
        self._entries.clear()
