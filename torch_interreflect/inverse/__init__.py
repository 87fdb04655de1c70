"""Inverse tools over the interreflection model: reflectance and illuminant estimation, interreflection removal,
recolouring."""

from .tools import (
    IlluminantEstimate,
    Recolored,
    ReflectanceEstimate,
    estimate_illuminant,
    estimate_reflectance,
    recolor,
    reflectance_from_radiance,
    remove_interreflections,
)

__all__ = [
    "IlluminantEstimate",
    "Recolored",
    "ReflectanceEstimate",
    "estimate_illuminant",
    "estimate_reflectance",
    "recolor",
    "reflectance_from_radiance",
    "remove_interreflections",
]
