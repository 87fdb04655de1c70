"""The form-factor stage: ``F_ij`` between the facets of a scene, and the operator the solver relies on.

- :mod:`.operator`: :class:`FormFactors` (dense or CSR) and the :class:`FormFactorOperator` protocol.
- :mod:`.quadrature`: :func:`form_factors` (Lambert's contour formula, adaptive Gauss quadrature).
- :mod:`.pairs`: culling and classification of facet pairs; :mod:`.fused`: the quadrature's compiled loops and
  their adjoints; :mod:`.fused_points`: the compiled point-to-polygon factors of the final gather;
  :mod:`.compiled`: loading and launching the numba loops (``_numba_*`` modules).
- :mod:`.contour`: :func:`point_polygon_factor`; :mod:`.rules`: quadrature rules and orders.
- :mod:`.basis` (:func:`facet_basis`: a polynomial basis per facet) and :mod:`.moments`
  (:func:`moment_form_factors`: the Galerkin moments on it; compiled loops in ``_numba_moments``).
- :mod:`.visibility`: occlusion by Embree rays (jittered per-point samples); :mod:`.hemisphere`: the hemisphere
  fractions of the sky; :mod:`.sampling`: their low-discrepancy samples; :mod:`.montecarlo`: the paper's estimator.
- :mod:`.hierarchical`: :func:`hierarchical_form_factors` for large scenes (the builder), with
  :mod:`.hierarchical_operator` (:class:`HierarchicalFormFactors`), :mod:`.cluster_tree` (cluster tree and
  traversal) and :mod:`.cluster_visibility` (visible fraction of far blocks).
"""

from .basis import FacetBasis, facet_basis
from .contour import point_polygon_factor
from .hierarchical import HierarchicalFormFactors, hierarchical_form_factors
from .moments import MomentFormFactors, moment_form_factors
from .operator import FormFactorOperator, FormFactors
from .quadrature import form_factors

__all__ = [
    "FacetBasis",
    "FormFactorOperator",
    "FormFactors",
    "HierarchicalFormFactors",
    "MomentFormFactors",
    "facet_basis",
    "form_factors",
    "hierarchical_form_factors",
    "moment_form_factors",
    "point_polygon_factor",
]
