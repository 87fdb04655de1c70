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
- **Form factors**: the per-entry quadrature tolerance (the Gauss order of every pair follows from it and the
  pair's distance/size ratio).
- **Sparsification**: entries are dropped (in reciprocal pairs, so conjugate gradients still apply) while the
  dropped mass per row stays under a bound whose effect on the solution, ``≤ m r_max ‖E‖∞ / (1 − r_max ρ)``, is
  within its share. It is used only where it makes the matrix sparse enough to pay.
- **Bounces**: the n-bounce series stops when its tail bound ``(r_max ρ)^n / (1 − r_max ρ) · ‖E0‖∞`` is within its
  share; conjugate gradients are used instead when they need fewer products (bright scenes).
- **Wavelengths** (camera RGB only): the interreflection gain ``h = E / S`` (``S`` the illuminant) is solved on a
  nested subset of the grid and interpolated linearly in between; the coarsest subset whose RGB error, measured
  on the user's facets against the full grid, is within its share is used for all the work.

Everything chosen and the estimated error come back in :class:`AccuracyReport`.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .. import lights, spectral
from ..camera.sensor import Camera
from ..errors import AccuracyWarning, ShapeError, ValueRangeError
from ..formfactors.operator import FormFactors
from ..formfactors.quadrature import form_factors as _form_factors
from ..geometry.scene import Scene, area_average
from ..lights import light_geometry
from ..solver.api import solve as _solve
from ..solver.method import estimate_cg_iterations

__all__ = ["BUDGET", "AccuracyReport", "AccuracyWarning", "Plan", "RenderResult", "plan", "render"]

#: Share of the requested error given to each source (they add up to 1; without a camera the wavelength share
#: goes to the discretisation).
BUDGET: dict[str, float] = {
    "discretisation": 0.6,
    "form_factors": 0.05,
    "sparsification": 0.1,
    "solver": 0.05,
    "wavelengths": 0.2,
}


#: Range of the convergence ratio ``q`` (successive changes of a facet's value when its level doubles) used in the
#: estimate ``change · q / (1 − q)``: first order gives 0.5, second order 0.25; slower convergence up to 0.8 is
#: believed, faster than 1/3 is not.
Q_MIN, Q_MAX = 1 / 3, 0.8


#: Refinement stops (and warns) when two refinements lowered the estimated discretisation error by less than
#: this factor: the error is then not falling with the facet size (the Cornell box's visibility), and going on
#: would spend minutes without reaching the target.
STALL = 0.8


@dataclass
class AccuracyReport:
    """What :func:`render` chose and the error it estimates it left.

    Attributes:
        requested: The requested relative RMS error.
        estimated: Estimated relative RMS error over the user's facets (and columns) of the returned output: the
            discretisation estimate plus the bounds of the other sources.
        estimated_max: The largest per-facet estimate.
        per_facet: Estimated relative error per user facet. Shape ``[F]``.
        parts: Estimated (discretisation) or bounded (the rest) relative RMS error per source.
        reached: Whether ``estimated <= requested``.
        leaves: Facets actually solved (after refinement).
        leaves_per_facet: Leaves per user facet. Shape ``[F]``.
        iterations: Refinement steps (solves of a refined mesh).
        form_factor_tol: Per-entry quadrature tolerance used.
        sparsified: Whether the matrix was sparsified; ``dropped`` the fraction of entries dropped and
            ``dropped_row_mass`` the largest dropped row sum.
        method: ``"series"`` (the n-bounce model with ``bounces``) or the iterative method used (``"cg"``...).
        bounces: Terms of the series (``None`` for an iterative solve), ``solver_tol`` its tolerance.
        wavelengths: The wavelengths solved (a subset of the grid when the output is camera RGB). Shape ``[L']``.
        wavelength_error: RGB error of the subset against the full grid, measured on the user's facets.
        seconds: Wall time per stage.
        history: Per refinement step: leaves, estimated discretisation error, seconds.
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
    form_factor_tol: float
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

    def __str__(self) -> str:
        solver = f"{self.bounces} bounces" if self.method == "series" else f"{self.method} (tol {self.solver_tol:.1g})"
        return (
            f"accuracy {self.requested:.3g} requested, {self.estimated:.3g} estimated "
            f"({'reached' if self.reached else 'NOT reached'}); {self.leaves} facets solved "
            f"({self.iterations} refinements), form-factor tol {self.form_factor_tol:.1g}, {solver}, "
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
    """

    irradiance: Tensor
    radiance: Tensor
    rgb: Tensor | None
    report: AccuracyReport


# ------------------------------------------------------------------------------------------------ leaves
@dataclass
class _Leaves:
    scene: Scene
    user: Tensor  # [n] user facet of each leaf


def _subset(scene: Scene, idx: Tensor) -> Scene:
    mat = scene.material[idx] if scene.material is not None else None
    return Scene._from_parts(scene.corners[idx], scene.is_triangle[idx], mat, scene.material_names)


def _split(leaves: _Leaves, sel: Tensor) -> _Leaves:
    """Split the selected leaves in four (kept leaves first, then the children)."""
    idx_keep = torch.nonzero(~sel).reshape(-1)
    idx_sel = torch.nonzero(sel).reshape(-1)
    fine, par = _subset(leaves.scene, idx_sel).subdivide(2)
    sc = leaves.scene
    mat = None
    if sc.material is not None:
        mat = torch.cat([sc.material[idx_keep], fine.material])
    scene = Scene._from_parts(
        torch.cat([sc.corners[idx_keep], fine.corners]),
        torch.cat([sc.is_triangle[idx_keep], fine.is_triangle]),
        mat,
        sc.material_names,
    )
    return _Leaves(scene, leaves.user[torch.cat([idx_keep, idx_sel[par]])])


def _to_user(values: Tensor, leaves: _Leaves, num_user: int) -> Tensor:
    """Area-weighted average of leaf values ``[..., n, C]`` onto the user facets ``[..., F, C]``."""
    return area_average(values, leaves.user, leaves.scene.areas, num_user)


def _rel(a: Tensor, b: Tensor) -> Tensor:
    """Per-facet relative difference ``[F]``: largest over the columns of ``|a − b| / |b|`` (facets on dim −2)."""
    d = (a - b).abs()
    scale = b.abs()
    floor = 1e-12 * scale.amax(dim=-2, keepdim=True).clamp_min(1e-300)
    r = d / torch.maximum(scale, floor)
    r = r.movedim(-2, 0).reshape(r.shape[-2], -1)
    return r.amax(dim=1) if r.shape[1] else r.new_zeros(r.shape[0])


def _rms(x: Tensor) -> float:
    return float(x.square().mean().sqrt()) if x.numel() else 0.0


# ------------------------------------------------------------------------------------------- the light
def _light_factor(light: Any, scene: Scene, K: FormFactors, user: Tensor, num_user: int) -> Tensor:
    """Geometric factor ``g [n]`` of the light on the leaves: ``E0 = g ⊗ spectrum``."""
    if isinstance(light, str) and light == "sky":
        return lights.sky(scene, K, torch.ones(1, dtype=scene.dtype, device=scene.device))[:, 0]
    if isinstance(light, Tensor) and light.ndim == 1 and light.shape[0] == num_user and num_user != 3:
        if light.dtype == torch.bool:
            return light_geometry(scene, K, light.to(scene.device)[user])
        return light.to(device=scene.device, dtype=scene.dtype)[user]  # a factor per user facet: per leaf
    return light_geometry(scene, K, light)


# -------------------------------------------------------------------------------------------- spectra
def _interp_matrix(nodes: Tensor, grid: Tensor) -> Tensor:
    """Linear interpolation from ``nodes`` (a subset of ``grid``) to ``grid`` as a matrix ``[L', L]``."""
    i = torch.searchsorted(nodes, grid, right=True).clamp(1, nodes.numel() - 1)
    a, b = nodes[i - 1], nodes[i]
    t = ((grid - a) / (b - a)).clamp(0, 1)
    m = grid.new_zeros(nodes.numel(), grid.numel())
    cols = torch.arange(grid.numel(), device=grid.device)
    m[i - 1, cols] += 1 - t
    m[i, cols] += t
    return m


def _nested_subsets(n: int) -> list[Tensor]:
    """Index subsets of a grid of ``n`` samples, coarsest first: every ``2^j``-th sample plus the last."""
    out = []
    step = 1
    while step < n:
        step *= 2
    while step >= 1:
        idx = torch.unique(torch.cat([torch.arange(0, n, step), torch.tensor([n - 1])]))
        if idx.numel() >= 2 and (not out or idx.numel() > out[-1].numel()):
            out.append(idx)
        step //= 2
    return out


# --------------------------------------------------------------------------------------------- public
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

    def apply(
        self, reflectance: Tensor, illuminant: Tensor | str | float = "D65", camera: Camera | None = None
    ) -> RenderResult:
        """Render with the planned refinement and settings: differentiable in reflectance and illuminant.

        Args:
            reflectance: Per user facet, in [0, 1]. Shape ``[..., F, L]`` or ``[..., F]``.
            illuminant: Spectrum ``[..., L]`` on the grid, or a name / CCT.
            camera: Camera for ``rgb`` (its grid must be the plan's).

        Returns:
            A :class:`RenderResult` on the user's facets; its report is the plan's.

        Shape:
            - reflectance: ``[..., F, L]`` or ``[..., F]``; illuminant: ``[..., L]``
            - output irradiance, radiance: ``[..., F, L]``; rgb: ``[..., F, C]``
        """
        F, L = self.scene.num_facets, self.grid.numel()
        S, r = _spectra(self.grid, illuminant, reflectance, F)
        nodes, user = self.nodes, self.leaf_user
        refl_leaf = r[..., user, :][..., nodes]
        g = self.light_factor
        e0 = g.to(refl_leaf.dtype)[:, None].expand(-1, refl_leaf.shape[-1])
        if self.method == "series":
            h = _solve(self.form_factors, refl_leaf, e0, bounces=self.bounces)
        else:
            h = _solve(self.form_factors, refl_leaf, e0, tol=self.solver_tol, method=self.method)
        h_full = h @ _interp_matrix(self.grid[nodes], self.grid).to(h.dtype) if nodes.numel() < L else h
        E_leaf = S[..., None, :] * h_full
        E = area_average(E_leaf, user, self.leaves.areas, F)
        rgb = None
        if camera is not None:
            if camera.num_wavelengths != L:
                raise ShapeError(f"the camera has {camera.num_wavelengths} wavelengths but the plan's grid {L}")
            rgb = area_average(camera(r[..., user, :] * E_leaf / math.pi), user, self.leaves.areas, F)
        return RenderResult(E, r * E / math.pi, rgb, self.report)


def _spectra(grid: Tensor, illuminant: Any, reflectance: Any, F: int) -> tuple[Tensor, Tensor]:
    """Illuminant ``[..., L]`` and reflectance ``[..., F, L]`` on ``grid``, validated."""
    dtype, dev, L = grid.dtype, grid.device, grid.numel()
    if isinstance(illuminant, (str, int, float)) and not isinstance(illuminant, bool):
        S = spectral.illuminant(illuminant, grid).to(dtype=dtype, device=dev)
    else:
        S = torch.as_tensor(illuminant).to(device=dev)
        S = S.to(torch.promote_types(S.dtype, dtype)) if S.is_floating_point() else S.to(dtype)
    if S.ndim == 0 or S.shape[-1] != L:
        raise ShapeError(f"illuminant must be [..., L] with L = {L} (the grid); got {list(S.shape)}")
    r = torch.as_tensor(reflectance, device=dev)
    r = r.to(torch.promote_types(r.dtype, dtype)) if r.is_floating_point() else r.to(dtype)
    if r.ndim >= 2 and r.shape[-2] == F and r.shape[-1] == L:
        pass
    elif r.ndim >= 1 and r.shape[-1] == F:
        r = r[..., None].expand(*r.shape, L)
    else:
        raise ShapeError(f"reflectance must be [..., F, L] or [..., F] with F = {F}, L = {L}; got {list(r.shape)}")
    if r.numel() and (bool((r.detach() < 0).any()) or bool((r.detach() > 1).any())):
        raise ValueRangeError(f"reflectance must lie in [0, 1]; got [{float(r.min()):.3g}, {float(r.max()):.3g}]")
    torch.broadcast_shapes(r.shape[:-2], S.shape[:-1])  # raises on batch shapes that do not broadcast
    return S, r


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
    progress: bool | None = None,
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
        progress: Show a progress bar (default: when the work is large).

    Returns:
        A :class:`RenderResult`: ``irradiance``, ``radiance``, ``rgb`` and the :class:`AccuracyReport`.

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
        >>> out = ti.render(scene, torch.full((32,), 0.8, dtype=torch.float64), light="uniform", accuracy=1e-2)
        >>> out.irradiance.shape, out.report.estimated <= 1e-2, out.report.leaves > 32
        (torch.Size([32, 31]), True, True)
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
        progress=progress,
    )
    return p.apply(reflectance, illuminant, camera)


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
    progress: bool | None = None,
) -> Plan:
    """Choose the refinement and settings that reach ``accuracy`` for this reflectance and light.

    Same arguments as :func:`render` (which is ``plan(...).apply(...)``). Nothing here is differentiated.

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
    if not isinstance(scene, Scene):
        raise TypeError(f"plan expects a Scene; got {type(scene).__name__}")
    if isinstance(accuracy, bool) or not isinstance(accuracy, (int, float)) or not math.isfinite(accuracy):
        raise ValueRangeError(f"accuracy must be a finite number in (0, 0.5]; got {accuracy!r}")
    if not (0 < accuracy <= 0.5):
        raise ValueRangeError(f"accuracy must lie in (0, 0.5] (a relative error); got {accuracy}")
    dtype, dev = scene.dtype, scene.device
    floor = 1e3 * torch.finfo(dtype).eps
    if accuracy < floor:
        raise ValueRangeError(
            f"accuracy {accuracy:.3g} is below what {dtype} can resolve in this model (about {floor:.1g}: "
            "quadrature, solver and averaging each lose a few digits); use a float64 scene or ask for less"
        )
    if not isinstance(max_facets, int) or max_facets < scene.num_facets:
        raise ValueError(f"max_facets must be an integer >= the scene's {scene.num_facets} facets; got {max_facets!r}")
    F = scene.num_facets

    # ------------------------------------------------------------------ spectra and shapes
    if camera is not None:
        grid = camera.wavelengths.to(dtype=dtype, device=dev)
    elif wavelengths is not None:
        grid = spectral.check_wavelengths(wavelengths).to(dtype=dtype, device=dev)
    else:
        grid = spectral.wavelengths(dtype=dtype, device=dev)
    L = grid.numel()
    S, r = _spectra(grid, illuminant, reflectance, F)
    S, r = S.detach(), r.detach()
    r_max = float(r.detach().max()) if r.numel() else 0.0

    budget = dict(BUDGET)
    if camera is None:
        budget["discretisation"] += budget.pop("wavelengths")
    ff_tol = min(1e-3, max(1e-7, budget["form_factors"] * accuracy))
    show = progress if progress is not None else F >= 2000 or accuracy < 3e-3
    seconds = {"form_factors": 0.0, "light": 0.0, "solve": 0.0}

    def rgb_of(h_nodes: Tensor, nodes: Tensor, refl: Tensor) -> Tensor:
        """Camera RGB ``[..., n, C]`` from the gain ``h`` on ``nodes`` (``E = S · interp(h)``)."""
        h = h_nodes @ _interp_matrix(grid[nodes], grid) if nodes.numel() < L else h_nodes
        E = S[..., None, :] * h
        return camera(refl * E / math.pi)  # type: ignore[misc]

    def solve_gain(K: FormFactors, refl: Tensor, g: Tensor, tol: float, **kw: Any) -> tuple[Tensor, Any]:
        t = time.perf_counter()
        h, info = _solve(K, refl, g[:, None].expand(-1, refl.shape[-1]), tol=tol, return_info=True, **kw)
        seconds["solve"] += time.perf_counter() - t
        return h, info

    # ------------------------------------------------------------------ refinement loop
    leaves = _Leaves(scene, torch.arange(F, device=dev))
    nodes = torch.arange(L, device=dev)
    wl_error = 0.0
    plan_tol = max(1e-10, 1e-3 * accuracy)
    prev_user: Tensor | None = None
    prev_delta = torch.full((F,), math.nan, dtype=torch.float64)
    est = torch.full((F,), math.inf, dtype=torch.float64)
    history: list[dict[str, float]] = []
    bar = tqdm(total=max_iterations + 1, desc="render", unit="step", leave=False, disable=None if show else True)
    touched = torch.zeros(F, dtype=torch.bool)
    sampled = torch.zeros(F, dtype=torch.bool)
    it = 0
    reason = ""
    while True:
        t = time.perf_counter()
        K = _form_factors(leaves.scene, quadrature_tol=ff_tol, progress=False)
        occ = K.info.get("occluded_facets")
        if occ is not None and bool(occ.any()):  # user facets whose rows rest on ray-cast visibility
            sampled[leaves.user.cpu()[occ.cpu()]] = True
        seconds["form_factors"] += time.perf_counter() - t
        t = time.perf_counter()
        g = _light_factor(light, leaves.scene, K, leaves.user, F)
        seconds["light"] += time.perf_counter() - t
        refl_leaf = r.detach()[..., leaves.user, :]
        with torch.no_grad():
            if it == 0 and camera is not None:
                h_full, _ = solve_gain(K, refl_leaf, g, plan_tol)
                rgb_full = rgb_of(h_full, nodes, refl_leaf)
                for sub in _nested_subsets(L):
                    err = _rms(_rel(rgb_of(h_full[..., sub.to(dev)], sub.to(dev), refl_leaf), rgb_full))
                    if err <= budget["wavelengths"] * accuracy or sub.numel() == L:
                        nodes, wl_error = sub.to(dev), err
                        break
                h = h_full[..., nodes]  # the full-grid solve already holds the subset
            else:
                h, _ = solve_gain(K, refl_leaf[..., nodes], g, plan_tol)
            vals = rgb_of(h, nodes, refl_leaf) if camera is not None else h * S[..., None, nodes]
            user_vals = _to_user(vals, leaves, F)
        if prev_user is not None:
            delta = _rel(prev_user, user_vals).to(torch.float64).cpu()
            q = (delta / prev_delta).nan_to_num(0.5).clamp(Q_MIN, Q_MAX)
            q = torch.where(sampled, torch.full_like(q, Q_MAX), q)  # sampled visibility converges slowly
            factor = q / (1 - q)
            est = torch.where(touched, delta * factor, torch.maximum(est, delta))
            prev_delta = torch.where(touched, delta, prev_delta)
        disc = _rms(est)
        history.append({"leaves": leaves.scene.num_facets, "estimate": disc, "seconds": time.perf_counter() - t_start})
        bar.set_postfix(facets=leaves.scene.num_facets, estimate=f"{disc:.2g}")
        bar.update(1)
        if disc <= budget["discretisation"] * accuracy:
            break
        if it >= max_iterations:
            reason = f"max_iterations={max_iterations}"
            break
        if len(history) >= 3 and disc > STALL * history[-3]["estimate"]:
            reason = (
                f"a stalled estimate ({history[-3]['estimate']:.3g} -> {disc:.3g} over the last two refinements; "
                "the scene converges too slowly under refinement for this target)"
            )
            break
        sel = _select(leaves, est, budget["discretisation"] * accuracy, max_facets)
        if sel is None:
            reason = f"max_facets={max_facets}"
            break
        touched = torch.zeros(F, dtype=torch.bool)
        touched[leaves.user[sel].cpu()] = True
        prev_user = user_vals
        leaves = _split(leaves, sel)
        it += 1
    bar.close()

    # ------------------------------------------------------------------ final settings
    t = time.perf_counter()
    # spread: RMS over user facets of max|h| / |h_i| (turns max-norm bounds into per-facet relative ones)
    user_h = _to_user(h.detach(), leaves, F).abs()
    ratio = user_h.amax(dim=-2, keepdim=True) / user_h.clamp_min(1e-300)
    spread = max(1.0, _rms(ratio.movedim(-2, 0).reshape(F, -1).amax(1))) if F else 1.0
    rho = r_max * float(K.row_sums().max()) if K.num_facets else 0.0
    K_final, dropped, dropped_mass, sparse_bound = K, 0.0, 0.0, 0.0
    if rho < 1 and K.is_sparse:  # a dense-stored kernel is too dense for dropping entries to pay
        mass = budget["sparsification"] * accuracy * (1 - rho) / max(r_max * spread, 1e-300)
        Ks = K.sparsify(mass)
        if Ks.info["density"] <= 0.1:
            K_final, dropped, dropped_mass = Ks, Ks.info["dropped"], Ks.info["dropped_row_mass"]
            sparse_bound = dropped_mass * r_max * spread / (1 - rho)
    seconds["sparsify"] = time.perf_counter() - t
    share = budget["solver"] * accuracy
    bounces: int | None = None
    if rho < 1:
        target = share * (1 - rho) / spread
        n_series = 1 if rho == 0 else max(1, math.ceil(math.log(target) / math.log(rho)))
        cg_iters = estimate_cg_iterations(rho, target, leaves.scene.num_facets)
        if n_series - 1 <= cg_iters:
            method, bounces, solver_tol = "series", n_series, 0.0
            solver_bound = rho**n_series / (1 - rho) * spread
        else:
            method, solver_tol = "cg", target
            solver_bound = share
    else:  # no a-priori bound: iterate to a tight tolerance
        method, solver_tol, solver_bound = "auto", 1e-3 * share, math.nan

    # ------------------------------------------------------------------ the report
    parts = {
        "discretisation": _rms(est),
        "form_factors": ff_tol,
        "sparsification": sparse_bound,
        "solver": solver_bound,
        "wavelengths": wl_error,
    }
    total = sum(v for v in parts.values() if math.isfinite(v))
    per_facet = est + (total - parts["discretisation"])
    seconds["total"] = time.perf_counter() - t_start
    counts = torch.bincount(leaves.user.cpu(), minlength=F)
    report = AccuracyReport(
        requested=float(accuracy),
        estimated=total,
        estimated_max=float(per_facet.max()) if F else 0.0,
        per_facet=per_facet,
        parts=parts,
        reached=total <= accuracy,
        leaves=leaves.scene.num_facets,
        leaves_per_facet=counts,
        iterations=it,
        form_factor_tol=ff_tol,
        sparsified=K_final is not K,
        dropped=dropped,
        dropped_row_mass=dropped_mass,
        method=method,
        bounces=bounces,
        solver_tol=solver_tol,
        wavelengths=grid[nodes],
        wavelength_error=wl_error,
        seconds=seconds,
        history=history,
    )
    if not report.reached:
        warnings.warn(
            f"render: requested accuracy {accuracy:.3g} not reached; estimated {total:.3g} after {it} refinements "
            f"({leaves.scene.num_facets} facets), stopped by {reason or 'the error budget'}. Raise max_facets / "
            "max_iterations or ask for less.",
            AccuracyWarning,
            stacklevel=3,
        )
    return Plan(scene, leaves.scene, leaves.user, K_final, g, grid, nodes, method, bounces, solver_tol, report)


def _select(leaves: _Leaves, est: Tensor, target: float, max_facets: int) -> Tensor | None:
    """Leaves to split: every leaf of the user facets that carry the excess error (largest estimates first, until
    the others alone would meet ``target``), as many as ``max_facets`` allows."""
    n = leaves.scene.num_facets
    user = leaves.user.cpu()
    count = torch.bincount(user, minlength=est.numel())
    if bool(torch.isinf(est).any()):  # not measured yet: every such facet
        chosen = torch.nonzero(torch.isinf(est)).reshape(-1).tolist()
    else:
        order = torch.argsort(est, descending=True).tolist()
        sq = est.square()
        total = float(sq.sum())
        limit = 0.8 * target * target * est.numel()
        chosen = []
        for i in order:  # the fewest facets without which the rest meets the target
            if total <= limit and chosen:
                break
            chosen.append(i)
            total -= float(sq[i])
    room = max_facets - n
    picked = []
    for i in chosen:  # each split adds three leaves per leaf
        if 3 * int(count[i]) <= room:
            picked.append(i)
            room -= 3 * int(count[i])
    if not picked:
        return None
    pick = torch.zeros(est.numel(), dtype=torch.bool)
    pick[picked] = True
    return pick[user].to(leaves.user.device)
