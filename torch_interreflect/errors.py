"""Exceptions and warnings raised by torch_interreflect.

Every validation error is a :class:`ValueError` (or :class:`TypeError`) subclass whose message says what was
expected and what came, so ``except ValueError`` keeps working for callers that do not care which one.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

__all__ = [
    "AccuracyWarning",
    "ConvergenceWarning",
    "DeviceError",
    "GeometryError",
    "GeometryWarning",
    "GradientWarning",
    "InsufficientMemoryError",
    "ShapeError",
    "SingularSystemError",
    "SpectralDataError",
    "ValueRangeError",
    "collect_warnings",
]


class GeometryError(ValueError):
    """Invalid scene geometry: non-finite vertices, degenerate, non-planar or non-convex facets."""


class ShapeError(ValueError):
    """A tensor has a shape (or a wavelength grid) that does not match what the operation needs."""


class ValueRangeError(ValueError):
    """A value lies outside its admissible range (NaN or inf, reflectance outside [0, 1], ...)."""


class SpectralDataError(ValueError):
    """Unknown illuminant, camera or spectral data set, or a wavelength grid outside the data's range."""


class SingularSystemError(ValueError):
    """The interreflection system ``(I - F R) E = E0`` is singular (e.g. reflectance 1 in a closed scene)."""


class ConvergenceWarning(RuntimeWarning):
    """An iterative method stopped at ``max_iter`` before reaching the requested tolerance."""


class AccuracyWarning(UserWarning):
    """The requested accuracy was not reached within the limits (``max_facets``, ``max_iterations``)."""


class DeviceError(ValueError):
    """Tensors that must share a device do not (nothing is moved between devices silently)."""


class InsufficientMemoryError(MemoryError):
    """A computation would need more memory than the machine has; raised before allocating, with the estimate,
    the memory available and a way that needs less (e.g. ``hierarchical_form_factors``)."""


class GeometryWarning(UserWarning):
    """The geometry is valid but probably not what was meant (e.g. no facet pair can exchange light because the
    facets face away from each other: normals pointing out of a concave mesh)."""


class GradientWarning(UserWarning):
    """Autograd will return a gradient that leaves out a known term (e.g. the part of an image's sky hidden by the
    backs of facets, held fixed while the geometry requires grad); the message names the term."""


@contextlib.contextmanager
def collect_warnings(category: type[Warning]) -> Iterator[list[str]]:
    """Collect the messages of ``category`` warnings raised in the block (every one, repeats included, whatever
    the filters say of that category, ``"error"`` too) into the yielded list, for the caller to report once. Other
    warnings go through the filters and are shown as they come.

    Example:
        >>> import warnings
        >>> with collect_warnings(AccuracyWarning) as got:
        ...     warnings.warn("bound 0.015 above tol", AccuracyWarning)
        >>> got
        ['bound 0.015 above tol']
    """
    messages: list[str] = []
    with warnings.catch_warnings():
        warnings.simplefilter("always", category)
        shown = warnings.showwarning

        def show(message: Warning | str, cat: type[Warning], filename: str, lineno: int, file: object = None,
                 line: str | None = None) -> None:
            if issubclass(cat, category):
                messages.append(str(message))
            else:
                shown(message, cat, filename, lineno, file, line)

        warnings.showwarning = show
        yield messages
