"""Spectral data: illuminants, ColorChecker reflectances, camera sensitivities.

All data come from `colour-science <https://www.colour-science.org>`_ and are sampled at the wavelengths
you pass, uniform or not. The sampling never touches colour's shared dataset objects: every spectral
distribution is copied first and evaluated with its own interpolator (the one colour assigns to it:
linear for the CIE D-series and illuminant tables, Sprague for 5 nm reflectance tables, ...), so values
on the data's own sampling points are the tabulated values exactly.

Range handling: a grid that reaches outside the native range of a data set raises
:class:`~torch_interreflect.errors.SpectralDataError` by default. Pass ``extrapolate="constant"`` to
repeat the end values outward, or ``extrapolate="zero"`` to set the data to zero outside its range (the
better guess for camera sensitivities). Native ranges worth knowing: CIE illuminant tables 300–780 nm
(F series 380–780 nm), ColorChecker 380–780 nm, "Nikon 5100 (NPL)" 380–780 nm, **"Sigma SDMerill (NPL)"
400–680 nm** (so the default 400–700 nm grid needs ``extrapolate`` for it), CIE 1931 observer 360–830 nm.
The blackbody has no range limit, the D series by CCT covers 300–830 nm.

Results are computed once per (data set, grid, extrapolation) in float64 and cached; each call returns a
fresh tensor (safe to modify in place) on the dtype and device of the ``wavelengths`` tensor (the default
dtype on the CPU for lists and arrays, or for integer tensors).

Units: wavelengths in nm. Illuminants are relative spectral power distributions (see :func:`illuminant`
for the normalisation); reflectances lie in [0, 1]; camera sensitivities are relative, as tabulated.
"""

from __future__ import annotations

import difflib
import functools
import math
import numbers
import re
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from torch import Tensor

from ..errors import SpectralDataError, ValueRangeError
from .grid import cached_on_grid

__all__ = [
    "CAMERA_NAMES",
    "COLORCHECKER",
    "REFLECTANCE_ALIASES",
    "blackbody",
    "camera_sensitivities",
    "colorchecker",
    "illuminant",
    "illuminant_names",
    "reflectance",
    "sample_spd",
]

#: The ColorChecker data set of colour-science that :func:`colorchecker` and :func:`reflectance` use.
COLORCHECKER = "ColorChecker N Ohta"

#: Short names accepted by :func:`reflectance`, and the ColorChecker patch each one means.
REFLECTANCE_ALIASES: dict[str, str] = {
    "grey": "neutral 5 (.70 D)",
    "gray": "neutral 5 (.70 D)",
    "neutral": "neutral 5 (.70 D)",
    "white": "white 9.5 (.05 D)",
    "black": "black 2 (1.5 D)",
}

#: Camera sensitivity data sets of colour-science (``colour.MSDS_CAMERA_SENSITIVITIES``).
CAMERA_NAMES: tuple[str, ...] = ("Nikon 5100 (NPL)", "Sigma SDMerill (NPL)")

_CMFS_ALIASES: dict[str, str] = {
    "cie 1931": "CIE 1931 2 Degree Standard Observer",
    "cie 1964": "CIE 1964 10 Degree Standard Observer",
}

#: Admissible correlated colour temperatures for the CIE D series, in K.
D_SERIES_CCT_RANGE = (4000.0, 25000.0)

Extrapolate = Literal["error", "constant", "zero"]
_EXTRAPOLATE = ("error", "constant", "zero")
# Grid points this far (nm) outside a data set's range still count as inside it.
_RANGE_ATOL = 1e-6

# ---------------------------------------------------------------------------------------------------------
# Wavelength grids
# ---------------------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------------------
# Name lookup and sampling helpers
# ---------------------------------------------------------------------------------------------------------


def _resolve(name: Any, available: Sequence[str], what: str, aliases: dict[str, str] | None = None) -> str:
    """Match ``name`` case-insensitively against ``available`` (and ``aliases``), else raise with hints."""
    if not isinstance(name, str):
        raise TypeError(f"{what} name must be a string; got {type(name).__name__}")
    key = " ".join(name.strip().lower().split())
    lookup = {a.lower(): a for a in available}
    if aliases:
        lookup.update({k.lower(): v for k, v in aliases.items()})
    if key in lookup:
        return lookup[key]
    close = difflib.get_close_matches(key, list(lookup), n=5, cutoff=0.6)
    hint = f"; did you mean {', '.join(repr(lookup[c]) for c in close)}?" if close else ""
    raise SpectralDataError(
        f"unknown {what} {name!r}{hint} Available: {', '.join(repr(a) for a in available)}"
    )


def _check_extrapolate(extrapolate: Any) -> None:
    if extrapolate not in _EXTRAPOLATE:
        raise ValueRangeError(f"extrapolate must be one of {_EXTRAPOLATE}; got {extrapolate!r}")


def sample_spd(data: Any, grid: np.ndarray, extrapolate: str, label: str) -> np.ndarray:
    """Evaluate a colour (multi-)spectral distribution at ``grid`` on a copy, with explicit range handling.

    Returns ``[L]`` for a spectral distribution, ``[L, C]`` for a multi-spectral one.
    """
    lo, hi = float(data.domain[0]), float(data.domain[-1])
    outside = (grid < lo - _RANGE_ATOL) | (grid > hi + _RANGE_ATOL)
    if outside.any() and extrapolate == "error":
        raise SpectralDataError(
            f"{label} is tabulated on {lo:g}–{hi:g} nm but the grid spans {grid[0]:g}–{grid[-1]:g} nm; "
            f"use a grid inside the data's range or pass extrapolate='constant' or 'zero'"
        )
    sd = data.copy()
    values = np.asarray(sd[np.clip(grid, lo, hi)], dtype=np.float64).reshape(grid.size, -1)
    if np.asarray(data.values).ndim == 1:
        values = values[:, 0]
    if extrapolate == "zero" and outside.any():
        values = values.copy()
        values[outside] = 0.0
    return values


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float64)
    a.setflags(write=False)
    return a


# ---------------------------------------------------------------------------------------------------------
# Illuminants
# ---------------------------------------------------------------------------------------------------------


def illuminant_names() -> list[str]:
    """Names of the tabulated illuminants :func:`illuminant` accepts (``colour.SDS_ILLUMINANTS``).

    ``"F1"``–``"F12"`` are accepted as aliases of colour's ``"FL1"``–``"FL12"``.
    """
    import colour

    return list(colour.SDS_ILLUMINANTS.keys())


def _planck(grid_nm: np.ndarray, temperature: float) -> np.ndarray:
    from colour.colorimetry import planck_law

    return np.asarray(planck_law(grid_nm * 1e-9, temperature), dtype=np.float64).reshape(grid_nm.shape)


@functools.lru_cache(maxsize=128)
def _blackbody_np(temperature: float, grid: tuple[float, ...]) -> np.ndarray:
    g = np.asarray(grid)
    return _frozen(100.0 * _planck(g, temperature) / _planck(np.array([560.0]), temperature)[0])


@functools.lru_cache(maxsize=128)
def _d_series_np(cct: float, grid: tuple[float, ...]) -> np.ndarray:
    import colour

    xy = colour.temperature.CCT_to_xy_CIE_D(cct)
    sd = colour.sd_CIE_illuminant_D_series(xy)
    return _frozen(sample_spd(sd, np.asarray(grid), "error", f"CIE D series at {cct:g} K"))


@functools.lru_cache(maxsize=256)
def _named_illuminant_np(name: str, extrapolate: str, grid: tuple[float, ...]) -> np.ndarray:
    import colour

    sd = colour.SDS_ILLUMINANTS[name]
    return _frozen(sample_spd(sd, np.asarray(grid), extrapolate, f"illuminant {name!r}"))


def _check_temperature(temperature: Any) -> float:
    if isinstance(temperature, bool) or not isinstance(temperature, numbers.Real):
        raise TypeError(f"temperature must be a number in K; got {type(temperature).__name__}")
    t = float(temperature)
    if not (math.isfinite(t) and t > 0):
        raise ValueRangeError(f"blackbody temperature must be finite and > 0 K; got {temperature}")
    return t


def blackbody(temperature: float, wavelengths: Tensor | Sequence[float] | np.ndarray) -> Tensor:
    """Relative spectral radiance of a blackbody (Planck's law), 100 at 560 nm.

    Planck's law ``c1 / λ⁵ / (exp(c2 / (λ T)) − 1)`` with colour-science's constants
    (``c2 = 1.4388e-2 m·K``, as in the CIE definition of illuminant A), scaled so the value at 560 nm is
    exactly 100, the CIE convention for illuminant A and the D series. Works at any wavelengths.

    Args:
        temperature: Temperature in K (> 0).
        wavelengths: Strictly increasing wavelengths in nm. Shape ``[L]``.

    Returns:
        Relative spectral power on the dtype/device of ``wavelengths``. Shape ``[L]``.

    Raises:
        ValueRangeError: temperature not finite and positive; bad grid.
        ShapeError: grid not 1-D.

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> s = spectral.blackbody(2856, torch.tensor([460.0, 560.0, 660.0], dtype=torch.float64))
        >>> round(float(s[1]), 9)
        100.0
    """
    return cached_on_grid(_blackbody_np, wavelengths, _check_temperature(temperature))


_BLACKBODY_RE = re.compile(r"^\s*(?:blackbody|planck)\s*[:=]?\s*([0-9.eE+-]+)\s*k?\s*$", re.IGNORECASE)
_FL_RE = re.compile(r"^\s*f\s*(\d+)\s*$", re.IGNORECASE)


def illuminant(
    name_or_cct: str | float,
    wavelengths: Tensor | Sequence[float] | np.ndarray,
    *,
    extrapolate: Extrapolate = "error",
) -> Tensor:
    """Relative spectral power distribution of a CIE illuminant, a D-series daylight or a blackbody.

    ``name_or_cct`` may be

    - the name of a tabulated illuminant in ``colour.SDS_ILLUMINANTS``, case-insensitive: ``"D50"``,
      ``"D65"``, ``"A"``, ``"E"``, ``"FL1"``–``"FL12"`` (``"F1"``–``"F12"`` also accepted), ``"LED-B1"``,
      ... (see :func:`illuminant_names`). Values as tabulated by the CIE: the D series and A are 100 at
      560 nm, E is 100 everywhere, the F series are in their own relative units;
    - a number, the correlated colour temperature in K (4000–25000) of a CIE daylight: the chromaticity
      from ``colour.temperature.CCT_to_xy_CIE_D`` and the spectrum from
      ``colour.sd_CIE_illuminant_D_series`` (``S0 + M1 S1 + M2 S2``, which is 100 at 560 nm by construction;
      valid on 300–830 nm). 6504 K reproduces the D65 table to within 0.1;
    - ``"blackbody:<T>"`` (e.g. ``"blackbody:2856"``), Planck's law at ``T`` kelvin, 100 at 560 nm
      (see :func:`blackbody`).

    Multiply by an irradiance scale to get W·m⁻²·nm⁻¹.

    Args:
        name_or_cct: Illuminant name, CCT in K, or ``"blackbody:<T>"``.
        wavelengths: Strictly increasing wavelengths in nm, uniform or not. Shape ``[L]``.
        extrapolate: Outside a table's range: ``"error"`` (default) raises, ``"constant"`` repeats the end
            values, ``"zero"`` gives zero. Ignored for the blackbody; the D series by CCT always raises
            outside 300–830 nm.

    Returns:
        Relative spectral power on the dtype/device of ``wavelengths``. Shape ``[L]``.

    Raises:
        SpectralDataError: unknown name (the message lists close matches and all names), or a grid outside
            the table's range with ``extrapolate="error"``.
        ValueRangeError: CCT outside [4000, 25000] K; bad grid.
        ShapeError: grid not 1-D.

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> wl = spectral.wavelengths()
        >>> float(spectral.illuminant("D65", wl)[16])  # 560 nm
        100.0
        >>> spectral.illuminant(5000, wl).shape
        torch.Size([31])
    """
    _check_extrapolate(extrapolate)
    if isinstance(name_or_cct, bool):
        raise TypeError("illuminant must be a name or a CCT in K; got a bool")
    if isinstance(name_or_cct, numbers.Real):
        cct = float(name_or_cct)
        lo, hi = D_SERIES_CCT_RANGE
        if not (math.isfinite(cct) and lo <= cct <= hi):
            raise ValueRangeError(
                f"CIE D-series CCT must lie in [{lo:g}, {hi:g}] K; got {name_or_cct}"
            )
        return cached_on_grid(_d_series_np, wavelengths, cct)
    if not isinstance(name_or_cct, str):
        raise TypeError(
            f"illuminant must be a name (str) or a CCT in K (number); got {type(name_or_cct).__name__}"
        )
    m = _BLACKBODY_RE.match(name_or_cct)
    if m:
        try:
            t = float(m.group(1))
        except ValueError as exc:
            raise SpectralDataError(
                f"cannot read a temperature from {name_or_cct!r}; expected e.g. 'blackbody:2856'"
            ) from exc
        return blackbody(t, wavelengths)
    aliases = {}
    fl = _FL_RE.match(name_or_cct)
    if fl:
        aliases[f"f{int(fl.group(1))}"] = f"FL{int(fl.group(1))}"
    name = _resolve(name_or_cct, illuminant_names(), "illuminant", aliases)
    return cached_on_grid(_named_illuminant_np, wavelengths, name, extrapolate)


# ---------------------------------------------------------------------------------------------------------
# Reflectances
# ---------------------------------------------------------------------------------------------------------


def _colorchecker_names() -> list[str]:
    import colour

    return list(colour.SDS_COLOURCHECKERS[COLORCHECKER].keys())


@functools.lru_cache(maxsize=64)
def _colorchecker_np(extrapolate: str, grid: tuple[float, ...]) -> np.ndarray:
    import colour

    g = np.asarray(grid)
    sds = colour.SDS_COLOURCHECKERS[COLORCHECKER]
    return _frozen(np.stack([sample_spd(sd, g, extrapolate, f"{COLORCHECKER} {k!r}") for k, sd in sds.items()]))


def colorchecker(
    wavelengths: Tensor | Sequence[float] | np.ndarray, *, extrapolate: Extrapolate = "error"
) -> tuple[Tensor, list[str]]:
    """Spectral reflectances of the 24 ColorChecker patches ("ColorChecker N Ohta" of colour-science).

    Rows follow the chart from "dark skin" to "black 2 (1.5 D)"; values in [0, 1]; the data cover
    380–780 nm (5 nm, Sprague-interpolated in between).

    Args:
        wavelengths: Strictly increasing wavelengths in nm. Shape ``[L]``.
        extrapolate: ``"error"`` (default), ``"constant"`` or ``"zero"`` outside 380–780 nm.

    Returns:
        ``(reflectance, names)``: reflectances on the dtype/device of ``wavelengths``, shape ``[24, L]``,
        and the 24 patch names in row order.

    Raises:
        SpectralDataError: grid outside 380–780 nm with ``extrapolate="error"``.
        ValueRangeError, ShapeError: bad grid.

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> r, names = spectral.colorchecker(spectral.wavelengths())
        >>> r.shape, names[14]
        (torch.Size([24, 31]), 'red')
    """
    _check_extrapolate(extrapolate)
    return cached_on_grid(_colorchecker_np, wavelengths, extrapolate), _colorchecker_names()


def reflectance(
    name: str, wavelengths: Tensor | Sequence[float] | np.ndarray, *, extrapolate: Extrapolate = "error"
) -> Tensor:
    """Spectral reflectance of one ColorChecker patch, by name.

    Names are the patch names of "ColorChecker N Ohta", case-insensitive (``"red"``, ``"orange"``,
    ``"blue"``, ``"cyan"``, ``"neutral 5 (.70 D)"``, ...); the part before the parenthesis is enough
    (``"neutral 8"``). Short aliases (:data:`REFLECTANCE_ALIASES`): ``"grey"``/``"gray"``/``"neutral"`` →
    ``"neutral 5 (.70 D)"`` (about 19 % reflectance), ``"white"`` → ``"white 9.5 (.05 D)"``, ``"black"`` →
    ``"black 2 (1.5 D)"``.

    Args:
        name: Patch name or alias.
        wavelengths: Strictly increasing wavelengths in nm. Shape ``[L]``.
        extrapolate: ``"error"`` (default), ``"constant"`` or ``"zero"`` outside 380–780 nm.

    Returns:
        Reflectance in [0, 1] on the dtype/device of ``wavelengths``. Shape ``[L]``.

    Raises:
        SpectralDataError: unknown name (the message lists close matches and all names); grid outside the
            data's range with ``extrapolate="error"``.
        ValueRangeError, ShapeError: bad grid.

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> r = spectral.reflectance("grey", spectral.wavelengths())
        >>> 0.18 < float(r.mean()) < 0.21
        True
    """
    _check_extrapolate(extrapolate)
    names = _colorchecker_names()
    aliases = dict(REFLECTANCE_ALIASES)
    aliases.update({n.split(" (")[0]: n for n in names if " (" in n})
    canonical = _resolve(name, names, "ColorChecker patch", aliases)
    r = cached_on_grid(_colorchecker_np, wavelengths, extrapolate)
    return r[names.index(canonical)].clone()


# ---------------------------------------------------------------------------------------------------------
# Camera sensitivities
# ---------------------------------------------------------------------------------------------------------


def _sensitivity_names() -> list[str]:
    import colour

    cmfs = [k for k in colour.MSDS_CMFS if k not in ("cie_2_1931", "cie_10_1964")]
    return [*CAMERA_NAMES, *cmfs]


@functools.lru_cache(maxsize=64)
def _sensitivities_np(name: str, extrapolate: str, grid: tuple[float, ...]) -> np.ndarray:
    import colour

    data = colour.MSDS_CAMERA_SENSITIVITIES[name] if name in CAMERA_NAMES else colour.MSDS_CMFS[name]
    return _frozen(sample_spd(data, np.asarray(grid), extrapolate, f"sensitivities {name!r}").T)


def camera_sensitivities(
    name: str, wavelengths: Tensor | Sequence[float] | np.ndarray, *, extrapolate: Extrapolate = "error"
) -> Tensor:
    """Spectral sensitivities of a camera (or of an observer used as one), one row per channel.

    Accepted names (case-insensitive): ``"Nikon 5100 (NPL)"`` (380–780 nm) and ``"Sigma SDMerill (NPL)"``
    (400–680 nm) from ``colour.MSDS_CAMERA_SENSITIVITIES``, channels (R, G, B), each peak-normalised to 1
    as tabulated; and every colour-matching function set of ``colour.MSDS_CMFS``, notably
    ``"CIE 1931 2 Degree Standard Observer"`` (alias ``"CIE 1931"``, channels x̄, ȳ, z̄, 360–830 nm) and
    ``"CIE 1964 10 Degree Standard Observer"`` (alias ``"CIE 1964"``), values as tabulated.

    Args:
        name: Camera or observer name.
        wavelengths: Strictly increasing wavelengths in nm. Shape ``[L]``.
        extrapolate: ``"error"`` (default), ``"constant"`` or ``"zero"`` outside the data's range. The
            Sigma data end at 680 nm, so the default 400–700 nm grid needs ``"zero"`` (the sensitivities
            there are below 0.6 % of the peak) or ``"constant"``.

    Returns:
        Sensitivities on the dtype/device of ``wavelengths``. Shape ``[3, L]``.

    Raises:
        SpectralDataError: unknown name (the message lists close matches and all names); grid outside the
            data's range with ``extrapolate="error"``.
        ValueRangeError, ShapeError: bad grid.

    Example:
        >>> import torch
        >>> from torch_interreflect import spectral
        >>> spectral.camera_sensitivities("Nikon 5100 (NPL)", spectral.wavelengths()).shape
        torch.Size([3, 31])
    """
    _check_extrapolate(extrapolate)
    canonical = _resolve(name, _sensitivity_names(), "camera", _CMFS_ALIASES)
    return cached_on_grid(_sensitivities_np, wavelengths, canonical, extrapolate)
