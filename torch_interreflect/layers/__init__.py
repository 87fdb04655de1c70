"""``nn.Module``\\ s only: thin holders of parameters over the functions of the pipeline (kornia style).

- :class:`Interreflection`: reflectance + illuminant → camera RGB (→ images); the function is
  :func:`torch_interreflect.camera.facet_rgb`.
- :class:`IlluminantBasis`: illuminants from a few parameters (functions in
  :mod:`torch_interreflect.spectral.illuminants`).
- :class:`ReflectanceBasis`, :class:`RGBToSpectrum`: reflectance bases (functions in
  :mod:`torch_interreflect.spectral.reflectances`).

The functions that used to be importable from here still are, for one release, with a ``DeprecationWarning``
that names their new home (see CHANGELOG.md).
"""

from typing import Any

from .._deprecation import moved_attribute
from .illuminant import IlluminantBasis
from .interreflection import Interreflection
from .reflectance import ReflectanceBasis, RGBToSpectrum

__all__ = ["IlluminantBasis", "Interreflection", "RGBToSpectrum", "ReflectanceBasis"]

_MOVED = {
    "CCT_RANGE": "torch_interreflect.spectral.illuminants",
    "cct_to_daylight_coefficients": "torch_interreflect.spectral.illuminants",
    "daylight": "torch_interreflect.spectral.illuminants",
    "daylight_basis": "torch_interreflect.spectral.illuminants",
    "daylight_from_cct": "torch_interreflect.spectral.illuminants",
    "planck": "torch_interreflect.spectral.illuminants",
    "coefficients_from_reflectance": "torch_interreflect.spectral.reflectances",
    "fit_reflectance_basis": "torch_interreflect.spectral.reflectances",
    "mallett2019_basis": "torch_interreflect.spectral.reflectances",
    "reflectance_data": "torch_interreflect.spectral.reflectances",
    "reflectance_from_coefficients": "torch_interreflect.spectral.reflectances",
    "rgb_to_spectrum": "torch_interreflect.spectral.reflectances",
    "light_geometry": "torch_interreflect.lights",
    "render": ("torch_interreflect.camera.facet_rgb", "facet_rgb"),
}


def __getattr__(name: str) -> Any:
    return moved_attribute(__name__, name, _MOVED)
