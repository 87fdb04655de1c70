"""torch_interreflect: exact, differentiable, spectral infinite-bounce interreflection for PyTorch.

Data flows one way: scene → form factors → (with light and reflectance) solve → radiance → camera → image.

Example:
    >>> import torch, torch_interreflect as ti
    >>> scene = ti.scenes.v_groove(45.0, divisions=4)
    >>> K = ti.form_factors(scene)
    >>> K.num_facets
    32
"""

from . import errors, scenes
from ._version import __version__

from .kernel import FormFactors
from .scene import Scene

__all__ = [
    "FormFactors",
    "Scene",
    "__version__",
    "errors",
    "form_factors",
    "scenes",
]
