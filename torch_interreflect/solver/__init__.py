"""The solve stage: ``(I − F R) E = E0`` for every wavelength and batch element, and radiance ``R E / π``.

- :mod:`.api`: :func:`solve`, :func:`solve_with_info` (returns :class:`Solution`), :func:`radiance`,
  :class:`SolveInfo` (validation, method choice, dispatch on the form-factor protocol).
- :mod:`.plan`, :mod:`.columns`, :mod:`.dense`, :mod:`.krylov`: the plan of a matrix, the column driver, the dense
  (Cholesky of the SPD form; guarded LU without reciprocity) and Krylov (CG on the SPD form, Neumann) solvers.
- :mod:`.operator`: solving with an operator (hierarchical form factors) instead of a stored matrix.
- :mod:`.moments`: :func:`solve_moments`, the Galerkin system on a polynomial basis per facet;
  :func:`solve_moments_twice`, two solves of one system on one factorisation.
- :mod:`.sky`: :func:`solve_moments_sky` and :func:`solve_sky`, under a sky, its two estimates of the open part
  weighed per facet (polynomial and constant basis).

Gradients come from the adjoint system (DESIGN.md §1), never from backpropagating through iterations.
"""

from .api import Solution, SolveInfo, radiance, solve, solve_with_info
from .moments import facet_averages, solve_moments, solve_moments_twice
from .sky import solve_moments_sky, solve_sky

__all__ = ["Solution", "SolveInfo", "facet_averages", "radiance", "solve", "solve_moments", "solve_moments_sky",
           "solve_moments_twice", "solve_sky", "solve_with_info"]
