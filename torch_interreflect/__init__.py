"""torch_interreflect: exact, differentiable, spectral infinite-bounce interreflection for PyTorch.

Data flows one way: scene → form factors → (with light and reflectance) solve → radiance → camera → image.

Example:
    >>> import torch, torch_interreflect as ti
    >>> scene = ti.scenes.v_groove(45.0, divisions=4)
    >>> K = ti.form_factors(scene)
    >>> K.num_facets
    32
"""

from . import accuracy, camera, errors, imaging, inverse, layers, lights, raycast, scenes, spectral, training
from ._version import __version__
from .accuracy import AccuracyReport, RenderResult, render
from .camera import Camera, spectral_to_rgb
from .formfactors import form_factors
from .hierarchical import HierarchicalFormFactors, hierarchical_form_factors
from .kernel import FormFactors
from .scene import Scene
from .solve import radiance, solve

__all__ = [
    "AccuracyReport",
    "Camera",
    "FormFactors",
    "HierarchicalFormFactors",
    "RenderResult",
    "Scene",
    "__version__",
    "accuracy",
    "camera",
    "errors",
    "form_factors",
    "hierarchical_form_factors",
    "imaging",
    "inverse",
    "layers",
    "lights",
    "radiance",
    "raycast",
    "render",
    "scenes",
    "solve",
    "spectral",
    "spectral_to_rgb",
    "training",
]
