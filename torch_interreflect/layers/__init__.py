"""``nn.Module``\\ s over the functional API (kornia style: each function has a thin module beside it).

- :class:`Interreflection` / :func:`render`: reflectance + illuminant → camera RGB (→ images).
- :class:`IlluminantBasis` / :func:`daylight`, :func:`daylight_from_cct`, :func:`planck`: illuminants from a
  few parameters (CIE daylight by M1, M2 or CCT; blackbody by temperature).
- :class:`ReflectanceBasis` / :func:`reflectance_from_coefficients`: a PCA basis of measured reflectances.
- :class:`RGBToSpectrum` / :func:`rgb_to_spectrum`: Mallett & Yuksel (2019) RGB → reflectance upsampling.
"""

from .illuminant import (
    CCT_RANGE,
    IlluminantBasis,
    cct_to_daylight_coefficients,
    daylight,
    daylight_basis,
    daylight_from_cct,
    planck,
)
from .interreflection import Interreflection, light_geometry, render
from .reflectance import (
    ReflectanceBasis,
    RGBToSpectrum,
    coefficients_from_reflectance,
    fit_reflectance_basis,
    mallett2019_basis,
    reflectance_data,
    reflectance_from_coefficients,
    rgb_to_spectrum,
)

__all__ = [
    "CCT_RANGE",
    "IlluminantBasis",
    "Interreflection",
    "RGBToSpectrum",
    "ReflectanceBasis",
    "cct_to_daylight_coefficients",
    "coefficients_from_reflectance",
    "daylight",
    "daylight_basis",
    "daylight_from_cct",
    "fit_reflectance_basis",
    "light_geometry",
    "mallett2019_basis",
    "planck",
    "reflectance_data",
    "reflectance_from_coefficients",
    "render",
    "rgb_to_spectrum",
]
