"""What :func:`~torch_interreflect.accuracy.render` returns: the result on the user's facets and its report."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

from torch import Tensor

__all__ = ["AccuracyReport", "RenderResult"]


@dataclass
class AccuracyReport:
    """What :func:`render` chose and the error it estimates it left.

    Attributes:
        requested: The requested relative RMS error.
        estimated: Estimated relative RMS error over the user's facets (and columns) of the returned output: the
            discretisation estimate plus the bounds of the other sources.
        estimated_max: The largest per-facet estimate.
        per_facet: Estimated relative error per user facet. Shape ``[F]``.
        parts: Estimated (discretisation, ray-cast light) or bounded (the rest) relative RMS error per source.
        reached: Whether ``estimated <= requested``.
        leaves: Facets actually solved (after refinement; when extrapolated, the coarse level's leaves,
            ``Plan.coarse.leaves``, are solved as well).
        leaves_per_facet: Leaves per user facet. Shape ``[F]``.
        iterations: Refinement steps (solves of a refined mesh).
        quadrature_tol: Per-entry form-factor quadrature tolerance used (``form_factor_tol`` is the deprecated
            name).
        sparsified: Whether the matrix was sparsified; ``dropped`` the fraction of entries dropped and
            ``dropped_row_mass`` the largest dropped row sum.
        method: ``"series"`` (the n-bounce model with ``bounces``), the method used (``"cg"``, ``"dense"``...), or
            ``"auto"`` on the polynomial basis (dense or CG by the solver's cost model at each solve).
        bounces: Terms of the series (``None`` for an iterative solve), ``solver_tol`` its tolerance.
        wavelengths: The wavelengths solved (a subset of the grid when the output is camera RGB). Shape ``[L']``.
        wavelength_error: RGB error of the subset against the full grid, measured on the user's facets.
        seconds: Wall time per stage.
        history: Per refinement step: leaves, estimated discretisation error, seconds.
        extrapolated: Whether the outputs are extrapolated against each facet one split back (the coarse level is
            solved too; :attr:`Plan.extrapolation`).
        degree: Degree of the polynomial irradiance inside every leaf (0: one constant per leaf; 1 or 2: the linear or
            quadratic basis of :mod:`torch_interreflect.accuracy.moments_plan`).
    """

    requested: float
    estimated: float
    estimated_max: float
    per_facet: Tensor
    parts: dict[str, float]
    reached: bool
    leaves: int
    leaves_per_facet: Tensor
    iterations: int
    quadrature_tol: float
    sparsified: bool
    dropped: float
    dropped_row_mass: float
    method: str
    bounces: int | None
    solver_tol: float
    wavelengths: Tensor
    wavelength_error: float
    seconds: dict[str, float] = field(default_factory=dict)
    history: list[dict[str, float]] = field(default_factory=list)
    extrapolated: bool = False
    degree: int = 0

    @property
    def form_factor_tol(self) -> float:
        """Deprecated name of :attr:`quadrature_tol`."""
        warnings.warn(
            "AccuracyReport.form_factor_tol is renamed quadrature_tol; the old name will be removed in the next "
            "release",
            DeprecationWarning,
            stacklevel=2,
        )
        return self.quadrature_tol

    def __str__(self) -> str:
        solver = f"{self.bounces} bounces" if self.method == "series" else f"{self.method} (tol {self.solver_tol:.1g})"
        basis = {0: "", 1: ", linear basis", 2: ", quadratic basis"}.get(self.degree, "")
        return (
            f"accuracy {self.requested:.3g} requested, {self.estimated:.3g} estimated "
            f"({'reached' if self.reached else 'NOT reached'}); {self.leaves} facets solved "
            f"({self.iterations} refinements{basis}), form-factor tol {self.quadrature_tol:.1g}, {solver}, "
            f"{self.wavelengths.numel()} wavelengths, {self.seconds.get('total', 0.0):.2f} s"
        )


@dataclass
class RenderResult:
    """Output of :func:`render` on the user's facets.

    Attributes:
        irradiance: ``E`` in W·m⁻²·nm⁻¹ on the full wavelength grid. Shape ``[..., F, L]``.
        radiance: ``R E / π`` in W·sr⁻¹·m⁻²·nm⁻¹. Shape ``[..., F, L]``.
        rgb: Camera responses when a camera was given, else ``None``. Shape ``[..., F, C]``.
        report: What was chosen and the estimated error.
        image: With a ``view``: the image (linear camera RGB ``[..., C, H, W]``, or spectral radiance
            ``[..., L, H, W]`` without a camera), else ``None``.
    """

    irradiance: Tensor
    radiance: Tensor
    rgb: Tensor | None
    report: AccuracyReport
    image: Tensor | None = None
