"""The solve stage: ``(I − F R) E = E0`` for every wavelength and batch element, and radiance ``R E / π``.

- :mod:`.api`: :func:`solve`, :func:`solve_with_info` (returns :class:`Solution`), :func:`radiance`,
  :class:`SolveInfo` (validation, method choice, dispatch on the form-factor protocol).
- :mod:`.plan`, :mod:`.columns`, :mod:`.dense`, :mod:`.krylov`: the plan of a matrix, the column driver, the dense
  (Cholesky of the SPD form; guarded LU without reciprocity) and Krylov (CG on the SPD form, Neumann) solvers.
- :mod:`.operator`: solving with an operator (hierarchical form factors) instead of a stored matrix.

Gradients come from the adjoint system (DESIGN.md §1), never from backpropagating through iterations.
"""

from .api import Solution, SolveInfo, radiance, solve, solve_with_info

__all__ = ["Solution", "SolveInfo", "radiance", "solve", "solve_with_info"]
