"""The error budget and the settings chosen after refinement: quadrature tolerance, sparsification, solver.

Each source of error gets a share of the requested accuracy (:data:`BUDGET`). The max-norm bounds of the
sparsification and of a truncated series are turned into per-facet relative ones by the *spread*
``max|h| / |h_i|`` of the solution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

from ..formfactors.operator import FormFactors
from ..solver.method import estimate_cg_iterations
from .leaves import Leaves, rms, to_user

__all__ = ["BUDGET", "Settings", "budget_for", "choose_settings", "quadrature_tol_for"]

#: Share of the requested error given to each source (they add up to 1; without a camera the wavelength share
#: goes to the discretisation).
BUDGET: dict[str, float] = {
    "discretisation": 0.6,
    "form_factors": 0.05,
    "sparsification": 0.1,
    "solver": 0.05,
    "wavelengths": 0.2,
}


def budget_for(camera: object | None) -> dict[str, float]:
    """:data:`BUDGET`, with the wavelength share moved to the discretisation when there is no camera."""
    budget = dict(BUDGET)
    if camera is None:
        budget["discretisation"] += budget.pop("wavelengths")
    return budget


def quadrature_tol_for(accuracy: float, budget: dict[str, float], amplification: float = 1.0) -> float:
    """Per-entry form-factor quadrature tolerance for the form-factor share of ``accuracy``, divided by
    ``amplification`` (how many times an extrapolated output can carry a level's error)."""
    return min(1e-3, max(1e-7, budget["form_factors"] * accuracy / amplification))


@dataclass
class Settings:
    """What is used for the final solve, and the bounds of the error it adds.

    Attributes:
        form_factors: The (possibly sparsified) form factors of the leaves.
        dropped: Fraction of entries dropped; ``dropped_row_mass`` the largest dropped row sum;
            ``sparse_bound`` the bound of the relative error it adds.
        method: ``"series"``, ``"cg"`` or ``"auto"``; ``bounces`` the series terms; ``solver_tol`` the iterative
            tolerance; ``solver_bound`` the bound of the relative error it leaves (NaN when there is none).
    """

    form_factors: FormFactors
    dropped: float
    dropped_row_mass: float
    sparse_bound: float
    method: str
    bounces: int | None
    solver_tol: float
    solver_bound: float


def _spread(h: Tensor, leaves: Leaves, F: int) -> float:
    """RMS over user facets of ``max|h| / |h_i|`` (turns max-norm bounds into per-facet relative ones)."""
    user_h = to_user(h.detach(), leaves, F).abs()
    ratio = user_h.amax(dim=-2, keepdim=True) / user_h.clamp_min(1e-300)
    return max(1.0, rms(ratio.movedim(-2, 0).reshape(F, -1).amax(1))) if F else 1.0


def _sparsify(
    K: FormFactors, share: float, r_max: float, rho: float, spread: float
) -> tuple[FormFactors, float, float, float]:
    """Drop entries (reciprocal pairs) while the error they add stays within ``share``; only when it pays."""
    if rho < 1 and K.is_sparse:  # a dense-stored kernel is too dense for dropping entries to pay
        mass = share * (1 - rho) / max(r_max * spread, 1e-300)
        Ks = K.sparsify(mass)
        if Ks.info["density"] <= 0.1:
            dropped_mass = Ks.info["dropped_row_mass"]
            return Ks, Ks.info["dropped"], dropped_mass, dropped_mass * r_max * spread / (1 - rho)
    return K, 0.0, 0.0, 0.0


def _solver(rho: float, share: float, spread: float, n: int) -> tuple[str, int | None, float, float]:
    """Series (bounces) or CG, whichever needs fewer products for the solver's share; ``"auto"`` with a tight
    tolerance when there is no a-priori bound (``rho >= 1``)."""
    if rho >= 1:
        return "auto", None, 1e-3 * share, math.nan
    target = share * (1 - rho) / spread
    n_series = 1 if rho == 0 else max(1, math.ceil(math.log(target) / math.log(rho)))
    if n_series - 1 <= estimate_cg_iterations(rho, target, n):
        return "series", n_series, 0.0, rho**n_series / (1 - rho) * spread
    return "cg", None, target, share


def choose_settings(
    K: FormFactors, h: Tensor, leaves: Leaves, F: int, r_max: float, accuracy: float, budget: dict[str, float],
    amplification: float = 1.0,
) -> Settings:
    """Sparsification and solver for the final solve on ``leaves``, from the last gain ``h`` solved there; their
    shares are divided by ``amplification`` (an extrapolated output carries up to that many times their error)."""
    spread = _spread(h, leaves, F)
    rho = r_max * float(K.row_sums().max()) if K.num_facets else 0.0
    Kf, dropped, mass, sparse_bound = _sparsify(K, budget["sparsification"] * accuracy / amplification, r_max, rho,
                                                spread)
    method, bounces, tol, bound = _solver(rho, budget["solver"] * accuracy / amplification, spread,
                                          leaves.scene.num_facets)
    return Settings(Kf, dropped, mass, sparse_bound, method, bounces, tol, bound)
