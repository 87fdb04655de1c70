"""torch_interreflect: exact, differentiable, spectral infinite-bounce interreflection for PyTorch.

Data flows one way, one folder (or file) per stage: ``geometry`` (scenes) → ``formfactors`` → ``lights`` and
``spectral`` (``E0``; ``light_moments`` on the polynomial basis, ``sky_parts`` the sky's two estimates) → ``solver``
→ ``camera`` (sensor RGB, images) → ``accuracy`` (``render``); ``layers`` (nn.Modules), ``inverse``, ``training`` and
``cli`` stand on them.
``training`` is imported on first use.

Example:
    >>> import torch, torch_interreflect as ti
    >>> scene = ti.scenes.v_groove(45.0, divisions=4)
    >>> K = ti.form_factors(scene)
    >>> K.num_facets
    32
"""

import importlib
from typing import Any

from . import (
    accuracy,
    camera,
    errors,
    formfactors,
    geometry,
    inverse,
    layers,
    light_moments,
    lights,
    sky_parts,
    solver,
    spectral,
)
from ._deprecation import moved_attribute
from ._version import __version__
from .accuracy import AccuracyReport, RenderResult, render
from .camera import Camera, View, spectral_to_rgb
from .formfactors import FormFactors, HierarchicalFormFactors, form_factors, hierarchical_form_factors
from .geometry import Scene, scenes
from .solver import SolveInfo, radiance, solve

__all__ = [
    "AccuracyReport",
    "Camera",
    "FormFactors",
    "HierarchicalFormFactors",
    "RenderResult",
    "Scene",
    "SolveInfo",
    "View",
    "__version__",
    "accuracy",
    "camera",
    "errors",
    "form_factors",
    "formfactors",
    "geometry",
    "hierarchical_form_factors",
    "inverse",
    "layers",
    "light_moments",
    "lights",
    "radiance",
    "render",
    "scenes",
    "sky_parts",
    "solve",
    "solver",
    "spectral",
    "spectral_to_rgb",
    "training",
]

#: Modules of earlier releases that moved: ``ti.imaging`` and ``ti.raycast`` still resolve, with a warning.
_MOVED = {
    "imaging": ("torch_interreflect", "camera"),
    "raycast": ("torch_interreflect.geometry", "raycast"),
}


def __getattr__(name: str) -> Any:
    if name == "training":  # heavy (datasets, models): imported on first use
        return importlib.import_module(".training", __name__)
    return moved_attribute(__name__, name, _MOVED)
