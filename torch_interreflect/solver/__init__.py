"""The solve stage: ``(I − F R) E = E0`` for every wavelength and batch element, and radiance ``R E / π``.

- :mod:`.api`: :func:`solve`, :func:`radiance`, :class:`SolveInfo` (validation, method choice, dispatch).
- :mod:`.kernels`: the dense and Krylov (CG on the SPD form, Neumann) column solvers and their plan.
- :mod:`.operator`: solving with an operator (hierarchical form factors) instead of a stored matrix.

Gradients come from the adjoint system (DESIGN.md §1), never from backpropagating through iterations.
"""

from .api import SolveInfo, radiance, solve

__all__ = ["SolveInfo", "radiance", "solve"]
