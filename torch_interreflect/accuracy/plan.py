"""Planning: the refinement and settings that reach a requested accuracy (:func:`plan`), kept as a :class:`Plan`
that renders differentiably (:meth:`Plan.apply`). How each source of error is bounded: :mod:`.render`."""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from .._threads import compiled_work
from ..camera.rendering import render_view
from ..camera.sensor import Camera
from ..camera.view import View
from ..errors import AccuracyWarning, ShapeError
from ..formfactors.operator import FormFactors
from ..formfactors.quadrature import form_factors
from ..geometry._polygon import bilinear, bilinear_coordinates
from ..geometry.contacts import split_at_contacts
from ..geometry.scene import Scene, area_average
from ..solver.api import solve
from ..solver.moments import DENSE_MAX_UNKNOWNS, solve_moments
from ..solver.sky import solve_moments_sky
from .leaves import light_factor, rms
from .moments_plan import leaf_light, moment_report, refine_moments
from .moments_settings import (
    constant_probe_pays,
    moment_quadrature_tol,
    polynomial_allowed,
    smooth_light,
    solver_tolerance,
)
from .refine import AMPLIFICATION, Problem, Refinement, refine
from .report import AccuracyReport, RenderResult
from .request import check_request
from .settings import Settings, budget_for, choose_settings, quadrature_tol_for
from .wavelengths import grid_of, interp_matrix, spectra

__all__ = ["Plan", "plan"]


@dataclass
class Plan:
    """The refined scene and settings :func:`plan` chose; :meth:`apply` renders with them (differentiably).

    Attributes:
        scene: The user's scene. ``leaves``: the refined scene that is solved; ``leaf_user [n]``: the user facet of
            each leaf.
        form_factors: Form factors of the leaves (sparsified when that paid). ``light_factor [n]``: ``g`` of the
            light on the leaves (``E0 = g ⊗ spectrum``).
        grid: The full wavelength grid ``[L]``; ``nodes``: indices of the wavelengths solved ``[L']``.
        method, bounces, solver_tol: How the final system is solved.
        report: What was chosen and the estimated error (for the reflectance and light the plan was made with).
        light: The light as :func:`plan` got it (per user facet); images gather their direct light from it.
        coarse: Every user facet one split back (its leaves before its own last split), as a plan with the same
            settings (``None`` when the plan did not refine); ``extrapolation [F]``: the coefficient ``c`` of each
            user facet in the extrapolated output ``x + c (x − x_coarse)`` (Richardson; 0 where it is not used).
        degree: Degree of the polynomial irradiance per leaf (0: constant; 2: ``form_factors`` are
            :class:`~torch_interreflect.formfactors.moments.MomentFormFactors` and ``light_factor`` the light's
            moments ``[n, nb]``, :mod:`.moments_plan`). ``sky_rows``: there, under a sky, its other estimate
            ``[n, nb]``, weighed with ``light_factor`` at each solve (``ti.solver.solve_moments_sky``; a
            ``dataclasses.replace`` of ``light_factor`` needs ``sky_rows=None`` or its own).
    """

    scene: Scene
    leaves: Scene
    leaf_user: Tensor
    form_factors: FormFactors
    light_factor: Tensor
    grid: Tensor
    nodes: Tensor
    method: str
    bounces: int | None
    solver_tol: float
    report: AccuracyReport
    light: Any = "uniform"
    coarse: Plan | None = None
    extrapolation: Tensor | None = None
    degree: int = 0
    sky_rows: Tensor | None = None

    def for_geometry(self, scene: Scene) -> Plan:
        """The same refinement and settings on ``scene``: the user's facets at other positions (same count, kind and
        order), e.g. a deformed groove in a fitting loop, or the planned scene itself with corners that require
        grad.

        Each leaf keeps its bilinear coordinates in its user facet, so the leaves follow the facets; the form
        factors (not sparsified) and the light factor are computed again on the moved leaves, keeping the graph of
        ``scene.corners`` (and of a light direction that requires grad); so does the coarse level of an extrapolated
        plan. The report is the original plan's: its estimate holds for small moves.

        Raises:
            ShapeError: ``scene`` has other facets than the plan's.
            ValueError: the plan is on the quadratic basis (its moments are not differentiable in the geometry:
                plan with ``basis="constant"``).
        """
        self._check_geometry_fixed()
        if scene.num_facets != self.scene.num_facets or not torch.equal(scene.is_triangle.cpu(),
                                                                          self.scene.is_triangle.cpu()):
            raise ShapeError(f"for_geometry needs the plan's {self.scene.num_facets} facets (same kinds, same order); "
                             f"got {scene.num_facets}")
        user = self.leaf_user.to(scene.device)
        leaves = self._moved_leaves(scene)
        K = form_factors(leaves, quadrature_tol=self.report.quadrature_tol, progress=False)
        g = light_factor(self.light, leaves, K, user, scene.num_facets)
        coarse = self._coarse().for_geometry(scene) if self.coarse is not None else None  # type: ignore[union-attr]
        return Plan(scene, leaves, self.leaf_user, K, g, self.grid, self.nodes, self.method, self.bounces,
                    self.solver_tol, self.report, self.light, coarse, self.extrapolation)

    def _moved_leaves(self, scene: Scene) -> Scene:
        """The leaves at ``scene``'s corners: each keeps its bilinear coordinates in its user facet (differentiable
        in ``scene.corners``)."""
        user = self.leaf_user.to(scene.device)
        uv = bilinear_coordinates(self.scene.corners[user].detach(), self.leaves.corners.detach())  # [n, 4, 2], fixed
        corners = bilinear(scene.corners[user], uv[..., 0], uv[..., 1])[0]  # [n, 4, 3]
        return Scene.from_parts(corners, self.leaves.is_triangle, self.leaves.material, self.leaves.material_names)

    def apply(
        self,
        reflectance: Tensor,
        illuminant: Tensor | str | float = "D65",
        camera: Camera | None = None,
        *,
        view: View | None = None,
        shading: str = "gather",
    ) -> RenderResult:
        """Render with the planned refinement and settings: differentiable in reflectance and illuminant.

        Args:
            reflectance: Per user facet, in [0, 1]. Shape ``[..., F, L]`` or ``[..., F]``.
            illuminant: Spectrum ``[..., L]`` on the grid, or a name / CCT.
            camera: Camera for ``rgb`` (its grid must be the plan's).
            view: A pinhole view (:class:`~torch_interreflect.camera.View`): the result then carries ``image``,
                linear camera RGB ``[..., C, H, W]`` (spectral radiance ``[..., L, H, W]`` without a camera), shaded
                from the solved leaves by a final gather per pixel (:func:`~torch_interreflect.camera.render_view`).
            shading: ``"gather"`` (per-pixel final gather, the default) or ``"flat"`` (each leaf one colour).

        Returns:
            A :class:`RenderResult` on the user's facets; its report is the plan's. When the plan refined, the
            per-facet outputs are extrapolated against each facet one split back (:attr:`extrapolation`; the
            coarse level is solved too); the ``image`` is shaded from the last level's leaves.

        Gradients:
            To ``reflectance`` and ``illuminant``; and, when the plan's scene was built from corners that require
            grad (or the light is a direction that requires grad), to those: the leaves follow their user facets
            (:meth:`for_geometry`) and the form factors, light factor and areas carry the gradient of the moved
            leaves while their values stay the plan's. Ray-cast visibility and sun shadows carry the gradient of
            their moving shadow edges as in :func:`~torch_interreflect.form_factors` and
            :func:`~torch_interreflect.lights.directional`. With a ``view`` the image passes them too: hit points,
            per-pixel kernel, per-pixel sun cosines, and the edges of silhouettes, facets and sun shadows in the
            image (:mod:`~torch_interreflect.camera.image_grad`; a
            :class:`~torch_interreflect.errors.GradientWarning` names what is held). Memory grows with the leaves'
            pairs (the form factors are rebuilt densely).

        Shape:
            - reflectance: ``[..., F, L]`` or ``[..., F]``; illuminant: ``[..., L]``
            - output irradiance, radiance: ``[..., F, L]``; rgb: ``[..., F, C]``; image: ``[..., C, H, W]``
        """
        fine = self._apply_level(reflectance, illuminant, camera, view, shading)
        if self.coarse is None or self.extrapolation is None:
            return fine
        low = self._coarse()._apply_level(reflectance, illuminant, camera, None, shading)  # type: ignore[union-attr]
        c = self.extrapolation.to(device=fine.irradiance.device, dtype=fine.irradiance.dtype)[:, None]
        E = fine.irradiance + c * (fine.irradiance - low.irradiance)
        rgb = fine.rgb + c * (fine.rgb - low.rgb) if fine.rgb is not None and low.rgb is not None else None
        _, r = spectra(self.grid, illuminant, reflectance, self.scene.num_facets)
        return RenderResult(E, r * E / math.pi, rgb, self.report, fine.image)

    def _coarse(self) -> Plan | None:
        """The coarse level with this plan's scene, grid, wavelengths, light and solver (they may have been replaced
        since planning, e.g. ``dataclasses.replace(plan, nodes=...)``). Its leaves, form factors and light factor
        stay its own: a plan whose ``leaves`` / ``form_factors`` / ``light_factor`` are replaced needs
        ``coarse=None``."""
        if self.coarse is None:
            return None
        return dataclasses.replace(self.coarse, scene=self.scene, grid=self.grid, nodes=self.nodes, light=self.light,
                                   method=self.method, bounces=self.bounces, solver_tol=self.solver_tol)

    def _check_geometry_fixed(self) -> None:
        if self.degree > 0:
            raise ValueError(
                f"this plan solves on a polynomial basis of degree {self.degree}, whose moments are constants of the "
                "geometry: it cannot follow moved corners or pass gradients to them; plan with basis='constant' "
                "(render(..., basis='constant')) for gradients to the geometry"
            )

    def _apply_level(
        self, reflectance: Tensor, illuminant: Tensor | str | float, camera: Camera | None, view: View | None,
        shading: str,
    ) -> RenderResult:
        """:meth:`apply` on this level's leaves alone (no extrapolation)."""
        F, L = self.scene.num_facets, self.grid.numel()
        S, r = spectra(self.grid, illuminant, reflectance, F)
        nodes, user = self.nodes, self.leaf_user
        refl_leaf = r[..., user, :][..., nodes]
        if self.degree > 0:
            light_grad = isinstance(self.light, Tensor) and self.light.requires_grad
            if torch.is_grad_enabled() and (self.scene.corners.requires_grad or light_grad):
                self._check_geometry_fixed()
            K, g, areas = self.form_factors, self.light_factor, self.leaves.areas
            g = g.to(device=refl_leaf.device, dtype=refl_leaf.dtype)
            M: Any = K  # MomentFormFactors where degree > 0
            h = self._planned(r, refl_leaf)  # the planner's last solve, for this reflectance
            if h is None and self.sky_rows is None:
                gl = g[:, :, None].expand(-1, -1, refl_leaf.shape[-1])
                h = solve_moments(M, refl_leaf, gl, tol=self.solver_tol, method=self.method)[..., 0, :]
            elif h is None:  # unit sky radiance per wavelength (S carries the spectrum)
                h = solve_moments_sky(M, refl_leaf, g, self.sky_rows.to(g), refl_leaf.new_ones(nodes.numel()),
                                      tol=self.solver_tol, method=self.method)[..., 0, :]
        else:
            K, g, areas = self._geometry()
            e0 = g.to(refl_leaf.dtype)[:, None].expand(-1, refl_leaf.shape[-1])
            if self.method == "series":
                h = solve(K, refl_leaf, e0, bounces=self.bounces)
            else:
                h = solve(K, refl_leaf, e0, tol=self.solver_tol, method=self.method)
        h_full = h @ interp_matrix(self.grid[nodes], self.grid).to(h.dtype) if nodes.numel() < L else h
        E_leaf = S[..., None, :] * h_full
        E = area_average(E_leaf, user, areas, F)
        rgb = None
        if camera is not None:
            if camera.num_wavelengths != L:
                raise ShapeError(f"the camera has {camera.num_wavelengths} wavelengths but the plan's grid {L}")
            rgb = area_average(camera(r[..., user, :] * E_leaf / math.pi), user, areas, F)
        image = None
        if view is not None:
            moved = None
            if torch.is_grad_enabled() and self.scene.corners.requires_grad and not self.leaves.corners.requires_grad:
                moved = self._moved_leaves(self.scene)  # the image's gradient to the corners (image_grad)
            r_leaf = r[..., user, :].expand(*E_leaf.shape[:-2], -1, -1)
            image = render_view(self.leaves, r_leaf, E_leaf, S, camera, view, self._leaf_light(), shading=shading,
                                geometry=moved)
        return RenderResult(E, r * E / math.pi, rgb, self.report, image)

    def _planned(self, r: Tensor, refl_leaf: Tensor) -> Tensor | None:
        """The leaf averages of the gain that :func:`plan` solved last on the quadratic basis, where this level solves
        the same system: the plan's own moments, light and grid (not replaced since), the reflectance ``r [..., F, L]``
        equal to the planner's and not requiring grad, the same solver settings (:func:`render` is
        ``plan(...).apply(...)``: one solve fewer, 2 of the box corner's 20 ms). None elsewhere."""
        saved = self.__dict__.get("_solved")
        if saved is None or (torch.is_grad_enabled() and r.requires_grad):
            return None
        (r0, key, h), now = saved, self._solve_key()
        same = (all(a is b for a, b in zip(key[:4], now[:4], strict=True)) and key[4:] == now[4:]
                and r.shape == r0.shape and r.dtype == r0.dtype and r.device == r0.device and torch.equal(r, r0))
        return h if same and h.shape == refl_leaf.shape and h.dtype == refl_leaf.dtype else None

    def _solve_key(self) -> tuple[Any, ...]:
        """A solve's inputs beside the reflectance: objects (by identity), the light's version, solver settings."""
        return (self.form_factors, self.light_factor, self.sky_rows, self.nodes, self.light_factor._version,
                self.solver_tol, self.method)

    def _geometry(self) -> tuple[FormFactors, Tensor, Tensor]:
        """Form factors, light factor and leaf areas to solve with: the plan's; when the user's corners (or a light
        direction) require grad, the same values carrying the gradient of :meth:`for_geometry` (straight-through:
        ``planned + (moved − moved.detach())``), so the output does not change, only its graph."""
        light_grad = isinstance(self.light, Tensor) and self.light.requires_grad
        if not (torch.is_grad_enabled() and (self.scene.corners.requires_grad or light_grad)):
            return self.form_factors, self.light_factor, self.leaves.areas
        if self.form_factors.matrix.requires_grad:  # built by for_geometry: already carries the graph
            return self.form_factors, self.light_factor, self.leaves.areas
        if not self.scene.corners.requires_grad:  # only the light: its factor on the planned leaves
            g = light_factor(self.light, self.leaves, self.form_factors, self.leaf_user.to(self.scene.device),
                             self.scene.num_facets)
            return self.form_factors, _straight_through(self.light_factor, g), self.leaves.areas
        moved = dataclasses.replace(self, coarse=None).for_geometry(self.scene)  # the coarse level moves on its own
        matrix = _straight_through(_dense(self.form_factors.matrix), _dense(moved.form_factors.matrix))
        return (FormFactors(matrix, moved.leaves.areas, dict(self.form_factors.info)),
                _straight_through(self.light_factor, moved.light_factor),
                _straight_through(self.leaves.areas, moved.leaves.areas))

    def _leaf_light(self) -> Any:
        """The light on the leaves: per-user-facet tensors (a factor or a mask) follow each leaf's user facet."""
        return leaf_light(self.light, self.leaf_user, self.scene.num_facets)


def _dense(m: Tensor) -> Tensor:
    return m.to_dense() if m.layout != torch.strided else m


def _straight_through(value: Tensor, moved: Tensor) -> Tensor:
    """``value`` (detached) carrying the gradient of ``moved``: ``value + (moved − moved.detach())``."""
    return value.detach().to(moved.dtype) + (moved - moved.detach())


def plan(
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
    basis: str = "auto",
) -> Plan:
    """Choose the refinement and settings that reach ``accuracy`` for this reflectance and light.

    Same arguments as :func:`render` (which is ``plan(...).apply(...)``), ``basis`` included. Nothing here is
    differentiated.

    Returns:
        A :class:`Plan`.

    Example:
        >>> import torch, torch_interreflect as ti
        >>> scene = ti.scenes.v_groove(60.0, divisions=2, dtype=torch.float64)
        >>> p = ti.accuracy.plan(scene, torch.full((8,), 0.5, dtype=torch.float64), accuracy=2e-2)
        >>> p.apply(torch.full((8,), 0.4, dtype=torch.float64)).irradiance.shape
        torch.Size([8, 31])
    """
    t_start = time.perf_counter()
    check_request(scene, accuracy, max_facets)
    quadratic = polynomial_allowed(basis, scene, light)
    if quadratic and basis == "auto":
        # one constant solve with its a-priori estimate, kept where it meets the request (constant_probe_pays)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AccuracyWarning)
            pb0 = _problem(scene, reflectance, light, illuminant, camera, accuracy, wavelengths, extrapolate)
            probe = _plan_constant(pb0, light, max_facets, max_iterations=0, show=False, t_start=time.perf_counter(),
                                   probe=True) if constant_probe_pays(pb0.r, accuracy, scene) else None
        if probe is not None and probe.report.reached:
            return probe
    pb = _problem(scene, reflectance, light, illuminant, camera, accuracy, wavelengths, extrapolate and not quadratic)
    show = progress if progress is not None else scene.num_facets >= 2000 or accuracy < 3e-3
    if quadratic:
        contact_split = split_at_contacts(scene)  # once for the light's test and the planner's first leaves
        return _plan_quadratic(pb, light, max_facets, max_iterations, show, t_start,
                               not smooth_light(scene, light, contact_split[0]), contact_split)
    return _plan_constant(pb, light, max_facets, max_iterations, show, t_start)


def _plan_constant(pb: Problem, light: Any, max_facets: int, max_iterations: int, show: bool, t_start: float,
                   probe: bool = False) -> Plan:
    """:func:`plan` on the constant basis (:func:`~.refine.refine`). ``probe``: the first look of ``basis="auto"``,
    kept only where it reaches the request, so the ray-cast light's check is skipped where the a-priori estimate alone
    is above it (:func:`~.refine.refine`)."""
    scene, accuracy = pb.scene, pb.accuracy
    with warnings.catch_warnings():
        # the planning solves (each level, the a-priori estimate) would each repeat the solver's closure-error
        # warning of the same form factors; the solve of the chosen plan (Plan.apply) raises it once
        warnings.filterwarnings("ignore", message=r"solve\(", category=AccuracyWarning)
        st = refine(pb, max_facets=max_facets, max_iterations=max_iterations, show=show, t_start=t_start,
                    probe=probe)
    t = time.perf_counter()
    r_max = float(pb.r.max()) if pb.r.numel() else 0.0
    amp = _amplification(st)
    settings = choose_settings(st.K, st.h, st.leaves, pb.F, r_max, accuracy, pb.budget, amp)  # type: ignore[arg-type]
    pb.seconds["sparsify"] = time.perf_counter() - t
    report = _report(pb, st, settings, t_start, amp)
    if not report.reached:
        warnings.warn(
            f"render: requested accuracy {accuracy:.3g} not reached; estimated {report.estimated:.3g} after "
            f"{st.iterations} refinements ({st.leaves.scene.num_facets} facets), stopped by "
            f"{st.reason or _over_budget(report)}. Raise max_facets / max_iterations or ask for less.",
            AccuracyWarning,
            stacklevel=4,
        )
    coarse, coef = None, None
    if st.coarse is not None and st.coef is not None and bool((st.coef > 0).any()):
        lv = st.coarse
        coarse = Plan(scene, lv.leaves.scene, lv.leaves.user, lv.K, lv.g, pb.grid, st.nodes,  # type: ignore[arg-type]
                      settings.method, settings.bounces, settings.solver_tol, report, light)
        coef = st.coef.to(device=scene.device, dtype=scene.dtype)
    return Plan(scene, st.leaves.scene, st.leaves.user, settings.form_factors, st.g, pb.grid,
                st.nodes, settings.method, settings.bounces, settings.solver_tol,  # type: ignore[arg-type]
                report, light, coarse, coef)


def _plan_quadratic(pb: Problem, light: Any, max_facets: int, max_iterations: int, show: bool, t_start: float,
                    halving: bool, contact_split: tuple[Scene, Tensor]) -> Plan:
    """:func:`plan` on the polynomial basis (:mod:`.moments_plan`); ``halving``: the light is rough over some piece
    (:func:`~.moments_settings.smooth_light`), so the error is estimated from splitting leaves, not from the degrees.
    ``contact_split``: the scene split at contacts, pieces and their user facets
    (:func:`~torch_interreflect.geometry.split_at_contacts`)."""
    pb.quadrature_tol = moment_quadrature_tol(pb.accuracy)
    kw = {"max_unknowns": max_facets, "max_iterations": max_iterations, "show": show, "t_start": t_start,
          "contact_split": contact_split}
    with compiled_work():  # the planner's torch glue on one thread; loops, rays and big solves on the caller's
        st = refine_moments(pb, halving=halving, **kw)
        if st.rough is not None and bool(st.rough.any()):
            # a rough light that the first test missed (a shadow edge between its 4 × 4 rays), or degrees that do not
            # converge on the first level (Q_CONVERGED): the degrees' difference does not bound the error there
            st = refine_moments(pb, halving=True, **kw)
    n = st.leaves.scene.num_facets
    # each apply picks dense or CG for its own reflectance columns (solver's cost model); CG above DENSE_MAX_UNKNOWNS
    method = "auto" if st.K.size * n <= DENSE_MAX_UNKNOWNS else "cg"
    tol = solver_tolerance(pb.accuracy)
    report = moment_report(pb, st, method, tol, t_start)
    if not report.reached:
        why = st.reason or _over_budget(report)
        warnings.warn(
            f"render: requested accuracy {pb.accuracy:.3g} not reached; estimated {report.estimated:.3g} on the "
            f"polynomial basis (degree {st.K.degree}) after {st.iterations} refinements ({n} leaves), stopped by "
            f"{why}. Raise max_facets / max_iterations or ask for less.", AccuracyWarning, stacklevel=3)
    p = Plan(pb.scene, st.leaves.scene, st.leaves.user, st.K, st.g, pb.grid,  # type: ignore[arg-type]
             torch.arange(pb.grid.numel(), device=pb.grid.device), method, None, tol, report, light,
             degree=st.K.degree, sky_rows=st.rows)
    if st.h is not None:  # not a field: a dataclasses.replace of the plan drops it (Plan._planned)
        p.__dict__["_solved"] = (pb.r, p._solve_key(), st.h)
    return p


def _over_budget(report: AccuracyReport) -> str:
    """Why the estimate is above the request although refinement met its share."""
    light = report.parts.get("light", 0.0)
    if light > 0.25 * report.requested:
        return (
            f"the ray-cast part of the light (the sky's open part where facets occlude each other: {light:.3g} "
            "relative, measured by casting its rays again; refinement does not lower it)"
        )
    return "the error budget"


def _problem(
    scene: Scene,
    reflectance: Tensor,
    light: str | Tensor | Sequence[float],
    illuminant: Tensor | str | float,
    camera: Camera | None,
    accuracy: float,
    wavelengths: Tensor | None,
    extrapolate: bool,
) -> Problem:
    """The validated, detached inputs on the grid, and the budget."""
    grid = grid_of(camera, wavelengths, scene.dtype, scene.device)
    S, r = spectra(grid, illuminant, reflectance, scene.num_facets)
    budget = budget_for(camera)
    return Problem(
        scene,
        grid,
        S.detach(),
        r.detach(),
        camera,
        light,
        float(accuracy),
        budget,
        quadrature_tol_for(accuracy, budget, AMPLIFICATION if extrapolate else 1.0),
        max(1e-10, 1e-3 * accuracy),
        extrapolate=bool(extrapolate),
    )


def _amplification(st: Refinement) -> float:
    """How many times the output can carry one level's error from the other sources: ``1 + 2 max c`` for the
    extrapolated ``(1 + c) x − c x_coarse`` (1 without extrapolation)."""
    return 1.0 + 2.0 * (float(st.coef.max()) if st.coef is not None and st.coef.numel() else 0.0)


def _report(pb: Problem, st: Refinement, settings: Settings, t_start: float, amp: float) -> AccuracyReport:
    """The :class:`AccuracyReport`: parts per source, their sum, and what was chosen (``amp``:
    :func:`_amplification`; the sparsification and solver bounds already include it)."""
    F = pb.F
    light = st.light_error if st.light_error is not None else torch.zeros_like(st.est)
    if st.coef is not None:  # the ray-cast light's error differs between the two levels' leaves: up to 1 + 2c
        light = light * (1 + 2 * st.coef)
    parts = {
        "discretisation": rms(st.est),
        "form_factors": amp * pb.quadrature_tol,
        "sparsification": amp * settings.sparse_bound,
        "solver": amp * settings.solver_bound,
        "wavelengths": st.wavelength_error,
        "light": rms(light),
    }
    total = sum(v for v in parts.values() if math.isfinite(v))
    per_facet = st.est + light + (total - parts["discretisation"] - parts["light"])
    pb.seconds["total"] = time.perf_counter() - t_start
    return AccuracyReport(
        requested=pb.accuracy,
        estimated=total,
        estimated_max=float(per_facet.max()) if F else 0.0,
        per_facet=per_facet,
        parts=parts,
        reached=total <= pb.accuracy,
        leaves=st.leaves.scene.num_facets,
        leaves_per_facet=torch.bincount(st.leaves.user.cpu(), minlength=F),
        iterations=st.iterations,
        quadrature_tol=pb.quadrature_tol,
        sparsified=settings.form_factors is not st.K,
        dropped=settings.dropped,
        dropped_row_mass=settings.dropped_row_mass,
        method=settings.method,
        bounces=settings.bounces,
        solver_tol=settings.solver_tol,
        wavelengths=pb.grid[st.nodes],
        wavelength_error=st.wavelength_error,
        seconds=pb.seconds,
        history=st.history,
        extrapolated=amp > 1.0,
    )
