"""Accuracy as an input: :func:`render` does the least work that reaches a requested relative error.

The user states ``accuracy``, the target *relative RMS error of per-facet irradiance* (or of per-facet camera RGB
when a camera is given): ``sqrt(mean_{facets, columns} ((x − x*) / x*)²)``, the measure of the benchmark. The
error is split into a budget per source (:data:`BUDGET`), and each source gets the cheapest setting that meets
its share:

- **Discretisation** (the only large one). The model is piecewise constant per facet, so the error lives where
  irradiance changes fast inside a facet: near concave edges (the paper's Table 9 and Fig. 12). The scene is
  refined adaptively: every user facet starts as one *leaf*; the user facets that carry the excess estimated error
  have all their leaves split in four (the level of a facet doubles), the others stay. Results are
  area-averaged back onto the user's facets, so the output keeps the user's layout (and total power, since the
  children's areas sum to their parent's). The error of a user facet is estimated from the change of its average
  between two refinements, ``|x_k − x_{k−1}| · q/(1 − q)`` with ``q`` the observed ratio of successive changes
  (0.5, first order, until two changes are known; clamped to ``[1/3, 0.8]``). Facets whose form factors rest on
  ray-cast visibility (a third facet can block some of their pairs) converge slowly and unevenly under refinement
  (the Cornell box: about order 0.65), so they always get the slowest ratio, 0.8 (estimate = 4 × change).
  After a refinement the outputs are extrapolated against each facet one split back (Richardson,
  ``x + c (x − x_coarse)`` with ``c = q/(1 − q) ≤ 2/3`` from one ratio for the scene, 2/3 until one is measured;
  not on facets with ray-cast visibility), and the estimate of an extrapolated facet is how far ``c`` can be from
  its own (a third of its change at its first split), or the change of its extrapolated value when larger
  (:mod:`.refine`); ``extrapolate=False`` turns it off. The discretisation's share is lowered by the measured error of
  a ray-cast light (the sky) when that is small, so that the total can meet the request.
- **Form factors**: the per-entry quadrature tolerance (the Gauss order of every pair follows from it and the
  pair's distance/size ratio).
- **Sparsification**: entries are dropped (in reciprocal pairs, so conjugate gradients still apply) while the
  dropped mass per row stays under a bound whose effect on the solution, ``≤ m r_max ‖E‖∞ / (1 − r_max ρ)``, is
  within its share. It is used only where it makes the matrix sparse enough to pay.
- **Bounces**: the n-bounce series stops when its tail bound ``(r_max ρ)^n / (1 − r_max ρ) · ‖E0‖∞`` is within its
  share; conjugate gradients are used instead when they need fewer products (bright scenes).
- **Ray-cast light** (the sky on scenes where facets occlude each other): its open part and back-face coverage are
  Monte Carlo estimates with the same rays per leaf at every level, so refinement does not lower their error. It
  is measured once, on the user's facets, by casting the rays again with fewer directions (the difference of two
  estimates); it has no share of its own, so when it is large the target is reported not reached (with an
  ``AccuracyWarning`` that names it) instead of being missed silently (the Cornell box under a sky). On the
  quadratic basis, where the scene's openings can be told (the faces of its convex hull no facet covers), the open
  part comes from them instead (:func:`~torch_interreflect.sky_openings.sky_through_openings`): far less noisy.
- **Wavelengths** (camera RGB only): the interreflection gain ``h = E / S`` (``S`` the illuminant) is solved on a
  nested subset of the grid and interpolated linearly in between; the coarsest subset whose RGB error, measured
  on the user's facets against the full grid, is within its share is used for all the work.

Everything chosen and the estimated error come back in :class:`AccuracyReport`.

Where it lives: :mod:`.plan` (:func:`plan`, :class:`Plan`), :mod:`.refine` (the refinement loop and the estimate),
:mod:`.leaves` (leaf bookkeeping, splitting, selection), :mod:`.settings` (the budget, sparsification, solver),
:mod:`.wavelengths` (grid, input spectra, nested subsets), :mod:`.report` (:class:`AccuracyReport`,
:class:`RenderResult`).
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from ..camera.sensor import Camera
from ..camera.view import View
from ..geometry.scene import Scene
from .plan import Plan, plan
from .refine import STALL
from .report import AccuracyReport, RenderResult
from .settings import BUDGET

__all__ = ["BUDGET", "STALL", "AccuracyReport", "Plan", "RenderResult", "plan", "render"]


def render(
    scene: Scene,
    reflectance: Tensor,
    light: str | Tensor | Sequence[float] = "uniform",
    illuminant: Tensor | str | float = "D65",
    camera: Camera | None = None,
    *,
    accuracy: float = 1e-2,
    wavelengths: Tensor | None = None,
    max_facets: int = 12_000,
    max_iterations: int = 12,
    extrapolate: bool = True,
    progress: bool | None = None,
    view: View | None = None,
    shading: str = "gather",
    basis: str = "auto",
) -> RenderResult:
    """Irradiance (and camera RGB) of a scene, computed to a requested relative accuracy.

    The library refines the facets where the error is (near concave edges), picks the quadrature tolerance, the
    sparsity of the form factors, the number of bounces and (for camera RGB) the wavelengths, and returns the
    result on the user's facets with the error it estimates it left (see the module docstring for how). The
    output is differentiable in ``reflectance`` and ``illuminant`` (the choices themselves are not). It is
    :func:`plan` followed by :meth:`Plan.apply`; keep the plan to render other reflectances on the same mesh.

    Args:
        scene: The user's scene; outputs keep its facet layout.
        reflectance: Diffuse reflectance in [0, 1] per user facet. Shape ``[..., F, L]`` or ``[..., F]`` (grey).
        light: ``"uniform"`` (every facet gets the illuminant), ``"sky"`` (a uniform sky of radiance
            ``illuminant``), a direction ``[3]`` (a sun of irradiance ``illuminant``, with cast shadows), a material
            name or a boolean mask ``[F]`` (an area light of radiance ``illuminant``), or a geometric factor ``[F]``
            per user facet (see :func:`torch_interreflect.lights.light_geometry`).
        illuminant: Spectrum of the light on the grid, ``[..., L]`` (W·m⁻²·nm⁻¹, or W·sr⁻¹·m⁻²·nm⁻¹ for the sky
            and area lights), or a name / CCT for :func:`torch_interreflect.spectral.illuminant`.
        camera: When given, the target is the error of camera RGB and the output includes ``rgb``; the camera's
            grid is used.
        accuracy: Target relative RMS error over facets (and columns) of the output, in ``(0, 0.5]``.
        wavelengths: Grid in nm when there is no camera (default 400–700 nm every 10 nm).
        max_facets: Most facets solved after refinement (memory and time grow as their square).
        max_iterations: Most refinement steps. Refinement also stops when two steps lowered the estimate by less
            than :data:`STALL` (then the target is out of reach at any affordable size: a warning says so).
        extrapolate: After a refinement, return the per-facet outputs extrapolated against each facet one split back
            (Richardson; the coarse level is solved too, and the estimate is that of the extrapolated values).
            ``False``: the last level alone.
        progress: Show a progress bar (default: when the work is large).
        view: A pinhole view (:class:`~torch_interreflect.camera.View`): also return ``image``, shaded per pixel by a
            final gather from the solved (refined) facets (:meth:`Plan.apply`).
        shading: ``"gather"`` (default) or ``"flat"`` (each solved facet one colour) for ``image``.
        basis: Irradiance inside every leaf: ``"quadratic"`` (a polynomial of degree 2, Galerkin moments,
            :mod:`.moments_plan`), ``"constant"`` (one value per leaf, refined and extrapolated as described in the
            module docstring), or ``"auto"`` (default): quadratic, except where gradients must reach the geometry
            (the scene's corners or a light direction require grad), which only the constant basis passes.

    Returns:
        A :class:`RenderResult`: ``irradiance``, ``radiance``, ``rgb``, ``image`` (with a ``view``) and the
        :class:`AccuracyReport`.

    Raises:
        ValueRangeError: ``accuracy`` outside ``(0, 0.5]`` or below what the scene's dtype can resolve.
        ShapeError: reflectance or illuminant shapes that do not match the scene and grid.

    Warns:
        AccuracyWarning: the estimate stayed above ``accuracy`` within ``max_facets`` / ``max_iterations``.

    Shape:
        - reflectance: ``[..., F, L]`` or ``[..., F]``
        - illuminant: ``[..., L]``
        - output irradiance, radiance: ``[..., F, L]``; rgb: ``[..., F, C]``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> scene = ti.scenes.v_groove(45.0, divisions=4, dtype=torch.float64)
        >>> out = ti.render(scene, torch.full((32,), 0.8, dtype=torch.float64), light="uniform", accuracy=1e-3)
        >>> out.irradiance.shape, out.report.estimated <= 1e-3, out.report.degree   # quadratic basis
        (torch.Size([32, 31]), True, 2)
        >>> old = ti.render(scene, torch.full((32,), 0.8, dtype=torch.float64), accuracy=1e-2, basis="constant")
        >>> old.report.degree, old.report.leaves > 32                                # refined constant leaves
        (0, True)
    """
    p = plan(
        scene,
        reflectance,
        light,
        illuminant,
        camera,
        accuracy=accuracy,
        wavelengths=wavelengths,
        max_facets=max_facets,
        max_iterations=max_iterations,
        extrapolate=extrapolate,
        progress=progress,
        basis=basis,
    )
    return p.apply(reflectance, illuminant, camera, view=view, shading=shading)
