"""The interreflection layer: reflectance and illuminant in, camera RGB (and images) out.

The functional form is :func:`torch_interreflect.camera.facet_rgb`: ``E0 = geometry ⊗ spectrum`` (or a given
``E0``), ``E = solve(F, R, E0)``,
``L = R E / π``, ``rgb = camera(L)``. :class:`Interreflection` holds the form factors, the light's geometric
factor, the camera and optionally a projection and a reflectance parametrisation, all as buffers or submodules.

How a light and a spectrum become ``E0``: :func:`torch_interreflect.lights.light_geometry`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from .. import spectral
from ..accuracy.plan import plan
from ..camera.facet_rgb import facet_rgb
from ..camera.gather import Gather, gather_operator, gathered_image, source_irradiance
from ..camera.image_grad import image_gradient
from ..camera.image_terms import ImageGradient
from ..camera.sensor import Camera
from ..camera.view import View
from ..errors import ShapeError
from ..formfactors.operator import FormFactors
from ..formfactors.quadrature import form_factors as _compute_form_factors
from ..geometry.scene import Scene, area_average
from ..lights import light_geometry
from ..solver.api import radiance, solve

__all__ = ["Interreflection"]


class Interreflection(nn.Module):
    """A differentiable spectral interreflection renderer: reflectance + illuminant → camera RGB (→ images).

    The form-factor matrix (dense or sparse CSR) and areas, the light's geometric factor ``g [F]``, the material
    index and (through submodules) the camera sensitivities, a :class:`~torch_interreflect.imaging.Projection` and
    a reflectance parametrisation are buffers, so ``.to(device, dtype)`` moves everything. Gradients reach the
    reflectance (or its parameters), the illuminant spectrum or ``E0``, and the camera sensitivities, by the
    adjoint of :func:`~torch_interreflect.solve`. Built from a scene whose corners require grad (e.g.
    ``ti.scenes.v_groove(angle)`` with a tensor angle), the form factors and the light factor keep their graph, so
    the output also passes gradients to the geometry (build the layer again after each step that changes it; see
    :func:`torch_interreflect.form_factors` for what the gradient includes); with ``view=`` the images do too
    (:mod:`~torch_interreflect.camera.image_grad`). Not with ``accuracy=`` (the refinement plan is detached).

    Args:
        scene_or_form_factors: A :class:`~torch_interreflect.Scene` (its form factors are computed with default
            settings), a ``(scene, form_factors)`` pair, or a :class:`~torch_interreflect.FormFactors` alone
            (then directional lights, material names and projections need a scene and are unavailable).
        wavelengths: Grid in nm. Shape ``[L]``.
        camera: A :class:`~torch_interreflect.Camera` on that grid, or a sensitivity name for
            :meth:`Camera.from_colour` (default ``"Nikon 5100 (NPL)"``).
        bounces: ``None`` (infinite-bounce) or ``n ≥ 1`` (the paper's n-bounce model).
        light: How a spectrum becomes ``E0`` (module docstring): ``"uniform"`` (default), ``"sky"``, a direction
            ``[3]``, a material name / facet mask (area light), or ``g [F]``.
        projection: A :class:`~torch_interreflect.imaging.Projection` (from
            :func:`~torch_interreflect.imaging.project`); when set, ``forward`` also returns images (one colour
            per facet).
        view: A :class:`~torch_interreflect.camera.View`; when set, ``forward`` also returns images shaded per
            pixel (:func:`~torch_interreflect.camera.gather_operator` of the scene, view and ``light``, built once
            here). Needs a scene and a spectrum ``illuminant`` in ``forward``; not with ``projection`` or
            ``accuracy``.
        shading: With ``view``: ``"gather"`` (per-pixel final gather, the default) or ``"flat"`` (one colour per
            facet).
        reflectance_model: Optional module mapping the first input (e.g. basis coefficients ``[..., K]`` or RGB
            ``[..., 3]``) to reflectance ``[..., L]`` (:class:`ReflectanceBasis`, :class:`RGBToSpectrum`, ...).
        per_material: The reflectance input is per material ``[..., M, ·]`` and is expanded to facets with the
            scene's material index.
        tol: Solver tolerance. method: Solver method (see :func:`~torch_interreflect.solve`).
        shadows: Shadows of a directional light.
        accuracy: Target relative RMS error of the camera RGB per facet (see :func:`torch_interreflect.render`).
            The scene is then refined once, at construction, by :func:`torch_interreflect.accuracy.plan` for
            ``plan_reflectance`` and a D65 illuminant; the layer solves on the refined facets (leaves) and
            area-averages back, so inputs and outputs keep the scene's facets. The plan's report is
            ``accuracy_report``. Needs a Scene; ``bounces``, ``tol`` and ``method`` then come from the plan.
        plan_reflectance: Reflectance the refinement is planned for, ``[F, L]`` or ``[F]`` (default 0.9 grey: a
            bright case, so darker reflectances are at least as accurate).

    Shape:
        - reflectance: ``[B, F, L]`` (or ``[F, L]``; ``[B, M, ·]`` with ``per_material``; the model's input shape
          with ``reflectance_model``)
        - illuminant: spectrum ``[B, L]`` or ``[L]``; or ``E0 = [B, F, L]`` / ``[F, L]`` by keyword
        - output: camera RGB ``[B, F, 3]``; with a projection, ``(rgb, image [B, 3, H, W])``; with a view,
          ``(rgb [..., F, 3], image [..., 3, H, W])``

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.layers import Interreflection
        >>> wl = ti.spectral.wavelengths()
        >>> layer = Interreflection(ti.scenes.v_groove(45.0, divisions=2), wl)
        >>> r = torch.full((2, 8, 31), 0.5, requires_grad=True)
        >>> rgb = layer(r, ti.spectral.illuminant("D65", wl).expand(2, -1))
        >>> rgb.shape
        torch.Size([2, 8, 3])
        >>> rgb.sum().backward(); r.grad.shape
        torch.Size([2, 8, 31])
    """

    matrix: Tensor
    areas: Tensor
    light_factor: Tensor
    material: Tensor

    def __init__(
        self,
        scene_or_form_factors: Scene | FormFactors | tuple[Scene, FormFactors],
        wavelengths: Tensor | Sequence[float] | np.ndarray,
        camera: Camera | str = "Nikon 5100 (NPL)",
        *,
        bounces: int | None = None,
        light: str | Tensor | Sequence[float] = "uniform",
        projection: nn.Module | None = None,
        view: View | None = None,
        shading: str = "gather",
        reflectance_model: nn.Module | None = None,
        per_material: bool = False,
        tol: float = 1e-6,
        method: str = "auto",
        shadows: str | bool = "auto",
        accuracy: float | None = None,
        plan_reflectance: Tensor | None = None,
    ) -> None:
        super().__init__()
        scene, ff = _scene_and_form_factors(scene_or_form_factors, accuracy is not None)
        wl = spectral.check_wavelengths(wavelengths, min_samples=2)
        camera = _camera(camera, wl)
        self.accuracy_report = None
        refined = None
        if accuracy is not None:
            refined = _refined(scene, ff, light, camera, accuracy, plan_reflectance)
            ff, bounces, self.accuracy_report = refined.form_factors, refined.bounces, refined.report
            tol = refined.solver_tol if refined.method != "series" else tol
            method = refined.method if refined.method != "series" else method
        n_facets = _check_parts(scene, ff, refined is not None, bounces, camera, wl, projection, per_material)
        self.bounces = bounces
        self.tol = float(tol)
        self.method = method
        self.per_material = bool(per_material)
        self.material_names = list(scene.material_names) if scene is not None and scene.material_names else None
        self.camera = camera
        self.projection = projection
        self.reflectance_model = reflectance_model
        self.light = light if isinstance(light, str) else "custom"
        self._register(ff, scene, n_facets, refined, light, shadows)
        self.shading = shading
        self.gather_view: Gather | None = None
        self.image_gradient: ImageGradient | None = None
        if view is not None:
            if scene is None or projection is not None or accuracy is not None:
                raise ValueError("view= needs a Scene and goes without projection= and accuracy= (for a refined "
                                 "scene's image use torch_interreflect.render(..., view=...))")
            if shading not in ("gather", "flat"):
                raise ValueError(f"shading must be 'gather' or 'flat'; got {shading!r}")
            self.gather_view = gather_operator(scene, view, light, shading=shading).to(ff.device)
            light_grad = isinstance(light, Tensor) and light.requires_grad
            if torch.is_grad_enabled() and (scene.corners.requires_grad or light_grad):
                # the image's own gradient to the geometry (and a sun direction): kept, like the matrix's graph
                self.image_gradient = image_gradient(self.gather_view, scene, light, shading=shading)

    def _register(
        self, ff: FormFactors, scene: Scene | None, n_facets: int, refined: Any, light: Any, shadows: str | bool
    ) -> None:
        """The buffers: matrix, areas, light factor, leaf → facet map (when refined), material index."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # sparse CSR beta warning
            # form factors of a scene whose corners require grad keep their graph (gradients to the geometry)
            self.register_buffer("matrix", ff.matrix if ff.matrix.requires_grad else ff.matrix.detach())
        self.register_buffer("areas", ff.areas.detach().clone())  # its own: load_state_dict writes it in place
        if refined is not None:
            self.register_buffer("light_factor", refined.light_factor.detach())
            self.register_buffer("leaf_user", refined.leaf_user.detach().to(ff.device))
        else:
            self.register_buffer("light_factor", light_geometry(scene, ff, light, shadows=shadows))
            self.leaf_user = None
        self._num_user = n_facets
        mat = scene.material if scene is not None and scene.material is not None else torch.zeros(n_facets)
        self.register_buffer("material", mat.detach().long().to(ff.device))

    # ------------------------------------------------------------------ properties
    @property
    def num_facets(self) -> int:
        """Facets of the scene (inputs and outputs); with ``accuracy`` the solve runs on more (the leaves)."""
        return int(self._num_user)

    @property
    def wavelengths(self) -> Tensor:
        return self.camera.wavelengths

    @property
    def num_wavelengths(self) -> int:
        return self.camera.num_wavelengths

    @property
    def form_factors(self) -> FormFactors:
        """The stored form factors (sharing the buffers)."""
        ff = getattr(self, "_ff_cache", None)
        if ff is None or ff.matrix is not self.matrix or ff.areas is not self.areas:
            ff = FormFactors(self.matrix, self.areas)
            self._ff_cache = ff  # keeps the solver's cached plan between calls
        return ff

    def facets_of(self, select: str | Sequence[str] | Tensor) -> Tensor:
        """Boolean mask ``[F]`` of a material name (or names), a mask, or facet indices."""
        if isinstance(select, str):
            select = [select]
        if isinstance(select, (list, tuple)) and all(isinstance(s, str) for s in select):
            names = self.material_names or []
            bad = [s for s in select if s not in names]
            if bad:
                raise ValueError(f"unknown material(s) {bad}; the scene has {names}")
            ids = torch.tensor([names.index(s) for s in select], device=self.material.device)
            return torch.isin(self.material, ids)
        t = torch.as_tensor(select, device=self.material.device)
        if t.dtype == torch.bool:
            if t.shape != (self.num_facets,):
                raise ShapeError(f"a facet mask must have shape [{self.num_facets}]; got {list(t.shape)}")
            return t
        if t.dtype.is_floating_point or t.ndim != 1:
            raise TypeError("select must be material name(s), a boolean mask [F] or integer facet indices [K]")
        if t.numel() and (int(t.min()) < -self.num_facets or int(t.max()) >= self.num_facets):
            raise ShapeError(f"facet indices must lie in [0, {self.num_facets}); got {t.tolist()}")
        mask = torch.zeros(self.num_facets, dtype=torch.bool, device=t.device)
        mask[t] = True
        return mask

    # ------------------------------------------------------------------ computation
    def reflectance(self, x: Tensor) -> Tensor:
        """Per-facet reflectance ``[..., F, L]`` of the first input of :meth:`forward`."""
        r = self.reflectance_model(x) if self.reflectance_model is not None else x
        if not isinstance(r, Tensor):
            raise TypeError(f"reflectance must be a tensor; got {type(r).__name__}")
        if self.per_material:
            m = len(self.material_names or [])
            if r.ndim < 2 or r.shape[-2] != m:
                raise ShapeError(f"per-material reflectance must be [..., M = {m}, L]; got {list(r.shape)}")
            r = r.index_select(-2, self.material)
        if r.ndim < 2 or r.shape[-2:] != (self.num_facets, self.num_wavelengths):
            raise ShapeError(
                f"reflectance must have shape [..., F, L] = [..., {self.num_facets}, {self.num_wavelengths}]; got "
                f"{list(r.shape)}"
            )
        return r

    def direct(self, illuminant: Tensor) -> Tensor:
        """``E0 = g ⊗ spectrum``: ``[..., F, L]`` from a spectrum ``[..., L]`` (module docstring)."""
        if not isinstance(illuminant, Tensor) or illuminant.ndim < 1 or illuminant.shape[-1] != self.num_wavelengths:
            got = list(illuminant.shape) if isinstance(illuminant, Tensor) else type(illuminant).__name__
            raise ShapeError(f"illuminant must be a spectrum [..., L] with L = {self.num_wavelengths}; got {got}")
        g = self.light_factor.to(device=illuminant.device)
        return g[:, None] * illuminant[..., None, :]  # on the leaves when refined

    def forward(
        self, reflectance: Tensor, illuminant: Tensor | None = None, *, E0: Tensor | None = None
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Camera RGB ``[..., F, 3]`` (and images ``[B, 3, H, W]`` when a projection is set).

        Args:
            reflectance: Reflectance ``[..., F, L]``, or the input of ``reflectance_model`` / per-material values.
            illuminant: Spectrum ``[..., L]`` (see ``light``). Exactly one of ``illuminant`` and ``E0``.
            E0: Direct irradiance ``[..., F, L]`` in W·m⁻²·nm⁻¹, used as is.
        """
        if (illuminant is None) == (E0 is None):
            raise ValueError("give exactly one of illuminant (a spectrum [..., L]) and E0 ([..., F, L])")
        r = self.reflectance(reflectance)
        e0 = self.direct(illuminant) if illuminant is not None else E0
        if self.leaf_user is not None:  # refined: reflectance (and a given E0) per leaf, RGB averaged back
            r = r.index_select(-2, self.leaf_user)
            if illuminant is None:
                e0 = e0.index_select(-2, self.leaf_user)  # type: ignore[union-attr]
        if self.gather_view is not None:
            return self._view_forward(r, e0, illuminant)
        rgb = facet_rgb(self.form_factors, r, e0, self.camera, bounces=self.bounces, tol=self.tol, method=self.method)
        if self.leaf_user is not None:
            rgb = area_average(rgb, self.leaf_user, self.areas, self.num_facets)
        if self.projection is None:
            return rgb
        flat = rgb.reshape(-1, *rgb.shape[-2:])
        return rgb, self.projection(flat)

    def _view_forward(self, r: Tensor, e0: Tensor, illuminant: Tensor | None) -> tuple[Tensor, Tensor]:
        """``(rgb [..., F, 3], image [..., 3, H, W])`` through the view's gather operator."""
        if illuminant is None:
            raise ValueError("a layer with a view needs illuminant= (the spectrum the per-pixel light is scaled by), "
                             "not E0=")
        E = solve(self.form_factors, r, e0, bounces=self.bounces, tol=self.tol, method=self.method)
        rgb = self.camera(radiance(E, r))
        if self.shading == "gather" and self.bounces is not None:  # the gather adds the last bounce
            E = source_irradiance(self.form_factors, r, e0, self.bounces, tol=self.tol, method=self.method)
        image = gathered_image(self.gather_view, r, E, illuminant, self.camera, shading=self.shading,
                               gradient=self.image_gradient)
        return rgb, image

    def extra_repr(self) -> str:
        layout = "sparse" if self.matrix.layout != torch.strided else "dense"
        refined = f", solved on {int(self.matrix.shape[0])} leaves" if self.leaf_user is not None else ""
        return (
            f"facets={self.num_facets}{refined} ({layout}), wavelengths={self.num_wavelengths}, "
            f"bounces={self.bounces}, "
            f"light={self.light!r}, per_material={self.per_material}"
        )

    def _apply(self, fn: Any, recurse: bool = True) -> Interreflection:  # drop the cached FormFactors view
        self._ff_cache = None
        g = self.image_gradient
        if g is not None:  # a plain attribute (it carries a graph): moved with the buffers, its graph kept
            self.image_gradient = dataclasses.replace(g, **{f.name: _moved(fn, getattr(g, f.name))
                                                          for f in dataclasses.fields(g)
                                                          if isinstance(getattr(g, f.name), Tensor)})
        return super()._apply(fn, recurse)


def _moved(fn: Any, t: Tensor) -> Tensor:
    """``fn`` (a module's ``.to`` / ``.double()`` ...) applied to a tensor; a sparse COO one is rebuilt from its moved
    indices and values (casting it whole breaks its backward)."""
    if t.layout == torch.sparse_coo:
        return torch.sparse_coo_tensor(fn(t.indices()), fn(t.values()), tuple(t.shape), is_coalesced=t.is_coalesced(),
                                       check_invariants=False)
    return fn(t)


# ---------------------------------------------------------------------------------------- construction steps
def _scene_and_form_factors(arg: Any, planned: bool) -> tuple[Scene | None, FormFactors | None]:
    """The scene (or ``None``) and form factors (``None`` when the planner computes them) of the first argument."""
    if isinstance(arg, Scene):
        return arg, None if planned else _compute_form_factors(arg)
    if isinstance(arg, FormFactors):
        return None, arg
    if isinstance(arg, tuple) and len(arg) == 2 and isinstance(arg[0], Scene) and isinstance(arg[1], FormFactors):
        return arg[0], arg[1]
    raise TypeError(
        f"scene_or_form_factors must be a Scene, a FormFactors or a (Scene, FormFactors) pair; got {type(arg).__name__}"
    )


def _camera(camera: Camera | str, wl: Tensor) -> Camera:
    """A :class:`Camera` from a camera or a sensitivity name."""
    if isinstance(camera, str):
        camera = Camera.from_colour(camera, wl)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera or a sensitivity name; got {type(camera).__name__}")
    return camera


@dataclass
class _Refined:
    """The planned refinement the layer solves on (from :func:`torch_interreflect.accuracy.plan`)."""

    form_factors: FormFactors
    light_factor: Tensor
    leaf_user: Tensor
    bounces: int | None
    method: str
    solver_tol: float
    report: Any


def _refined(
    scene: Scene | None,
    ff: FormFactors | None,
    light: Any,
    camera: Camera,
    accuracy: float,
    plan_reflectance: Tensor | None,
) -> _Refined:
    """Plan the refinement for ``accuracy`` (a bright grey reflectance by default, a D65 illuminant)."""
    if scene is None or ff is not None:
        raise ValueError("accuracy= needs the layer to be built from a Scene (it refines the scene itself)")
    n_user = scene.num_facets
    pr = plan_reflectance if plan_reflectance is not None else torch.full((n_user,), 0.9, dtype=scene.dtype)
    cam_plan = Camera(camera.sensitivities.to(scene.dtype), camera.wavelengths.to(scene.dtype))
    # the layer solves one level of the constant basis (its buffers are form factors; gradients reach the geometry)
    p = plan(scene, pr, light, "D65", cam_plan, accuracy=accuracy, extrapolate=False, basis="constant")
    ff = FormFactors(p.form_factors.matrix, p.form_factors.areas, dict(p.form_factors.info))
    return _Refined(ff, p.light_factor, p.leaf_user, p.bounces, p.method, p.solver_tol, p.report)


def _check_parts(
    scene: Scene | None,
    ff: FormFactors,
    refined: bool,
    bounces: int | None,
    camera: Camera,
    wl: Tensor,
    projection: nn.Module | None,
    per_material: bool,
) -> int:
    """Typed errors for parts that do not fit together; returns the number of facets of inputs and outputs."""
    if scene is not None and scene.num_facets != ff.num_facets and not refined:
        raise ShapeError(f"the scene has {scene.num_facets} facets but the form factors {ff.num_facets}")
    if bounces is not None and (isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 1):
        raise ValueError(f"bounces must be None (infinite) or an integer >= 1; got {bounces!r}")
    if camera.num_wavelengths != wl.shape[0]:
        raise ShapeError(f"the camera has {camera.num_wavelengths} wavelengths but the grid has {wl.shape[0]}")
    n_facets = scene.num_facets if refined and scene is not None else ff.num_facets
    if projection is not None and getattr(projection, "num_facets", n_facets) != n_facets:
        raise ShapeError(f"the projection has {projection.num_facets} facets but the scene {n_facets}")
    if per_material and (scene is None or scene.material is None):
        raise ValueError("per_material=True needs a scene with a material index")
    return n_facets
