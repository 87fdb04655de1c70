"""The checks of a request to :func:`~.plan.plan` and :func:`~.render.render` that no planning can serve."""

from __future__ import annotations

import math

import torch

from ..errors import ValueRangeError
from ..geometry.scene import Scene

__all__ = ["check_request"]


def check_request(scene: Scene, accuracy: float, max_facets: int) -> None:
    """Typed errors for a request the planner cannot serve.

    Raises:
        TypeError: ``scene`` is not a :class:`~torch_interreflect.geometry.scene.Scene`.
        ValueRangeError: ``accuracy`` is not a finite number in ``(0, 0.5]``, or below what the scene's dtype resolves.
        ValueError: ``max_facets`` is not an integer at least the scene's facet count.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"plan expects a Scene; got {type(scene).__name__}")
    if isinstance(accuracy, bool) or not isinstance(accuracy, (int, float)) or not math.isfinite(accuracy):
        raise ValueRangeError(f"accuracy must be a finite number in (0, 0.5]; got {accuracy!r}")
    if not (0 < accuracy <= 0.5):
        raise ValueRangeError(f"accuracy must lie in (0, 0.5] (a relative error); got {accuracy}")
    floor = 1e3 * torch.finfo(scene.dtype).eps
    if accuracy < floor:
        raise ValueRangeError(
            f"accuracy {accuracy:.3g} is below what {scene.dtype} can resolve in this model (about {floor:.1g}: "
            "quadrature, solver and averaging each lose a few digits); use a float64 scene or ask for less"
        )
    if not isinstance(max_facets, int) or max_facets < scene.num_facets:
        raise ValueError(f"max_facets must be an integer >= the scene's {scene.num_facets} facets; got {max_facets!r}")
