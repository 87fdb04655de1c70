"""Per-pixel shading by final gather: irradiance varies inside a facet, as in a path tracer's image.

For every primary hit point ``x`` of a view, ``E(x) = g0(x) S + Σ_j F(x → j) V(x, j) B_j`` with ``B = R E`` the
solved facets' radiosity, ``F(x → j)`` the exact point-to-polygon form factor (Lambert's contour formula, ``j``
clipped to the tangent plane of ``x``), ``V(x, j)`` the kernel-weighted visible fraction of ``j`` from ``x`` (Embree
rays to ``samples²`` jittered stratified points on ``j``, only for pairs a third facet could block) and ``g0(x) S``
the direct light at ``x`` itself (``S`` the light's spectrum): ``"uniform"`` ``g0 = 1``; a sun of direction ``d``
``max(0, n·(−d))`` times a shadow ray per sub-pixel ray; ``"sky"`` ``π (1 − Σ_j |F(x → j)| V(x, j))`` over every
facet, front or back; an area light (material name or mask) ``π Σ_{j ∈ light} F(x → j) V(x, j)``; a factor ``g [F]``
``g`` of the hit facet. The radiance is ``r(x) E(x) / π`` with ``r`` the hit facet's reflectance.

Sub-pixel rays (``s × s`` per pixel, as :func:`~torch_interreflect.camera.project`) are grouped into *fragments*
(pixel, hit facet): the gather is evaluated once per fragment, at the mean of its hit points, weighted by its share
of the pixel's rays. The geometry (the ``[fragments, facets]`` gather matrix, ``g0``, the coverage) is built once
per (scene, view, light) by :func:`gather_operator` and cached; the image is linear and differentiable in ``B`` and
``S`` (so in reflectance and illuminant through the solve).
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from .._checks import broadcast_shapes, check_count
from .._sparse import constant_product, sparse_matrix, to_csr
from ..errors import ShapeError
from ..geometry.raycast import RayCaster
from ..geometry.scene import Scene, area_average
from ..lights import sun_direction
from ..solver.api import solve
from .fragments import coarse_points, primary_fragments
from .image_terms import ImageGradient, edge_pixels, shadow_pixels
from .point_kernel import point_form_factors
from .sensor import Camera
from .view import View

__all__ = [
    "Gather",
    "gather_operator",
    "gathered_image",
    "gathered_radiance",
    "mix_direct",
    "source_irradiance",
]

#: Most operators kept by the cache of :func:`gather_operator`.
CACHE_SIZE = 8
_CACHE: OrderedDict[tuple, Gather] = OrderedDict()


def _light_key(light: Any) -> Any:
    if isinstance(light, str):
        return light
    t = torch.as_tensor(light).detach().cpu()
    return (str(t.dtype), tuple(t.shape), t.numpy().tobytes())


def _sun_of(light: Any, num_facets: int) -> Tensor | None:
    """The light as a unit sun direction ``[3]`` float64 (CPU, detached), or ``None`` when it is not a direction."""
    t = sun_direction(light, num_facets)
    if t is None:
        return None
    t = t.detach().cpu().to(torch.float64)
    return t / t.norm()


def _direct(scene: Scene, light: Any, frag: dict[str, Tensor], covered: Tensor | None,
            factors: Tensor | None) -> Tensor:
    """``g0`` per fragment (float64) for the light (see the module docstring)."""
    h = frag["facet"]
    if isinstance(light, str) and light == "uniform":
        return torch.ones(h.numel(), dtype=torch.float64)
    if isinstance(light, str) and light == "sky":
        return math.pi * (1.0 - covered).clamp_min(0.0)
    sc = scene.to(torch.float64).to("cpu")
    if isinstance(light, str):
        if scene.material_names is None or light not in scene.material_names:
            raise ValueError(
                f"light must be 'uniform', 'sky', a direction [3], a facet mask [F], a tensor [F] or a material name "
                f"of the scene {list(scene.material_names or [])}; got {light!r}"
            )
        light = (scene.material == scene.material_names.index(light)).cpu()
    t = torch.as_tensor(light).detach().cpu()
    F = scene.num_facets
    if t.dtype == torch.bool:
        if t.shape != (F,):
            raise ShapeError(f"an area-light mask must have shape [{F}] (one flag per facet); got {list(t.shape)}")
        return math.pi * torch.sparse.mm(factors, t.to(torch.float64)[:, None])[:, 0]
    d = _sun_of(light, F)
    if d is not None:
        ray_h = h[frag["ray_fragment"]]
        cos = (-(sc.normals[ray_h] @ d)).clamp_min(0)
        per_ray = cos * frag["ray_free"]  # the shadow flags of primary_fragments(sun=), kept for image_grad
        return area_average(per_ray[:, None], frag["ray_fragment"], torch.ones_like(per_ray), h.numel())[:, 0]
    if not t.is_floating_point() or t.shape != (F,):
        raise ShapeError(f"light as a tensor must be a direction [3], a mask [F = {F}] or a factor [F]; got "
                         f"{list(t.shape)} ({t.dtype})")
    return t.to(torch.float64)[h]


# ------------------------------------------------------------------------------------------- the operator
class Gather(nn.Module):
    """The geometry of a gathered view: built by :func:`gather_operator`, used by :func:`gathered_radiance`.

    ``K`` fragments (one per pixel and front-hit facet). Buffers are non-persistent (rebuild from the geometry).

    Attributes:
        pixel_fragments: Share of each pixel's sub-pixel rays in each fragment. Sparse CSR ``[H·W, K]``.
        coverage: The same per facet (what :func:`~torch_interreflect.camera.project` gives). Sparse CSR
            ``[H·W, F]``; with ``shading="flat"`` the image is ``coverage @ facet values``.
        fragment_facet: The facet of each fragment. ``[K]`` int64.
        gather: ``F(x_k → j) V(x_k, j)`` at each fragment's mean hit point. Sparse CSR ``[K, F]`` (``None`` when
            built for flat shading only).
        direct: ``g0`` of the light at each fragment (see the module docstring). ``[K]`` (``None`` likewise).
        open_sky: ``1 − Σ_j |F(x_k → j)| V(x_k, j)``, the cosine-weighted part of each fragment's hemisphere that
            sees no facet (``g0`` of a uniform sky is ``π`` times it). ``[K]`` (``None`` likewise).
        background: Fraction of each pixel that sees no facet. ``[H, W]``.
        fragment_pixel: The pixel (``row · W + column``) of each fragment. ``[K]`` int64.
        ray_direction: The direction of each sub-pixel ray that hits a facet's front (as :meth:`View.rays`).
            ``[R, 3]`` float64.
        ray_weight: Its share of its pixel (``1/s²``, or ``1/e²`` in an edge pixel). ``[R]`` float64.
        ray_fragment: The fragment of each of them. ``[R]`` int64.
        ray_free: For a sun: 1 where the ray's hit point sees the sun unblocked, else 0. ``[R]`` (else ``None``).
        kernel: With ``stride > 1``: the coarse gather points, ``(ray_point [R], facet [Kc], weights [K, Kc],
            factors [Kc, F])`` (:func:`~torch_interreflect.camera.fragments.coarse_points`); else ``None``.
        view: The :class:`~torch_interreflect.camera.View`; ``supersample``, ``edge_supersample``, ``samples``: the
            settings.
        info: ``pairs``, ``rays`` and ``seconds`` (per stage) of the build; ``edge_pixels``, the number of pixels
            given ``edge_supersample`` rays.
    """

    def __init__(self, view: View, frag: dict[str, Tensor], num_facets: int, dtype: torch.dtype,
                 device: torch.device, supersample: int, samples: int, edge_supersample: int | None = None) -> None:
        super().__init__()
        self.view, self.supersample, self.samples = view, int(supersample), int(samples)
        self.edge_supersample = None if edge_supersample is None else int(edge_supersample)
        self.height, self.width, self.num_facets = view.height, view.width, int(num_facets)
        K = frag["facet"].numel()
        p, w = frag["pixel"], frag["weight"]
        # fragments are sorted by (pixel, facet) and unique (torch.unique of pixel · F + facet)
        pf = sparse_matrix(p, torch.arange(K), w, (self.height * self.width, K), dtype, ordered=True)
        cov = sparse_matrix(p, frag["facet"], w, (self.height * self.width, self.num_facets), dtype, ordered=True)
        self.register_buffer("pixel_fragments", pf.to(device), persistent=False)
        self.register_buffer("coverage", cov.to(device), persistent=False)
        self.register_buffer("fragment_facet", frag["facet"].to(device), persistent=False)
        self.register_buffer("fragment_pixel", frag["pixel"].to(device), persistent=False)
        self.register_buffer("ray_direction", frag["ray_direction"].to(device), persistent=False)
        self.register_buffer("ray_weight", frag["ray_weight"].to(device), persistent=False)
        self.register_buffer("ray_fragment", frag["ray_fragment"].to(device), persistent=False)
        self.register_buffer("ray_free", None, persistent=False)
        self.kernel: tuple[Tensor, Tensor, Tensor, Tensor] | None = None
        self.register_buffer("background", frag["background"].to(device=device, dtype=dtype), persistent=False)
        self.register_buffer("gather", None, persistent=False)
        self.register_buffer("direct", None, persistent=False)
        self.register_buffer("open_sky", None, persistent=False)
        self.info: dict[str, Any] = {"edge_pixels": int(frag["edge_pixels"].numel())}
        self._operands: dict[tuple[str, torch.dtype, torch.device], tuple[Tensor, Tensor, Tensor]] = {}

    @property
    def num_fragments(self) -> int:
        return int(self.fragment_facet.numel())

    def _operand(self, name: str, like: Tensor) -> tuple[Tensor, Tensor]:
        """The sparse buffer ``name`` in ``like``'s dtype and device, and its CSR transpose, for products that take a
        gradient (:func:`gathered_radiance`). Built at the first such product and kept: a fit that renders one view
        many times (:func:`~torch_interreflect.training.refine_illuminant`) converts them once, where torch's
        backward would convert ``mᵀ`` to CSR at every call. They hold about the buffers' memory again; ``.to()``
        (and every other conversion of the module) drops them, and pickling leaves them out.
        """
        m = getattr(self, name)
        key = (name, like.dtype, like.device)
        hit = self._operands.get(key)
        if hit is None or hit[0] is not m:  # the dict is replaced, never changed in place: threads may share it
            moved = m.to(device=like.device, dtype=like.dtype)
            hit = (m, moved, to_csr(moved.t()))
            self._operands = {**{k: h for k, h in self._operands.items() if getattr(self, k[0]) is h[0]}, key: hit}
        return hit[1], hit[2]

    def _apply(self, fn: Any, recurse: bool = True) -> Gather:  # .to(), .cuda(), .float(), ...: new buffers
        self._operands = {}
        out = super()._apply(fn, recurse)
        self._operands = {}  # and what another thread kept of the old buffers meanwhile
        return out

    def __getstate__(self) -> dict[str, Any]:
        state = super().__getstate__()
        state["_operands"] = {}
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        super().__setstate__({**state, "_operands": {}})  # an operator pickled before the cache existed has none

    def _set_kernel(self, factors: Tensor, direct: Tensor, covered: Tensor) -> None:
        idx = factors.indices()
        g = sparse_matrix(idx[0], idx[1], factors.values(), tuple(factors.shape), self.background.dtype,
                    ordered=factors.is_coalesced())
        self.register_buffer("gather", g.to(self.background.device), persistent=False)
        self.register_buffer("direct", direct.to(self.background), persistent=False)
        self.register_buffer("open_sky", (1.0 - covered).clamp_min(0.0).to(self.background), persistent=False)

    def forward(self, reflectance: Tensor, irradiance: Tensor, spd: Tensor, camera: Camera | None = None,
                shading: str = "gather") -> Tensor:
        """:func:`gathered_image` (with a camera) or :func:`gathered_radiance` (without) of this operator."""
        if camera is None:
            return gathered_radiance(self, reflectance, irradiance, spd, shading=shading)
        return gathered_image(self, reflectance, irradiance, spd, camera, shading=shading)

    def extra_repr(self) -> str:
        return (f"height={self.height}, width={self.width}, facets={self.num_facets}, "
                f"fragments={self.num_fragments}, supersample={self.supersample}, "
                f"edge_supersample={self.edge_supersample}, samples={self.samples}")


def _cache_key(scene: Scene, view: View, light: Any, s: int, samples: int, seed: int) -> tuple:
    c = scene.corners.detach()
    finger = (scene.num_facets, float(c.double().sum()), float(c.double().square().sum()), str(scene.dtype),
              str(scene.device))
    return (id(scene), finger, view, _light_key(light), s, samples, seed)


def gather_operator(
    scene: Scene,
    view: View,
    light: str | Tensor | Sequence[float] = "uniform",
    *,
    supersample: int = 3,
    samples: int = 4,
    seed: int = 0,
    shading: str = "gather",
    stride: int = 1,
    cache: bool = True,
    edge_supersample: int | None = None,
) -> Gather:
    """Cast a view's rays once and build its gather operator (cached per scene, view, light and settings).

    Args:
        scene: The scene (the facets whose irradiance is solved: user facets or refined leaves).
        view: The :class:`~torch_interreflect.camera.View`.
        light: As for :func:`~torch_interreflect.lights.light_geometry`: ``"uniform"``, ``"sky"``, a direction
            ``[3]`` (the way the light travels), a material name or boolean mask ``[F]`` (area light), or a factor
            ``[F]`` (used per hit facet).
        supersample: Sub-pixel rays per pixel side (anti-aliasing; the direct sun is shadow-tested per ray).
        edge_supersample: ``e``, for ``e²`` rays at Sobol points (a net when ``e²`` is a power of two) in the
            pixels where the ``supersample`` rays see an edge: a change of plane or material, the background, a back
            face or a sun shadow between neighbouring rays, across pixel borders too
            (:func:`~torch_interreflect.camera.fragments.primary_fragments`). ``None`` (or ``≤ supersample``):
            uniform rays. On 4 generator scenes at 32 × 32 (18–33 % of the pixels by edges), ``supersample=2`` with
            ``e = 8`` was 0.4–0.7 % (relative RMS of the image) from ``e = 64`` (uniform 8 × 8 rays: 0.5–1.7 %,
            2 × 2: 3.4–9.0 %), in about 30 % less time than uniform 8 × 8 rays; 16: 0.1–0.2 %.
        samples: Visibility rays per side of a target facet for pairs a third facet could block.
        seed: Seed of the visibility jitter.
        shading: ``"gather"`` builds everything; ``"flat"`` only the coverage (no kernel, no light needed).
        stride: Evaluate the gather (and the sky's open part) at one point per ``stride × stride`` pixels and per
            facet, and interpolate bilinearly to the pixels on the same facet (about ``stride²`` times less work;
            the sun's shadow rays stay per sub-pixel ray). ``1``: at every pixel.
        cache: Reuse an operator built for the same arguments (the scene by identity and geometry).

    Returns:
        The :class:`Gather`, in the scene's dtype and device; ``info`` holds pairs, rays and seconds.

    Example:
        >>> import torch_interreflect as ti
        >>> from torch_interreflect.camera import View, gather_operator
        >>> scene = ti.scenes.v_groove(90.0, divisions=2)
        >>> view = View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=8, width=8)
        >>> op = gather_operator(scene, view, [0.0, 0.0, -1.0])  # a sun straight down
        >>> op.gather.shape, op.direct.shape == (op.num_fragments,)
        (torch.Size([81, 8]), True)
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene; got {type(scene).__name__}")
    if not isinstance(view, View):
        raise TypeError(f"view must be a torch_interreflect.camera.View; got {type(view).__name__}")
    if shading not in ("gather", "flat"):
        raise ValueError(f"shading must be 'gather' or 'flat'; got {shading!r}")
    check_count(supersample, "supersample")
    check_count(stride, "stride")
    check_count(edge_supersample, "edge_supersample", optional=True)
    edge = None if edge_supersample is None or int(edge_supersample) <= int(supersample) else int(edge_supersample)
    key = (*_cache_key(scene, view, light, int(supersample), int(samples), int(seed)), int(stride), edge)
    scene = scene.detach()  # ray casting and the kernel are constants of the geometry (see image_grad for its gradient)
    op = _CACHE.get(key) if cache else None
    if op is None:
        t0 = time.perf_counter()
        caster = RayCaster.of(scene.to(torch.float64).to("cpu"))
        frag = primary_fragments(scene, view, int(supersample), caster, edge_supersample=edge,
                                 sun=_sun_of(light, scene.num_facets))
        op = Gather(view, frag, scene.num_facets, scene.dtype, scene.device, int(supersample), int(samples), edge)
        op._frag, op._caster = frag, caster  # kept until the kernel is built
        op.info["seconds"] = {"primary": time.perf_counter() - t0}
    if shading == "gather" and op.gather is None:
        frag = op._frag
        if int(stride) == 1:
            factors, covered, info = point_form_factors(scene, frag["centre"], frag["facet"], samples=samples,
                                                        seed=seed, caster=op._caster)
        else:
            centres, facets, weights, ray_point = coarse_points(frag, view.height, view.width, scene.num_facets,
                                                                int(stride))
            factors, covered, info = point_form_factors(scene, centres, facets, samples=samples, seed=seed,
                                                        caster=op._caster)
            op.kernel = (ray_point, facets, weights, factors)
            factors = torch.sparse.mm(weights, factors).coalesce()
            covered = torch.sparse.mm(weights, covered[:, None])[:, 0]
            info["points"] = int(centres.shape[0])
        t0 = time.perf_counter()
        op._set_kernel(factors, _direct(scene, light, frag, covered, factors), covered)
        if "ray_free" in frag:
            op.register_buffer("ray_free", frag["ray_free"].to(op.background), persistent=False)
        op.info.update(pairs=info["pairs"], rays=info["rays"], points=info.get("points", op.num_fragments))
        op.info["seconds"].update(kernel=info["seconds"], direct=time.perf_counter() - t0)
        del op._frag, op._caster
    if cache:
        _CACHE[key] = op
        _CACHE.move_to_end(key)
        while len(_CACHE) > CACHE_SIZE:
            _CACHE.popitem(last=False)
    return op


# ------------------------------------------------------------------------------------------- images
def _columns(m: Tensor, x: Tensor, transposed: Tensor | None = None) -> Tensor:
    """``m [R, N] @ x [..., N, C]`` → ``[..., R, C]`` as one (sparse) matrix product over all columns; with
    ``transposed`` (``mᵀ`` in CSR, ``m`` already in ``x``'s dtype and device) the backward uses it."""
    lead, n, c = x.shape[:-2], x.shape[-2], x.shape[-1]
    cols = x.movedim(-2, 0).reshape(n, -1)
    out = m.to(device=x.device, dtype=x.dtype) @ cols if transposed is None else constant_product(m, transposed, cols)
    return out.reshape(m.shape[0], *lead, c).movedim(0, -2)


def _product(op: Gather, name: str, x: Tensor) -> Tensor:
    """``_columns`` of the operator's sparse buffer ``name``; when ``x`` takes a gradient, with the operator's kept
    transpose (:meth:`Gather._operand`) for the backward."""
    m = getattr(op, name)
    if not (torch.is_grad_enabled() and x.requires_grad) or m.layout != torch.sparse_csr or m.requires_grad:
        return _columns(m, x)
    moved, transposed = op._operand(name, x)
    return _columns(moved, x, transposed)


def _to_image(op: Gather, pixels: Tensor) -> Tensor:
    """``[..., H·W, C]`` → ``[..., C, H, W]``."""
    return pixels.movedim(-1, -2).reshape(*pixels.shape[:-2], pixels.shape[-1], op.height, op.width)


def _check_spectra(op: Gather, reflectance: Tensor, irradiance: Tensor) -> tuple[Tensor, Tensor]:
    r = reflectance if reflectance.ndim >= 2 else reflectance[:, None]
    if r.shape[-2] != op.num_facets or irradiance.ndim < 2 or irradiance.shape[-2] != op.num_facets:
        raise ShapeError(
            f"reflectance and irradiance must be [..., F, L] with F = {op.num_facets} (the operator's scene); got "
            f"{list(reflectance.shape)} and {list(irradiance.shape)}"
        )
    r, E = torch.broadcast_tensors(r, irradiance)
    return r, E


def gathered_radiance(op: Gather, reflectance: Tensor, irradiance: Tensor, spd: Tensor | None = None, *,
                      shading: str = "gather", direct: Tensor | None = None,
                      gradient: ImageGradient | None = None) -> Tensor:
    """Spectral radiance images ``r(x) E(x) / π`` of a view, per pixel (W·sr⁻¹·m⁻²·nm⁻¹).

    ``E(x) = g0(x) S + Σ_j G[x, j] B_j`` with ``B = R E`` the facets' radiosity (``shading="gather"``), or the
    hit facet's own ``E`` (``"flat"``). Linear in ``B`` and ``S``; differentiable in ``reflectance``,
    ``irradiance`` and ``spd``.

    Args:
        op: The view's :class:`Gather` (:func:`gather_operator`).
        reflectance: In [0, 1]. Shape ``[..., F, L]`` (or ``[F]`` grey).
        irradiance: The solved facet irradiance ``E`` (e.g. :func:`torch_interreflect.solve` with
            ``E0 = g ⊗ S``). Shape ``[..., F, L]``.
        spd: The light's spectrum ``S`` as given to the solve (irradiance of a sun, radiance of a sky or area
            light, the uniform irradiance). Shape ``[..., L]``. Needed for ``"gather"``.
        shading: ``"gather"`` or ``"flat"``.
        direct: ``g0`` per fragment in place of ``op.direct``, e.g. a mix of lights
            ``a · op.open_sky · π + (1 − a) · op.direct``. Shape ``[K]``.
        gradient: The :class:`~torch_interreflect.camera.image_terms.ImageGradient`
            (:func:`~torch_interreflect.camera.image_grad.image_gradient`) of the operator and a scene whose corners
            (or a sun direction) require grad: the image then passes gradients to them (values unchanged). With
            ``direct=`` its direct-light terms (the per-ray cosines and the sun's shadow edges) are left out.

    Returns:
        Radiance images. Shape ``[..., L, H, W]``.
    """
    if shading not in ("gather", "flat"):
        raise ValueError(f"shading must be 'gather' or 'flat'; got {shading!r}")
    r, E = _check_spectra(op, reflectance, irradiance)
    if shading == "flat":
        flat = _product(op, "coverage", r * E / math.pi)
        if gradient is not None:
            flat = flat + edge_pixels(gradient, None, r * E / math.pi, op.height * op.width)
        return _to_image(op, flat)
    if op.gather is None:
        raise ValueError("this operator was built with shading='flat'; build it with gather_operator(..., "
                         "shading='gather') to gather")
    if spd is None:
        raise ValueError("shading='gather' needs the light's spectrum spd [..., L] (the S of E0 = g ⊗ S)")
    S = torch.as_tensor(spd, dtype=E.dtype, device=E.device)
    if S.shape[-1] != E.shape[-1]:
        raise ShapeError(f"spd must be [..., L] with L = {E.shape[-1]}; got {list(S.shape)}")
    if direct is not None and direct.shape != (op.num_fragments,):
        raise ShapeError(f"direct must be [K] with K = {op.num_fragments} (one per fragment); got {list(direct.shape)}")
    own_direct = direct is None  # the operator's light: the gradient's direct-light terms apply to it
    direct = (op.direct if own_direct else direct).to(device=E.device, dtype=E.dtype)
    if own_direct and gradient is not None and gradient.direct is not None:
        direct = direct + gradient.direct.to(direct)
    e_frag = direct[:, None] * S[..., None, :] + _product(op, "gather", r * E)  # [..., K, L]
    if gradient is not None and gradient.gather is not None:
        moved = _columns(gradient.gather, r * E)
        e_frag = e_frag + (moved if gradient.weights is None else _columns(gradient.weights, moved))
    r_frag = r.index_select(-2, op.fragment_facet.to(E.device))
    r_frag, e_frag = torch.broadcast_tensors(r_frag, e_frag)
    values = r_frag * e_frag / math.pi
    pixels = _product(op, "pixel_fragments", values)
    if gradient is not None:
        pixels = pixels + edge_pixels(gradient, values, r * E / math.pi, op.height * op.width)
        if gradient.shadow_pixel.numel() and own_direct:
            pixels = pixels + shadow_pixels(gradient, r, S, op.height * op.width)
    return _to_image(op, pixels)


def gathered_image(op: Gather, reflectance: Tensor, irradiance: Tensor, spd: Tensor | None, camera: Camera, *,
                   shading: str = "gather", direct: Tensor | None = None,
                   gradient: ImageGradient | None = None) -> Tensor:
    """Linear camera RGB images of a view: :func:`gathered_radiance` through the camera's sensitivities.

    Arguments as for :func:`gathered_radiance` (``direct`` and ``gradient`` included), and ``camera`` (a
    :class:`~torch_interreflect.camera.Camera` whose grid has the ``L`` wavelengths). ``shading="gather"``
    (per-pixel final gather) or ``"flat"`` (one colour per facet).

    Returns:
        Camera RGB. Shape ``[..., C, H, W]`` (``[3, H, W]`` for unbatched inputs).

    Example:
        >>> import torch, torch_interreflect as ti
        >>> from torch_interreflect.camera import View, gather_operator, gathered_image
        >>> scene = ti.scenes.v_groove(90.0, divisions=2)
        >>> wl = ti.spectral.wavelengths(); cam = ti.Camera.from_colour("Nikon 5100 (NPL)", wl)
        >>> op = gather_operator(scene, View((0.03, 0.03, 0.1), (0.03, 0.03, 0.0), (0, 1, 0), height=8, width=8))
        >>> r = torch.full((8, 31), 0.5); S = torch.ones(31)
        >>> E = ti.solve(ti.form_factors(scene), r, S.expand(8, 31))
        >>> gathered_image(op, r, E, S, cam).shape
        torch.Size([3, 8, 8])
    """
    rad = gathered_radiance(op, reflectance, irradiance, spd, shading=shading, direct=direct,
                            gradient=gradient)  # [..., L, H, W]
    rgb = camera(rad.movedim(-3, -1))  # [..., H, W, C]
    return rgb.movedim(-1, -3)


def source_irradiance(form_factors: Any, reflectance: Tensor, E0: Tensor, bounces: int | None = None,
                      **solve_kwargs: Any) -> Tensor:
    """The facet irradiance an ``n``-bounce image gathers from: the gather adds the last bounce, so it is the
    ``(n − 1)``-bounce solution (zero for ``n = 1``: direct light only), and the full solution for ``None``.

    Args:
        form_factors, reflectance, E0, solve_kwargs: As for :func:`torch_interreflect.solve`.
        bounces: ``None`` (infinite) or ``n ≥ 1``.

    Returns:
        ``E`` in W·m⁻²·nm⁻¹. Shape that of ``solve``'s output ``[..., F, L]``.
    """
    if bounces == 1:
        return torch.zeros(broadcast_shapes(reflectance.shape, E0.shape), dtype=E0.dtype, device=E0.device)
    return solve(form_factors, reflectance, E0, bounces=None if bounces is None else bounces - 1, **solve_kwargs)


def mix_direct(op: Gather, ambient_weight: float, sky: bool) -> Tensor:
    """``g0`` per fragment ``[K]`` of the generator's light mix: ``a · ambient + (1 − a) · op.direct`` with the
    ambient part uniform (1) or the sky's open part at the fragment (``op.open_sky``), as ``g = a g_ambient +
    (1 − a) g_sun`` per facet; ``op`` built with the sun's direction."""
    if op.direct is None or op.open_sky is None:
        raise ValueError("mix_direct needs an operator built with shading='gather'")
    ambient = op.open_sky if sky else torch.ones_like(op.direct)
    return ambient_weight * ambient + (1.0 - ambient_weight) * op.direct
