"""The spectral stage: wavelength grids, measured spectra (colour-science) and spectral models as functions.

- :mod:`.grid`: :func:`wavelengths`, :func:`check_wavelengths`, :func:`integration_weights`.
- :mod:`.data`: :func:`illuminant`, :func:`blackbody`, :func:`colorchecker`, :func:`reflectance`,
  :func:`camera_sensitivities` (sampled from colour-science on any grid, cached).
- :mod:`.illuminants`: the CIE daylight basis, daylight from a CCT, Planck (differentiable).
- :mod:`.illuminant_basis`: a non-negative basis for any illuminant (daylight, blackbody, fluorescent, LED, lamps).
- :mod:`.reflectances`: measured reflectance sets, PCA bases, Mallett 2019 RGB → spectrum (differentiable).
"""

from . import illuminants, reflectances
from .data import (
    CAMERA_NAMES,
    COLORCHECKER,
    D_SERIES_CCT_RANGE,
    REFLECTANCE_ALIASES,
    blackbody,
    camera_sensitivities,
    colorchecker,
    illuminant,
    illuminant_names,
    reflectance,
    sample_spd,
)
from .grid import check_wavelengths, integration_weights, wavelengths
from .illuminant_basis import (
    ILLUMINANT_FAMILIES,
    coefficients_from_illuminant,
    fit_illuminant_basis,
    illuminant_basis,
    illuminant_from_coefficients,
    illuminant_library,
)
from .illuminants import CCT_RANGE, cct_to_daylight_coefficients, daylight, daylight_basis, daylight_from_cct, planck
from .reflectances import (
    coefficients_from_reflectance,
    fit_reflectance_basis,
    mallett2019_basis,
    reflectance_data,
    reflectance_from_coefficients,
    rgb_to_spectrum,
)

__all__ = [
    "CAMERA_NAMES",
    "CCT_RANGE",
    "COLORCHECKER",
    "D_SERIES_CCT_RANGE",
    "ILLUMINANT_FAMILIES",
    "REFLECTANCE_ALIASES",
    "blackbody",
    "camera_sensitivities",
    "cct_to_daylight_coefficients",
    "check_wavelengths",
    "coefficients_from_illuminant",
    "coefficients_from_reflectance",
    "colorchecker",
    "daylight",
    "daylight_basis",
    "daylight_from_cct",
    "fit_illuminant_basis",
    "fit_reflectance_basis",
    "illuminant",
    "illuminant_basis",
    "illuminant_from_coefficients",
    "illuminant_library",
    "illuminant_names",
    "illuminants",
    "integration_weights",
    "mallett2019_basis",
    "planck",
    "reflectance",
    "reflectance_data",
    "reflectance_from_coefficients",
    "reflectances",
    "rgb_to_spectrum",
    "sample_spd",
    "wavelengths",
]
