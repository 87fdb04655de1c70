"""The interreflection layer: reflectance and illuminant in, camera RGB (and images) out.

:func:`render` is the functional form: ``E0 = geometry ⊗ spectrum`` (or a given ``E0``), ``E = solve(F, R, E0)``,
``L = R E / π``, ``rgb = camera(L)``. :class:`Interreflection` holds the form factors, the light's geometric
factor, the camera and optionally a projection and a reflectance parametrisation, all as buffers or submodules.

How an illuminant spectrum becomes ``E0`` (the ``light=`` argument): ``E0[..., i, λ] = g_i · S[..., λ]`` with a
geometric factor ``g [F]`` computed once at construction (DESIGN.md §3):

- ``"uniform"`` (default): ``g_i = 1``, the paper's homogeneous light; ``S`` is the irradiance every facet gets.
- a direction ``[3]`` (the direction the light travels): ``g_i = max(0, n_i·(−d)) · lit_i`` with cast shadows
  (:func:`torch_interreflect.lights.directional`); ``S`` is the irradiance on a plane facing the light.
- ``"sky"``: ``g_i = π (1 − Σ_j F_ij)`` (:func:`torch_interreflect.lights.sky`); ``S`` is the sky radiance.
- a material name (e.g. ``"light"`` of the Cornell box) or a boolean mask ``[F]``: an area light, the listed
  facets emit exitance ``M = π S`` (radiance ``S``) toward the others: ``g_i = π Σ_{j ∈ light} F_ij`` (the
  irradiance a diffuse emitter produces, by reciprocity). The emitters' own emission is not part of the rendered
  radiance ``R E / π`` (add it for display if wanted).
- a tensor ``[F]``: ``g`` itself.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from .. import lights, spectral
from ..camera import Camera
from ..errors import ShapeError, ValueRangeError
from ..formfactors import form_factors as _compute_form_factors
from ..kernel import FormFactors
from ..scene import Scene, area_average
from ..solve import radiance as _radiance
from ..solve import solve as _solve

__all__ = ["Interreflection", "light_geometry", "render"]


def light_geometry(
    light: str | Tensor | Sequence[float],
    form_factors: FormFactors,
    scene: Scene | None = None,
    *,
    shadows: str | bool = "auto",
) -> Tensor:
    """The geometric factor ``g [F]`` of a light: ``E0[..., i, :] = g_i · spectrum`` (see the module docstring).

    Args:
        light: ``"uniform"``, ``"sky"``, a direction ``[3]``, a material name, a boolean mask ``[F]`` (area light),
            or ``g`` itself as a floating tensor ``[F]``.
        form_factors: The scene's form factors (``"sky"`` and area lights use them).
        scene: The scene (directional lights and material names need it).
        shadows: Shadow handling of directional lights (see :func:`torch_interreflect.lights.lit_fraction`).

    Returns:
        ``g`` in the form factors' dtype and device. Shape ``[F]``.

    Raises:
        ValueError: an unknown light name, or a light that needs the scene when none is given.
        ShapeError: a tensor of the wrong size.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.layers import light_geometry
        >>> scene = ti.scenes.v_groove(90.0, divisions=1)
        >>> light_geometry([0.0, 0.0, -1.0], ti.form_factors(scene), scene).tolist()
        [1.0, 0.0]
    """
    n = form_factors.num_facets
    dtype, device = form_factors.dtype, form_factors.device
    if isinstance(light, str):
        if light == "uniform":
            return torch.ones(n, dtype=dtype, device=device)
        if light == "sky":
            return math.pi * (1.0 - form_factors.row_sums().detach()).clamp_min(0.0)
        if scene is None or scene.material_names is None or light not in scene.material_names:
            names = list(scene.material_names) if scene is not None and scene.material_names else []
            raise ValueError(
                f"light must be 'uniform', 'sky', a direction [3], a facet mask [F], a tensor [F] or a material name "
                f"of the scene {names}; got {light!r}"
            )
        mask = scene.material == scene.material_names.index(light)
        return light_geometry(mask.to(device), form_factors, scene)
    t = torch.as_tensor(light)
    if t.dtype == torch.bool:
        if t.shape != (n,):
            raise ShapeError(f"an area-light mask must have shape [{n}] (one flag per facet); got {list(t.shape)}")
        cols = t.to(device=device, dtype=dtype)[:, None]
        return math.pi * form_factors.matmul(cols).reshape(n).detach()
    if t.numel() == 3 and t.ndim == 1 and n != 3:
        if scene is None:
            raise ValueError("a directional light needs the scene (for normals and shadows); pass a Scene")
        e0 = lights.directional(scene, t.to(torch.float64), torch.ones(1, dtype=torch.float64), shadows=shadows)
        return e0[:, 0].to(device=device, dtype=dtype)
    if not t.is_floating_point() or t.shape != (n,):
        raise ShapeError(
            f"light as a tensor must be a direction [3] or a geometric factor / mask [F = {n}]; got "
            f"{list(t.shape)} ({t.dtype})"
        )
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueRangeError("a geometric light factor [F] must be finite and non-negative")
    return t.detach().to(device=device, dtype=dtype)


def render(
    form_factors: FormFactors,
    reflectance: Tensor,
    E0: Tensor,
    camera: Camera,
    *,
    bounces: int | None = None,
    tol: float = 1e-6,
    method: str = "auto",
) -> Tensor:
    """Camera RGB of a scene after ``bounces`` reflections: ``camera(R · solve(F, R, E0) / π)``.

    Differentiable in ``reflectance``, ``E0``, the form-factor values and the camera's sensitivities.

    Args:
        form_factors: The scene's form factors.
        reflectance: In [0, 1]. Shape ``[..., F, L]`` (or ``[..., F]`` grey).
        E0: Direct irradiance in W·m⁻²·nm⁻¹. Shape ``[..., F, L]`` broadcastable with the reflectance.
        camera: The camera (its grid must have ``L`` wavelengths).
        bounces: ``None`` (infinite) or ``n ≥ 1`` (see :func:`torch_interreflect.solve.solve`).
        tol: Solver tolerance.
        method: Solver method.

    Returns:
        Camera responses. Shape ``[..., F, C]``.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.layers import render
        >>> scene = ti.scenes.v_groove(60.0, divisions=2)
        >>> wl = ti.spectral.wavelengths()
        >>> rgb = render(ti.form_factors(scene), torch.full((8, 31), 0.5), torch.ones(8, 31),
        ...              ti.Camera.from_colour("Nikon 5100 (NPL)", wl))
        >>> rgb.shape
        torch.Size([8, 3])
    """
    E = _solve(form_factors, reflectance, E0, bounces=bounces, tol=tol, method=method)
    return camera(_radiance(E, reflectance))


class Interreflection(nn.Module):
    """A differentiable spectral interreflection renderer: reflectance + illuminant → camera RGB (→ images).

    The form-factor matrix (dense or sparse CSR) and areas, the light's geometric factor ``g [F]``, the material
    index and (through submodules) the camera sensitivities, a :class:`~torch_interreflect.imaging.Projection` and
    a reflectance parametrisation are buffers, so ``.to(device, dtype)`` moves everything. Gradients reach the
    reflectance (or its parameters), the illuminant spectrum or ``E0``, and the camera sensitivities, by the
    adjoint of :func:`~torch_interreflect.solve.solve`.

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
            :func:`~torch_interreflect.imaging.project`); when set, ``forward`` also returns images.
        reflectance_model: Optional module mapping the first input (e.g. basis coefficients ``[..., K]`` or RGB
            ``[..., 3]``) to reflectance ``[..., L]`` (:class:`ReflectanceBasis`, :class:`RGBToSpectrum`, ...).
        per_material: The reflectance input is per material ``[..., M, ·]`` and is expanded to facets with the
            scene's material index.
        tol: Solver tolerance. method: Solver method (see :func:`~torch_interreflect.solve.solve`).
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
        - output: camera RGB ``[B, F, 3]``; with a projection, ``(rgb, image [B, 3, H, W])``

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
        reflectance_model: nn.Module | None = None,
        per_material: bool = False,
        tol: float = 1e-6,
        method: str = "auto",
        shadows: str | bool = "auto",
        accuracy: float | None = None,
        plan_reflectance: Tensor | None = None,
    ) -> None:
        super().__init__()
        scene: Scene | None
        if isinstance(scene_or_form_factors, Scene) and accuracy is not None:
            scene, ff = scene_or_form_factors, None
        elif isinstance(scene_or_form_factors, Scene):
            scene, ff = scene_or_form_factors, _compute_form_factors(scene_or_form_factors)
        elif isinstance(scene_or_form_factors, FormFactors):
            scene, ff = None, scene_or_form_factors
        elif (
            isinstance(scene_or_form_factors, tuple)
            and len(scene_or_form_factors) == 2
            and isinstance(scene_or_form_factors[0], Scene)
            and isinstance(scene_or_form_factors[1], FormFactors)
        ):
            scene, ff = scene_or_form_factors
        else:
            raise TypeError(
                "scene_or_form_factors must be a Scene, a FormFactors or a (Scene, FormFactors) pair; got "
                f"{type(scene_or_form_factors).__name__}"
            )
        wl = spectral.check_wavelengths(wavelengths, min_samples=2)
        if isinstance(camera, str):
            camera = Camera.from_colour(camera, wl)
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a Camera or a sensitivity name; got {type(camera).__name__}")
        self.accuracy_report = None
        leaf_user = None
        if accuracy is not None:
            if scene is None or ff is not None:
                raise ValueError("accuracy= needs the layer to be built from a Scene (it refines the scene itself)")
            from ..accuracy import plan as _plan

            n_user = scene.num_facets
            pr = plan_reflectance if plan_reflectance is not None else torch.full((n_user,), 0.9, dtype=scene.dtype)
            cam_plan = Camera(camera.sensitivities.to(scene.dtype), camera.wavelengths.to(scene.dtype))
            p = _plan(scene, pr, light, "D65", cam_plan, accuracy=accuracy)
            p_full = p.form_factors
            ff = FormFactors(p_full.matrix, p_full.areas, dict(p_full.info))
            leaf_user, leaf_light = p.leaves, p.light_factor
            bounces = p.bounces
            tol = p.solver_tol if p.method != "series" else tol
            method = p.method if p.method != "series" else method
            self.accuracy_report = p.report
        if ff is None:  # pragma: no cover - every branch above sets it
            raise RuntimeError("no form factors")
        if scene is not None and scene.num_facets != ff.num_facets and leaf_user is None:
            raise ShapeError(f"the scene has {scene.num_facets} facets but the form factors {ff.num_facets}")
        if bounces is not None and (isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 1):
            raise ValueError(f"bounces must be None (infinite) or an integer >= 1; got {bounces!r}")
        if camera.num_wavelengths != wl.shape[0]:
            raise ShapeError(
                f"the camera has {camera.num_wavelengths} wavelengths but the grid has {wl.shape[0]}"
            )
        n_facets = scene.num_facets if leaf_user is not None and scene is not None else ff.num_facets
        if projection is not None and getattr(projection, "num_facets", n_facets) != n_facets:
            raise ShapeError(f"the projection has {projection.num_facets} facets but the scene {n_facets}")
        if per_material and (scene is None or scene.material is None):
            raise ValueError("per_material=True needs a scene with a material index")

        self.bounces = bounces
        self.tol = float(tol)
        self.method = method
        self.per_material = bool(per_material)
        self.material_names = list(scene.material_names) if scene is not None and scene.material_names else None
        self.camera = camera
        self.projection = projection
        self.reflectance_model = reflectance_model
        self.light = light if isinstance(light, str) else "custom"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # sparse CSR beta warning
            self.register_buffer("matrix", ff.matrix.detach())
        self.register_buffer("areas", ff.areas.detach())
        if leaf_user is not None:
            self.register_buffer("light_factor", leaf_light.detach())
            self.register_buffer("leaf_user", p.leaf_user.detach().to(ff.device))
        else:
            self.register_buffer("light_factor", light_geometry(light, ff, scene, shadows=shadows))
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
        rgb = render(self.form_factors, r, e0, self.camera, bounces=self.bounces, tol=self.tol, method=self.method)
        if self.leaf_user is not None:
            rgb = area_average(rgb, self.leaf_user, self.areas, self.num_facets)
        if self.projection is None:
            return rgb
        flat = rgb.reshape(-1, *rgb.shape[-2:])
        return rgb, self.projection(flat)

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
        return super()._apply(fn, recurse)
