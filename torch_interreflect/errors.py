"""Exceptions and warnings raised by torch_interreflect.

Every validation error is a :class:`ValueError` (or :class:`TypeError`) subclass whose message says what was
expected and what came, so ``except ValueError`` keeps working for callers that do not care which one.
"""

from __future__ import annotations

__all__ = [
    "AccuracyWarning",
    "ConvergenceWarning",
    "DeviceError",
    "GeometryError",
    "ShapeError",
    "SingularSystemError",
    "SpectralDataError",
    "ValueRangeError",
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
